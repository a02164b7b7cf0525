"""Bad input that reached a traceback, a hang or a gigabyte before 2026-12-05, each answered now in one line with
exit status 2, leaving nothing behind: output paths that cannot be written (every verb that writes one), eval's
seed and step cap past what the store holds, `serve` on a port it cannot have, a store with a corrupt block, a
locked store (said while waiting, not after minutes of silence), and `sql --max-rows` holding only its rows."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pipeline.cli import main
from store import Store, StoreError
from store.db import HEADER_BYTES, LOCK_NOTICE_AFTER_S
from tests.conftest import ROOT

STARTER = ROOT / "games" / "scaffolds" / "pong.py"


def _run(capsys, *argv) -> tuple[int, str, str]:
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def _one_line_error(code: int, err: str) -> str:
    """The error line of a refused command: exit 2, no traceback."""
    assert code == 2 and "Traceback" not in err, err
    return err.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def played(tmp_path_factory) -> Path:
    """A store holding one short Pong evaluation."""
    path = tmp_path_factory.mktemp("played") / "s.duckdb"
    assert main(["eval", str(STARTER), "--episodes", "1", "--max-steps", "30", "--store", str(path)]) == 0
    return path


def test_an_output_path_that_cannot_be_written_is_one_line_and_leaves_nothing(played, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    a_dir = tmp_path / "a_dir"
    a_dir.mkdir()
    under_a_file = a_file / "sub"
    cases = [
        ("report", "last", "--out", under_a_file, "--store", played),
        ("compare", STARTER, STARTER, "--episodes", "1", "--max-steps", "5", "--out", under_a_file, "--store", played),
        ("view", "last", "--save", a_file / "x.rrd", "--store", played),
        ("view", "last", "--save", a_dir, "--store", played),
        ("new", under_a_file / "policy.py", "--game", "pong"),
        ("eval", STARTER, "--episodes", "1", "--max-steps", "5", "--rerun", under_a_file, "--store", played),
    ]
    runs_before = Store(played).query("SELECT count(*) FROM runs")[0][0]
    for argv in cases:
        line = _one_line_error(*_run(capsys, *argv)[::2])
        assert "give another path" in line and ("a_file" in line or "a_dir" in line), (argv, line)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_dir", "a_file"] and not list(a_dir.iterdir())
    assert Store(played).query("SELECT count(*) FROM runs")[0][0] == runs_before, "no run was started"
    # the check that the path can be written leaves no empty file where the command then fails for another reason
    code, _, err = _run(capsys, "view", "no-such-run", "--save", tmp_path / "y.rrd", "--store", played)
    assert code == 2 and not (tmp_path / "y.rrd").exists(), err


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full (a device whose every write fails: disk full)")
def test_a_recording_on_a_full_disk_is_one_line_naming_the_file(played, capsys):
    """Rerun's own RuntimeError ('Failed to write: No space left on device (os error 28)') was the traceback."""
    import stat

    line = _one_line_error(*_run(capsys, "view", "last", "--save", "/dev/full", "--store", played)[::2])
    assert "/dev/full: No space left on device; give another path" in line, line
    # a recording is written whole under a partial name, then renamed: never over what is not a plain file (as
    # root, /dev/full.partial was made and renamed over the device)
    assert stat.S_ISCHR(os.stat("/dev/full").st_mode) and not os.path.lexists("/dev/full.partial")


@pytest.mark.parametrize("flag, value", [("--seed", -1), ("--seed", 10**23), ("--max-steps", 10**23),
                                         ("--max-steps", 2**31), ("--call-time-limit", "nan"),
                                         ("--call-time-limit", "inf"), ("--call-time-limit", "-1"),
                                         ("--episode-time-limit", "0"), ("--episode-time-limit", "-inf"),
                                         ("--episodes", 99_999_999_999), ("--episodes", 0)])
def test_eval_refuses_a_seed_or_a_cap_the_store_cannot_hold_before_it_starts_a_run(tmp_path, capsys, flag, value):
    path = tmp_path / "s.duckdb"
    line = _one_line_error(*_run(capsys, "eval", STARTER, "--episodes", "1", flag, value, "--store", path)[::2])
    assert flag in line, line
    assert not path.exists() or Store(path).query("SELECT count(*) FROM runs")[0][0] == 0


@pytest.mark.parametrize("flag, value", [("--temperature", "-1"), ("--temperature", "5"),
                                         ("--iterations", 10**11)])
def test_optimize_refuses_a_temperature_or_iterations_out_of_range_before_it_starts_a_run(tmp_path, capsys, flag,
                                                                                        value):
    """A temperature of -1 or 5 ran the loop (providers take 0-2); 10^11 iterations made a run whose planned count
    the views could not read (shown as '?'). Refused by the parser, in its words, as every flag out of range is
    (it said "codearcade: error: --temperature must be ..." where --sticky said "codearcade eval: argument ...")."""
    path = tmp_path / "s.duckdb"
    line = _one_line_error(*_run(capsys, "optimize", "--game", "pong", flag, value, "--store", path)[::2])
    assert line.startswith(f"codearcade optimize: argument {flag}: must be within"), line
    assert not path.exists() or Store(path).query("SELECT count(*) FROM runs")[0][0] == 0


def test_serve_refuses_a_port_out_of_range_or_taken_before_it_makes_a_run(tmp_path, capsys):
    path = tmp_path / "s.duckdb"
    for port in ("-1", "65536", "http"):
        code, _, err = _run(capsys, "serve", "--game", "pong", "--port", port, "--store", path)
        assert code == 2 and "a port number is 0-65535" in err, err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for flag in ("--port", "--mcp-port"):
            line = _one_line_error(*_run(capsys, "serve", "--game", "pong", flag, port, "--store", path)[::2])
            assert f"{flag} {port}" in line and "give another port" in line, line
    assert not path.exists(), "no serve run was made for a server that could not start"


def test_serve_refuses_a_limit_a_workspace_or_a_recording_it_cannot_use_before_it_makes_a_run(tmp_path, capsys):
    """A nan call limit answered every submit with a 500 (a negative one forfeited every episode); a missing
    workspace refused every submission by path later; a --rerun it cannot write left a junk run behind."""
    path = tmp_path / "s.duckdb"
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    cases = [(("--call-time-limit", "nan"), "--call-time-limit: must be a finite number"),
             (("--call-time-limit", "-1"), "--call-time-limit: must be within [0, "),
             (("--workspace", tmp_path / "none"), "no such directory"),
             (("--workspace", a_file), "not a directory"),
             (("--rerun", a_file / "sub"), "a_file")]
    for flags, said in cases:
        line = _one_line_error(*_run(capsys, "serve", "--game", "pong", "--port", "0", *flags, "--store", path)[::2])
        assert said in line, (flags, line)
    assert not path.exists(), "no serve run was made for a server that could not start"


@pytest.mark.parametrize("where", ["header", "first block", "steps"])
def test_a_store_with_a_corrupt_block_is_one_line_everywhere_and_a_finding_for_the_doctor(played, tmp_path, capsys,
                                                                                         where):
    path = tmp_path / "s.duckdb"
    data = bytearray(played.read_bytes())
    if where == "steps":  # a block of the steps table's data, where DuckDB placed it
        size, block = Store(played).query("SELECT (SELECT block_size FROM pragma_database_size() WHERE database_name = current_database()), "
                                          "min(block_id) "
                                          "FROM pragma_storage_info('steps') WHERE persistent AND block_id >= 0")[0]
        at = HEADER_BYTES + block * size
    else:
        at = {"header": 4096, "first block": HEADER_BYTES}[where]
    data[at:at + 512] = os.urandom(512)
    path.write_bytes(bytes(data))
    damaged = 0
    for argv in (("runs",), ("sql", "SELECT count(DISTINCT step || episode_id) FROM steps"), ("report", "last")):
        code, out, err = _run(capsys, *argv, "--store", path)
        if code == 0:  # the damage is in a block this command does not read
            continue
        line = _one_line_error(code, err)
        assert "damaged" in line and "codearcade doctor" in line, line
        damaged += 1
    if where == "steps":  # a write that appends to the damaged table: the damage is met by its checkpoint, which
        # ended eval with DuckDB's "Detached database ..., but CHECKPOINT during DETACH failed" and no score
        code, out, err = _run(capsys, "eval", STARTER, "--episodes", "1", "--max-steps", "20", "--store", path)
        line = _one_line_error(code, err)
        assert "damaged: a block is corrupt" in line and "s.duckdb.wal" in line and "codearcade doctor" in line, line
    code, out, err = _run(capsys, "doctor", "--store", path)
    assert code == 1 and "Traceback" not in out + err and "corrupt" in (out + err).lower(), out + err
    assert damaged, "every case breaks a block that some command reads"


def test_a_locked_store_is_said_while_the_command_waits(played, tmp_path, capfd):
    """Another process holds the file: a writer waits for it (a run must not fail for someone's long query), and
    says so after LOCK_NOTICE_AFTER_S rather than staying silent for up to ten minutes."""
    path = tmp_path / "s.duckdb"
    path.write_bytes(played.read_bytes())
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import duckdb, sys, time
        con = duckdb.connect({str(path)!r})
        print("held", flush=True)
        time.sleep(60)
    """)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        store = Store(path, lock_timeout_s=LOCK_NOTICE_AFTER_S + 1.5, write_lock_timeout_s=LOCK_NOTICE_AFTER_S + 1.5)
        began = time.monotonic()
        with pytest.raises(StoreError, match="stayed locked by another process"):
            with store.write():
                pass
        waited = time.monotonic() - began
    finally:
        holder.kill()
        holder.wait()
    err = capfd.readouterr().err
    assert waited >= LOCK_NOTICE_AFTER_S and err.count("is locked by another process") == 1, err
    assert f"PID {holder.pid}" in err and "waiting up to" in err, err


def test_sql_max_rows_holds_only_the_rows_it_shows(played, capsys):
    """`--max-rows 3` of three million rows: their count is said, and the query's rows are not held (peak memory of
    the same query kept whole, in the same kind of process, as the baseline)."""
    code, out, _ = _run(capsys, "sql", "SELECT range AS n FROM range(3000000)", "--max-rows", "3", "--store", played)
    assert code == 0 and "(3000000 rows, 2999997 not shown" in out, out

    def peak_mb(keep: int | None) -> float:
        script = textwrap.dedent(f"""
            from store import Store
            from store.views import run_user_query
            result = run_user_query(Store({str(played)!r}), "SELECT range AS n FROM range(3000000)", [], {keep!r})
            assert (result.total or len(result.rows)) == 3000000
            # VmHWM, this process's own peak (getrusage's counts a forking parent's too, carried across exec)
            print(next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")))
        """)
        done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300,
                              env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
        assert done.returncode == 0, done.stderr
        return float(done.stdout.split()[-1]) / 1024

    shown, whole = peak_mb(3), peak_mb(None)
    assert whole - shown > 100, (shown, whole)  # 3M rows held: ~200 MB here


def test_the_doctor_says_an_empty_duckdb_file_is_no_store_and_leaves_it_as_it_was(tmp_path, capsys):
    import duckdb

    path = tmp_path / "other.duckdb"
    duckdb.connect(str(path)).close()
    before = path.read_bytes()
    code, out, err = _run(capsys, "doctor", "--store", path)
    assert code == 1 and "Traceback" not in out + err and "not a codearcade store" in out, out + err
    assert path.read_bytes() == before


def test_a_batch_naming_a_missing_policy_file_is_refused_before_any_run(tmp_path, capsys):
    batch = tmp_path / "b.toml"
    batch.write_text(f'name = "t"\nstore = "{tmp_path / "s.duckdb"}"\n[defaults]\ngame = "pong"\npolicy = "nope.py"\n'
                     '[matrix]\nseed = [0, 1]\n')
    for dry in ((), ("--dry-run",)):
        line = _one_line_error(*_run(capsys, "batch", batch, *dry)[::2])
        assert "nope.py does not exist" in line, line
    assert not (tmp_path / "s.duckdb").exists()


@pytest.mark.parametrize("text, said", [("def broken(:\n", "syntax error"), ("x = 1\n", "Policy"),
                                        (None, "no trainable methods")])
def test_a_batch_naming_a_policy_that_cannot_start_a_run_is_refused_before_any_run(tmp_path, capsys, text, said):
    """It passed --dry-run; the run then failed on starting, and rerunning the batch (its way to resume) could
    never mend it."""
    policy = tmp_path / "p.py"
    policy.write_text(text if text is not None else STARTER.read_text().replace("trainable=True", "trainable=False"))
    batch = tmp_path / "b.toml"
    batch.write_text(f'name = "t"\nstore = "{tmp_path / "s.duckdb"}"\n[defaults]\npolicy = "p.py"\n'
                     '[matrix]\nseed = [0, 1]\n')
    for dry in ((), ("--dry-run",)):
        line = _one_line_error(*_run(capsys, "batch", batch, *dry)[::2])
        assert "b.toml: p.py" in line and said in line, line
    assert not (tmp_path / "s.duckdb").exists()


def test_a_batch_log_that_takes_no_appending_is_one_line(tmp_path, capsys):
    batch = tmp_path / "b.toml"
    batch.write_text(f'name = "t"\nstore = "{tmp_path / "s.duckdb"}"\n[defaults]\ngame = "pong"\n'
                     '[matrix]\nseed = [0]\n')
    line = _one_line_error(*_run(capsys, "batch", batch, "--log", "/proc/version")[::2])
    assert "--log /proc/version: Invalid argument; give another path" in line, line


@pytest.mark.parametrize("dry_run", [True, False])
def test_a_batch_whose_store_folder_is_missing_says_so_dry_run_or_not(tmp_path, capsys, dry_run):
    """An experiment file's store in a folder that does not exist: --dry-run said "1 runs into ..." and exit 0, and
    the real run blamed a --log the person never gave. Both now name the store's folder, and make nothing."""
    batch = tmp_path / "b.toml"
    batch.write_text(f'name = "t"\nstore = "{tmp_path / "nodir" / "s.duckdb"}"\n[defaults]\ngame = "pong"\n'
                     '[matrix]\nseed = [0]\n')
    line = _one_line_error(*_run(capsys, "batch", batch, *(["--dry-run"] if dry_run else []))[::2])
    assert f"directory {tmp_path / 'nodir'} does not exist" in line and "--log" not in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.toml"]


def test_an_emptied_migration_table_is_damage_for_every_command_and_the_doctor(played, tmp_path, capsys):
    """Its tables there but schema_migrations emptied: the commands tried to create the first migration's tables
    again (a traceback) and the doctor said ok."""
    import duckdb

    path = tmp_path / "s.duckdb"
    path.write_bytes(played.read_bytes())
    con = duckdb.connect(str(path))
    con.execute("DELETE FROM schema_migrations")
    con.close()
    for argv in (("runs",), ("eval", STARTER, "--episodes", "1", "--max-steps", "5")):
        line = _one_line_error(*_run(capsys, *argv, "--store", path)[::2])
        assert "is damaged: schema_migrations lists version 0" in line, line
    code, out, err = _run(capsys, "doctor", "--store", path)
    assert code == 1 and "PROBLEM: schema_migrations" in out and "Traceback" not in out + err, out + err
    code, out, err = _run(capsys, "doctor", "--store", played)
    assert code == 0 and "ok: no damage found" in out, out + err


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf", "1e308", "86401", "abc"])
def test_export_names_its_timeout_flag_when_the_value_is_no_time(played, capsys, value):
    """``--timeout 1e308`` reached the OTLP exporter, which failed with "timestamp out of range for platform
    time_t"; ``abc`` was argparse's own "invalid positive_seconds value"."""
    code, _, err = _run(capsys, "export", "last", "--timeout", value, "--store", played)
    assert code == 2 and ("--timeout: must be a number of seconds above 0 and at most 86400" in err or
                          "--timeout: give a number of seconds, got 'abc'" in err), err


@pytest.mark.parametrize("statement, named", [("INSTALL httpfs", "INSTALL"), ("load httpfs", "LOAD"),
                                              ("  DELETE FROM runs", "DELETE"), ("-- a note\nDROP TABLE runs", "DROP")])
def test_sql_refuses_a_statement_by_the_name_it_was_written_with(played, capsys, statement, named):
    line = _one_line_error(*_run(capsys, "sql", statement, "--store", played)[::2])
    assert f"read-only: {named} statements are refused" in line, line


def test_the_doctor_names_a_column_a_table_lost(played, tmp_path, capsys):
    """The columns each table must have are DuckDB's own answer for the store's migrations applied to an empty
    database; a store edited by hand (a dropped column) was 'a check that could not run'."""
    import duckdb

    path = tmp_path / "s.duckdb"
    path.write_bytes(played.read_bytes())
    con = duckdb.connect(str(path))
    con.execute("ALTER TABLE episodes DROP COLUMN env_s")
    con.close()
    code, out, err = _run(capsys, "doctor", "--store", path)
    assert code == 1 and "PROBLEM: columns missing: 1 — episodes.env_s" in out, out + err


def test_sql_says_a_select_that_writes_is_refused_and_changes_nothing(played, capsys):
    runs = Store(played).query("SELECT count(*) FROM runs")[0][0]
    line = _one_line_error(*_run(capsys, "sql", "WITH gone AS (DELETE FROM runs RETURNING *) SELECT * FROM gone",
                                 "--store", played)[::2])
    assert "read-only: the query writes to the store" in line, line
    assert Store(played).query("SELECT count(*) FROM runs")[0][0] == runs


@pytest.mark.parametrize("table, column", [("episodes", "return"), ("runs", "status"), ("steps", "reward")])
def test_a_column_dropped_by_hand_is_named_by_every_command_that_reads_it(played, tmp_path, capsys, table, column):
    """Before, each command but the doctor stopped on DuckDB's binder error (a traceback). The doctor's column
    check runs once the error is seen: what the query missed is named, and the doctor pointed to."""
    import duckdb

    path = tmp_path / "s.duckdb"
    path.write_bytes(played.read_bytes())
    con = duckdb.connect(str(path))
    con.execute(f'ALTER TABLE {table} DROP COLUMN "{column}"')
    con.close()
    failed = 0
    for argv in (("runs",), ("report", "last", "--out", tmp_path / "r.html"),
                 ("eval", STARTER, "--episodes", "1", "--max-steps", "5")):
        code, _, err = _run(capsys, *argv, "--store", path)
        if code == 0:  # a command that never reads the column has nothing to say
            continue
        failed += 1
        line = _one_line_error(code, err)
        assert f"the store lacks columns its schema made ({table}.{column})" in line, line
        assert "`codearcade doctor`" in line, line
    assert failed, "no command read the dropped column"


def test_a_query_naming_a_column_that_never_was_is_the_query_s_error_not_damage(played, capsys):
    code, _, err = _run(capsys, "sql", "SELECT no_such_column FROM runs", "--store", played)
    assert code != 0 and "no_such_column" in err and "lacks columns" not in err, err


def test_a_dry_run_of_a_starting_policy_that_forfeits_says_so(tmp_path, capsys):
    """It was a TypeError (a forfeit has no score to format)."""
    policy = tmp_path / "raises.py"
    policy.write_text(STARTER.read_text().replace("        predicted_ball_y = self.predict_ball_trajectory(obs)",
                                                  "        raise RuntimeError('boom')"))
    flags = ("--dry-run", "--eval-max-steps", "50", "--rollout-steps", "50", "--store", tmp_path / "s.duckdb")
    code, out, err = _run(capsys, "optimize", policy, *flags)
    assert code == 0 and "starting policy forfeited (" in out and "RuntimeError" in out, out + err
    code, out, err = _run(capsys, "optimize", policy, *flags, "--json")
    report = json.loads(out)
    assert code == 0 and report["starter_score"] is None and "RuntimeError" in report["starter_forfeit"], report


def test_a_model_whose_server_is_implied_is_checked_before_the_run_starts(tmp_path, capsys, monkeypatch):
    """`--model ollama_chat/NAME` alone calls litellm's default server (or $OLLAMA_API_BASE): with none there it
    played iteration 0 and then failed on a refused connection; hosted_vllm/NAME without a URL the same."""
    with socket.socket() as free:  # a port nothing listens on
        free.bind(("127.0.0.1", 0))
        closed = free.getsockname()[1]
    monkeypatch.setenv("OLLAMA_API_BASE", f"http://127.0.0.1:{closed}")
    monkeypatch.delenv("HOSTED_VLLM_API_BASE", raising=False)
    path = tmp_path / "s.duckdb"
    for model, said in (("ollama_chat/llama3", f"$OLLAMA_API_BASE (the server of --model ollama_chat/llama3) "
                                               f"http://127.0.0.1:{closed} cannot be reached"),
                        ("ollama/llama3", "cannot be reached (connection refused"),
                        ("hosted_vllm/x", "--model hosted_vllm/x needs its server's URL: give --api-base URL")):
        line = _one_line_error(*_run(capsys, "optimize", "--game", "pong", "--model", model, "--iterations", "1",
                                     "--store", path)[::2])
        assert said in line, (model, line)
    assert not path.exists(), "no run was made"


@pytest.mark.parametrize("url", ["http://[::1", "http://localhost:99999", "ftp://host:4318", "localhost:4318"])
def test_export_names_a_receiver_url_it_cannot_use(played, capsys, url):
    """A broken IPv6 literal or port was urllib's bare 'Invalid IPv6 URL' / 'Port out of range'."""
    line = _one_line_error(*_run(capsys, "export", "last", "--otlp", url, "--store", played)[::2])
    assert f"--otlp {url!r} is not an http(s) URL; give the receiver's address" in line, line


def test_an_empty_resume_is_an_error_not_a_new_run(tmp_path, capsys):
    path = tmp_path / "s.duckdb"
    line = _one_line_error(*_run(capsys, "optimize", "--resume", "", "--game", "pong", "--store", path)[::2])
    assert "--resume: give the run to continue" in line, line
    assert not path.exists()


@pytest.mark.parametrize("filler", ["0\n", "0,\n", "# a comment\n"])
def test_a_policy_file_past_the_largest_a_policy_holds_is_one_line_before_anything_parses_it(tmp_path, capsys,
                                                                                             filler):
    """A megabyte of statements after the starter held ~820 MB in `eval`'s own process (parsed there after its
    worker vetted it) and ~1.1 GB in `optimize`'s: refused at MAX_POLICY_CHARS, read no further than that, and
    nothing is stored. Just under the limit still plays."""
    from tracing.policy_file import MAX_POLICY_CHARS

    base = STARTER.read_text()
    big = tmp_path / "big.py"
    big.write_text(base + filler * (MAX_POLICY_CHARS // len(filler) + 1))
    store = tmp_path / "s.duckdb"
    for verb in (["eval", big, "--max-steps", "30"], ["optimize", big, "--dry-run"]):
        line = _one_line_error(*_run(capsys, *verb, "--store", store)[:3:2])
        assert f"longer than {MAX_POLICY_CHARS:,} characters" in line, line
    assert not store.exists() or not Store(store).query("SELECT count(*) FROM runs")[0][0]
    fits = tmp_path / "fits.py"
    fits.write_text(base + "# x\n" * ((MAX_POLICY_CHARS - len(base)) // 4 - 10))
    assert main(["eval", str(fits), "--max-steps", "30", "--store", str(store)]) == 0


def test_new_from_a_script_of_many_statements_reads_it_in_one_pass(tmp_path, capsys):
    """`new --from SCRIPT` split the whole script again for each top-level statement (ast.get_source_segment):
    20,000 of them took 47 s. Counted by what it asks of the splitter: the text split once."""
    import ast

    script = tmp_path / "script.py"
    script.write_text('GAME = "pong"\nimport tracing as trace\nimport math\nclass Policy(trace.Module):\n'
                      '    def select_action(self, obs):\n        return 0\n' + "0\n" * 20_000)
    splits = []
    original = ast._splitlines_no_ff

    def counted(*args, **kwargs):
        splits.append(1)
        return original(*args, **kwargs)

    ast._splitlines_no_ff = counted
    try:
        code, out, err = _run(capsys, "new", tmp_path / "policy.py", "--from", script)
    finally:
        ast._splitlines_no_ff = original
    assert code == 0, err
    assert len(splits) <= 1, f"the script was split {len(splits)} times"
    assert "import math" in (tmp_path / "policy.py").read_text()
    script.write_text(script.read_text() + "0\n" * 100_000)  # past MAX_POLICY_CHARS: said of a script
    line = _one_line_error(*_run(capsys, "new", tmp_path / "other.py", "--from", script)[::2])
    assert f"script '{script}' is longer than 200,000 characters" in line and "a file of their own" in line, line


@pytest.mark.parametrize("saved", ["crlf", "cr", "bom", "bom+crlf"])
def test_a_policy_file_saved_on_windows_plays_as_the_same_version(tmp_path, capsys, saved):
    """A policy file with ``\\r\\n`` line ends (or old Mac ``\\r``, or a UTF-8 byte-order mark, as Notepad writes)
    is a file Python runs: it was refused as "the static check of the code crashed (unexpected indent)", since
    a method's source cut from it could not be dedented. It now plays, as the very version its ``\\n`` copy is."""
    source = (ROOT / "games" / "scaffolds" / "pong.py").read_text()
    text = source.replace("\n", "\r\n" if "crlf" in saved else "\r" if saved == "cr" else "\n")
    path = tmp_path / "windows.py"
    path.write_bytes((b"\xef\xbb\xbf" if "bom" in saved else b"") + text.encode())
    (tmp_path / "unix.py").write_text(source)
    store = str(tmp_path / "s.duckdb")
    for played in (path, tmp_path / "unix.py"):
        assert main(["eval", str(played), "--max-steps", "5", "--store", store]) == 0, capsys.readouterr().err
    versions = Store(Path(store)).query("SELECT DISTINCT policy_version_id FROM episodes")
    assert len(versions) == 1, versions


@pytest.mark.parametrize("verb", [("runs",), ("sql", "SELECT 1"), ("eval", str(STARTER), "--max-steps", "5")])
def test_a_directory_given_as_the_store_is_named_as_one(tmp_path, capsys, verb):
    """``--store DIR`` was DuckDB's raw 'IO Error: Could not read from file ...: Is a directory'; it now says what
    to give, and leaves the directory as it was."""
    line = _one_line_error(*_run(capsys, *verb, "--store", tmp_path)[::2])
    assert f"{tmp_path} is a directory, not a store file; give a file, e.g. --store {tmp_path}/codearcade.duckdb" \
        in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    [b"eval", b"pol\xff.py"], [b"sql", b"SELECT '\xff'"], [b"runs", b"--game", b"\xff"], [b"blame", b"\xff"],
    [b"new", b"new\xff.py", b"--game", b"pong"], [b"runs", b"--store", b"st\xff.duckdb"]],
    ids=["eval", "sql", "runs", "blame", "new", "store"])
def test_an_argument_that_is_not_utf8_is_refused_in_one_line(argv, tmp_path):
    """Bytes on the command line that are not UTF-8 reached DuckDB (ConversionException, InvalidInputException),
    sqlglot (TypeError) and file names (`new` wrote 'new\\ufffd.py' instead), as tracebacks. Each is now refused
    at parsing, in one line that shows the byte, before anything is made."""
    exe = os.path.join(os.path.dirname(sys.executable), "codearcade").encode()
    store = os.fsencode(tmp_path / "s.duckdb")
    extra = [] if b"--store" in argv else [b"--store", store]
    done = subprocess.run([exe, *argv, *extra], cwd=tmp_path, capture_output=True, timeout=120)
    err = done.stderr.decode("utf-8", "replace")
    assert done.returncode == 2 and "Traceback" not in err, err[-2000:]
    assert len(err.strip().splitlines()) == 1 and "is not UTF-8 text" in err and "\\xff" in err, err
    assert sorted(os.listdir(tmp_path)) == [], "nothing was made"


def test_the_doctor_says_how_each_kind_of_interrupted_run_goes_on(played, tmp_path, capsys):
    """The doctor told every run left 'running' by a killed process to "finish with --resume", though only an
    optimization is resumed that way (`optimize --resume` refuses an evaluation) and a served run by `serve
    --resume`. Each kind is named with what to do."""
    import duckdb
    import shutil

    path = tmp_path / "s.duckdb"
    shutil.copy(played, path)
    with duckdb.connect(str(path)) as con:
        (run_id,) = con.execute("SELECT run_id FROM runs").fetchone()
        con.execute("UPDATE runs SET status = 'running'")
        for kind in ("optimize", "serve"):
            con.execute(f"INSERT INTO runs BY NAME SELECT * REPLACE ('{kind}{run_id[len(kind):]}' AS run_id, "
                        f"'{kind}' AS kind) FROM runs WHERE run_id = ?", [run_id])
    capsys.readouterr()
    main(["doctor", "--store", str(path)])
    out = capsys.readouterr().out
    said = {line for line in out.splitlines() if "runs interrupted" in line}
    assert any("codearcade optimize --resume RUN" in line for line in said), out
    assert any("codearcade serve --resume RUN" in line for line in said), out
    assert any("evaluate the policy again" in line for line in said), out
    assert "finish with --resume)" not in out


@pytest.mark.parametrize("argv, said", [
    (["compare", STARTER, STARTER, "--audit", "--seed", "5"], "--audit draws sealed seeds for each side"),
    (["serve", "--game", "pong", "--mcp", "--mcp-port", "5"], "not allowed with argument --mcp"),
    (["batch", ROOT / "examples" / "benchmarks.toml", "--address", "ray://10.0.0.1:10001"],
     "--address is a Ray cluster's: it goes with --executor ray"),
], ids=["compare --audit --seed", "serve --mcp --mcp-port", "batch --address without ray"])
def test_options_that_cannot_go_together_are_refused_before_anything_plays(argv, said, tmp_path, capsys):
    """Given together, one of the two was silently left out (compare's --seed under --audit, serve's stdio MCP
    beside --mcp-port)."""
    path = tmp_path / "s.duckdb"
    code, _, err = _run(capsys, *argv, "--store", path)
    assert code == 2 and said in err and len(err.strip().splitlines()) == 1, err
    assert not path.exists()


@pytest.mark.parametrize("argv, said", [
    (["eval", STARTER, "--max-steps", "20", "--store", ""], "--store: an empty path"),
    (["runs", "--store", " "], "--store: an empty path"),
    (["eval", "", "--max-steps", "20"], "path is empty"),
    (["optimize", "--game", "pong", "--model", "", "--iterations", "0"], "--model is empty"),
    (["optimize", "--game", "pong", "--api-base", "", "--iterations", "0"], "--api-base is empty"),
    (["optimize", "--game", "pong", "--rng-key", " ", "--iterations", "0"], "--rng-key is empty"),
], ids=["eval --store ''", "runs --store ' '", "eval ''", "--model ''", "--api-base ''", "--rng-key ' '"])
def test_an_empty_value_is_refused_not_taken_for_the_flag_left_out(argv, said, tmp_path, capsys, monkeypatch):
    """``--store "$UNSET"`` wrote the run into the per-user store; ``--model ''`` started the offline model;
    ``eval ''`` read the current directory ("is a directory"). Each is one line, and nothing is made anywhere."""
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("CODEARCADE_STORE", raising=False)
    code, _, err = _run(capsys, *argv)
    assert said in _one_line_error(code, err), err
    assert list(tmp_path.iterdir()) == [], "nothing made: no store, here or per user"


def test_new_given_a_folder_names_the_file_to_give(tmp_path, capsys):
    """``new DIR`` said "DIR exists; pass --force to overwrite it", and with --force "DIR: Is a directory": it now
    says, with or without --force, that a file is wanted, and the folder is left as it was."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "kept.txt").write_text("kept")
    for force in ([], ["--force"]):
        code, _, err = _run(capsys, "new", folder, "--game", "pong", *force)
        assert f"{folder} is a folder; give the policy file's path: {folder / 'policy.py'}" in _one_line_error(code,
                                                                                                             err)
    assert [p.name for p in folder.iterdir()] == ["kept.txt"]
    assert _run(capsys, "new", folder / "policy.py", "--game", "pong")[0] == 0


def test_lives_are_asked_only_of_games_that_have_them(tmp_path, capsys):
    """``--one-life-continue`` on Pong played whole games past their step cap as "lives", with an interval over
    them, and no word. Every game without lives refuses it, in eval, optimize and a batch file, before anything is
    made (``--one-life``, a game's first life, is its whole game there: tests/test_curated_games.py); every game
    with lives takes both."""
    from games import GAMES

    for game in GAMES.values():
        game.check_one_life(True)
        if game.lives:
            game.check_one_life("continue")
            continue
        with pytest.raises(ValueError, match=f"{game.name} has no lives"):
            game.check_one_life("continue")
    store = tmp_path / "s.duckdb"
    batch = tmp_path / "b.toml"
    batch.write_text("[defaults]\none_life = 'continue'\n[matrix]\ngame = ['breakout', 'freeway']\n")
    for argv in (["eval", STARTER, "--one-life-continue"],
                 ["optimize", "--game", "enduro", "--one-life-continue", "--iterations", "0"],
                 ["batch", batch, "--dry-run"]):
        code, _, err = _run(capsys, *argv, "--store", store)
        said = _one_line_error(code, err)
        assert "has no lives" in said and ("pong" in said or "enduro" in said or "freeway" in said), said
        assert not store.exists()


def test_a_value_its_type_refuses_is_said_one_way_whatever_the_flag_s_type(capsys):
    """``--call-time-limit abc`` said argparse's "invalid float value: 'abc'" where ``--episodes abc`` said "give a
    whole number, got 'abc'": every flag that takes a number says it in the project's words."""
    from pipeline.cli import build_parser

    parser = build_parser()
    verbs = parser._subparsers._group_actions[0].choices
    checked = 0
    for verb, sub in verbs.items():
        for action in sub._actions:
            kind = action.type if action.type in (int, float) else getattr(action.type, "kind", None)
            if kind not in (int, float) or not action.option_strings:
                continue
            code, _, err = _run(capsys, verb, *(["x.py"] if verb in ("eval", "new") else []),
                                action.option_strings[0], "abc")
            said = _one_line_error(code, err)
            assert "invalid" not in said and f"give a {'whole ' * (kind is int)}number, got 'abc'" in said, \
                (verb, action.option_strings, said)
            checked += 1
    assert checked >= 5


def test_a_locks_folder_that_is_a_file_is_said_before_a_run_is_made(tmp_path, capsys, scripted):
    """`<store>.locks` (where the run locks are kept) existing as a file: optimize made its run, then failed it
    with "File exists; give another path". It is said in one line before any run is made; eval, whose lock only
    shows a run live, plays on."""
    from tests.conftest import COMPETENT_REPLY

    model = scripted([COMPETENT_REPLY])
    path = tmp_path / "s.duckdb"
    (tmp_path / "s.duckdb.locks").write_text("a file, not the folder\n")
    line = _one_line_error(*_run(capsys, "optimize", "--game", "pong", "--model", model.model, "--api-base",
                                 model.api_base, "--iterations", "1", "--store", path)[::2])
    assert "s.duckdb.locks is a file" in line and "move the file away" in line, line
    assert not path.exists() or Store(path).query("SELECT count(*) FROM runs") == [(0,)]
    code, _, err = _run(capsys, "eval", STARTER, "--episodes", "1", "--max-steps", "20", "--store", path)
    assert code == 0, err


def test_a_wal_that_does_not_belong_to_its_file_is_damage_said_in_one_line(played, tmp_path, capsys):
    """A backup of the store put back beside the WAL of a later state: every command, the doctor too, ended with
    DuckDB's "Failure while replaying WAL file ..." (exit 2). It is the store's damage, said as such, and the
    doctor's finding (exit 1), with what the WAL may hold."""
    import shutil

    import duckdb

    path = tmp_path / "s.duckdb"
    path.write_bytes(played.read_bytes())
    backup = tmp_path / "backup.duckdb"
    shutil.copy(path, backup)
    con = duckdb.connect(str(path))
    con.execute("PRAGMA disable_checkpoint_on_shutdown")
    con.execute("CREATE TABLE later (x INTEGER)")
    con.execute("CHECKPOINT")
    con.execute("INSERT INTO later VALUES (1)")  # in the WAL, written against the checkpoint above
    con.close()
    shutil.copy(backup, path)
    line = _one_line_error(*_run(capsys, "runs", "--store", path)[::2])
    assert "is damaged: its WAL (s.duckdb.wal) does not belong" in line and "codearcade doctor" in line, line
    code, out, err = _run(capsys, "doctor", "--store", path)
    assert code == 1 and "Traceback" not in out + err and "WAL" in out + err, out + err
    assert (tmp_path / "s.duckdb.wal").exists(), "the WAL is left as it was"


def test_optimize_into_a_folder_that_does_not_exist_makes_none(tmp_path, capsys, scripted):
    """The run locks' folder is checked before a run is made: that check must not make the store's own folder (a
    mistyped --store would have made the folders and a store in them)."""
    from tests.conftest import COMPETENT_REPLY

    model = scripted([COMPETENT_REPLY])
    path = tmp_path / "typo" / "s.duckdb"
    line = _one_line_error(*_run(capsys, "optimize", "--game", "pong", "--model", model.model, "--api-base",
                                 model.api_base, "--iterations", "1", "--store", path)[::2])
    assert "does not exist" in line and not (tmp_path / "typo").exists(), line
