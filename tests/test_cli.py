"""The everyday command line (#24): runs addressed without ids, `runs` that tells them apart, the store found from
a subdirectory, `sql --param/--schema` and every SQL example of README and docs run as printed, typo'd flags and
verbs answered with the nearest, optimize's start line and its Ctrl-C (a real SIGINT), reused episodes explained,
an unreachable --api-base refused before anything plays, batch labels and its dry run's key warnings, eval's
speed. Real DuckDB files, the real console script in subprocesses, a scripted model behind real HTTP."""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.cli.eval import PAPER_PROTOCOL_NOTE
from store import Store
from store.locate import user_store_path
from tests.conftest import COMPETENT_REPLY, ROOT, json_reply, run_main, said
from tests.scripted_llm import ScriptedModel

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
COMPETENT = ROOT / "tests" / "policies" / "pong_competent.py"
SHORT = r"[0-9A-Z]{8,25}"
"""A run id as the command line prints it: its shortest unique prefix (8 characters or more, never whole)."""
FAST = ("--eval-max-steps", "300", "--rollout-steps", "60", "--workers", "2", "--rng-key", "cli")


def _env(home: Path, **extra) -> dict[str, str]:
    """The environment of a person with no keys and no $CODEARCADE_STORE, whose per-user store is under ``home``."""
    env = {k: v for k, v in os.environ.items() if not k.endswith("_API_KEY") and k != "CODEARCADE_STORE"}
    env.update(XDG_DATA_HOME=str(home / "xdg"), LITELLM_LOCAL_MODEL_COST_MAP="True", OMP_WAIT_POLICY="PASSIVE",
               CODEARCADE_LLM_BACKOFF_S="0.05", **extra)
    return env


def _cli(*argv, cwd: Path, env: dict[str, str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([EXE, *map(str, argv)], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def _ok(done: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert done.returncode == 0, done.stdout + done.stderr
    return done


def _in_process(capsys, *argv) -> tuple[int, str, str]:
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


# --------------------------------------------------------------------------------------------- a day's use


@pytest.fixture(scope="module")
def day(tmp_path_factory):
    """A project whose store was made once with --store, then used from a subdirectory without ids: a traced eval,
    then two short optimizations (the first labelled, its iteration 2 reusing iteration 1's episodes, its held-out
    audit one game per version and protocol; the second's audit, which no test reads, left out)."""
    root = tmp_path_factory.mktemp("project")
    sub = root / "notes" / "today"
    sub.mkdir(parents=True)
    env = _env(root)
    model = ScriptedModel([COMPETENT_REPLY, json_reply({}, "nothing to change")], root / "model").start()
    try:
        made = _ok(_cli("eval", COMPETENT, "--trace", "--max-steps", "200", "--store", "codearcade.duckdb",
                        cwd=root, env=env))
        first = _ok(_cli("optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                         "--iterations", "2", "--name", "morning", "--audit-episodes", "1", *FAST, cwd=sub, env=env))
        second = _ok(_cli("optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                          "--iterations", "2", "--feedback", "rollout", "--audit-episodes", "0", *FAST, cwd=sub,
                          env=env))
    finally:
        model.stop()
    store = Store(root / "codearcade.duckdb")
    ids = [r[0] for r in store.query("SELECT run_id FROM runs ORDER BY created_at")]
    return {"root": root, "sub": sub, "env": env, "store": store, "ids": ids, "eval": made, "first": first,
            "second": second}


@pytest.mark.slow
def test_a_day_without_ids_from_a_subdirectory(day):
    env, sub, ids = day["env"], day["sub"], day["ids"]
    assert len(ids) == 3
    eval_id, morning, afternoon = ids

    def cli(*argv, whole_ids=False):
        done = _ok(_cli(*argv, cwd=sub, env=env))
        assert "nearest in a parent directory" in done.stderr, "the store found in a parent directory is said"
        for run_id in ids if not whole_ids else ():  # ids are printed by their shortest unique prefixes
            assert run_id not in done.stdout
        return done

    # the store was made with --store once, then found from the subdirectory; each run's id said before iteration 0
    assert re.match(rf"run ({SHORT}) started: eval pong_competent.py, 1 episode\(s\); store codearcade.duckdb "
                    r"\(given with --store\)", day["eval"].stdout)
    start = day["first"].stdout.splitlines()
    assert re.fullmatch(rf"run ({SHORT}) 'morning' started: optimize pong, model openai/scripted; store "
                        rf"{re.escape(str(day['root'] / 'codearcade.duckdb'))} \(the nearest in a parent directory\)",
                        start[0]), start[0]
    assert start[1].startswith("iteration   0") and morning.startswith(start[0].split()[1])
    finished = start.index(f"run {start[0].split()[1]} finished")
    assert all(line.startswith("audit  ") for line in start[finished + 1:]) and len(start) > finished + 1, \
        "the run's held-out audit follows its end"

    listed = cli("runs", "-n", "3").stdout.splitlines()
    header = listed[0].split()
    for column in ("run", "name", "policy", "strategy", "feedback", "status", "best"):
        assert column in header
    rows = [line.split() for line in listed[2:]]
    assert [afternoon.startswith(rows[0][0]), morning.startswith(rows[1][0]), eval_id.startswith(rows[2][0])] == \
        [True] * 3, "newest first"
    assert rows[1][1] == "morning" and "rollout" in rows[0] and "staged" in rows[1], "labels and settings tell apart"

    report = Path(cli("report", "last", whole_ids=True).stdout.strip())  # a directory named for good: the whole id
    assert report == Path("reports") / afternoon / "README.md" and (sub / report).is_file()
    blamed = cli("blame", "last").stdout
    assert re.match(rf"run ({SHORT}) \(pong\), policy version", blamed) and afternoon.startswith(blamed.split()[1])
    compared = cli("compare", "last~1", "last").stdout
    table = {line.split()[0]: line.split()[1] for line in compared.splitlines()[2:4]}
    assert morning.startswith(table["A"]) and afternoon.startswith(table["B"])

    by_last = json.loads(cli("sql", "SELECT run_id, name, kind FROM runs WHERE run_id = run('last')", "--json",
                             whole_ids=True).stdout)  # the rows asked for
    assert by_last == [{"run_id": afternoon, "name": None, "kind": "optimize"}]
    short = rows[1][0]
    by_prefix = cli("sql", f"SELECT iteration, score FROM learning_curve WHERE run_id = run('{short.lower()}') "
                    "ORDER BY iteration").stdout
    assert [line.split()[0] for line in by_prefix.splitlines()[2:5]] == ["0", "1", "2"]
    by_label = json.loads(cli("sql", "SELECT run_id FROM runs WHERE run_id = run(?)", "--param", "morning",
                              "--json", whole_ids=True).stdout)
    assert by_label == [{"run_id": morning}]


def _examples() -> list[tuple[str, int, str]]:
    """Every `codearcade sql` command in README.md and docs/*.md: (file, line, the command), continuation lines of
    a query that spans lines joined as the shell would."""
    found = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        lines = path.read_text().splitlines()
        k = 0
        while k < len(lines):
            if lines[k].startswith("codearcade sql "):
                text, first = lines[k], k
                while True:
                    try:
                        shlex.split(text, comments=True)
                        break
                    except ValueError:  # an open quote: the query goes on on the next line
                        k += 1
                        text += "\n" + lines[k]
                found.append((path.name, first + 1, text))
            else:  # in a sentence: `codearcade sql ...` (the command table's synopses, with their "...", are not)
                found += [(path.name, k + 1, span) for span in re.findall(r"`(codearcade sql [^`]+)`", lines[k])
                          if "..." not in span]
            k += 1
    return found


@pytest.mark.slow
def test_every_sql_example_in_readme_and_docs_runs_as_printed(day):
    examples = _examples()
    assert len(examples) >= 22 and {name for name, _, _ in examples} >= {"README.md", "schema.md"}
    for name, line, text in examples:
        # "$(cat examples/x.sql)" is the file's text, as the shell reads it; another store named is this one
        text = re.sub(r'"\$\(cat ([^)]+)\)"', lambda m: shlex.quote((ROOT / m.group(1)).read_text()), text)
        argv = shlex.split(text, comments=True)[1:]
        if "--store" in argv:
            argv[argv.index("--store") + 1] = str(day["store"].path)
        done = _cli(*argv, cwd=day["sub"], env=day["env"])
        assert done.returncode == 0, f"{name}:{line}: {text}\n{done.stderr}"
        assert "row" in done.stdout.splitlines()[-1] or done.stdout.lstrip().startswith("["), f"{name}:{line}"


@pytest.mark.slow
def test_view_explains_episodes_reused_from_an_earlier_iteration(day):
    store, morning = day["store"], day["ids"][1]
    assert store.query("SELECT evaluation FROM candidates WHERE run_id = ? AND iteration = 2", [morning]) == \
        [("cached",)], "iteration 2 proposed no change: its episodes are iteration 1's"
    saved = day["root"] / "it2.rrd"
    done = _ok(_cli("view", "morning", "--iteration", "2", "--save", saved, cwd=day["sub"], env=day["env"]))
    note = [line for line in done.stderr.splitlines() if "played no episodes" in line]
    assert len(note) == 1 and "reused" in note[0] and "evaluation cache" in note[0]
    assert "assessed in iteration 1" in note[0] and f"showing {morning}.1.train.0" in note[0]
    assert "`codearcade view morning --iteration 1`" in note[0] and saved.stat().st_size > 0
    whole = _ok(_cli("view", "morning", "--save", day["root"] / "run.rrd", cwd=day["sub"], env=day["env"]))
    said = whole.stdout.splitlines()[0]
    assert re.fullmatch(rf"run ({SHORT}): 3 iteration\(s\)", said) and morning.startswith(said.split()[1][:-1])
    assert morning not in said, "the run by its shortest unique prefix, as every verb prints it"
    beyond = _cli("view", "morning", "--iteration", "7", cwd=day["sub"], env=day["env"])
    assert beyond.returncode == 2 and "has iterations 0..2, no iteration 7" in beyond.stderr
    assert len(beyond.stderr.strip().splitlines()) == 2  # the store's line, then the error


# ------------------------------------------------------------------------------------------------- optimize


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_ctrl_c_prints_the_resume_command_and_it_continues_the_run(tmp_path):
    """A real SIGINT while iteration 1 waits for the model: exit 130 with the run and the exact command, which
    then finishes the same run."""
    env = _env(tmp_path)
    store = Store(tmp_path / "s.duckdb")
    with ScriptedModel([{"sleep": 120, "content": COMPETENT_REPLY}, COMPETENT_REPLY], tmp_path / "model") as model:
        proc = subprocess.Popen([EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base",
                                 model.api_base, "--iterations", "1", "--audit-episodes", "0", *FAST, "--store",
                                 str(store.path)],
                                cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        lines = []
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            if line.startswith("iteration   0"):
                break
        deadline = time.monotonic() + 60
        while not (model.log_path.exists() and model.raw_requests()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert model.raw_requests(), "iteration 1 asked the model (which takes 120 s to answer)"
        proc.send_signal(signal.SIGINT)
        for pause in (0.02, 0.05, 0.1, 0.2, 0.4):  # a person pressing Ctrl-C again while the run winds down
            time.sleep(pause)
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 130, err
        assert "Traceback" not in err and "Exception ignored" not in err, err
        start = re.fullmatch(rf"run ({SHORT}) started: optimize pong, model openai/scripted; store \S+ \(given with "
                             r"--store\)", lines[0])
        assert start and lines[1].startswith("iteration   0"), lines
        said = err.strip().splitlines()[-1]
        match = re.fullmatch(rf"codearcade: interrupted: run ({SHORT}) is stored up to its last whole iteration; "
                             r"continue it with `(.+)`", said)
        assert match and match.group(1) == start.group(1), said
        command = shlex.split(match.group(2))
        assert command == ["codearcade", "optimize", "--resume", start.group(1), "--store", str(store.path)]
        (run_id, status), = store.query("SELECT run_id, status FROM runs")
        assert status == "interrupted" and run_id.startswith(start.group(1))
        resumed = _ok(_cli(*command[1:], cwd=tmp_path / "..", env=env))
    assert resumed.stdout.startswith(f"run {start.group(1)} resumed: optimize pong")
    assert store.query("SELECT run_id, status FROM runs") == [(run_id, "finished")]
    assert store.query("SELECT iteration, update_status FROM iterations ORDER BY iteration") == \
        [(0, "initial"), (1, "accepted")]


@pytest.mark.slow
@pytest.mark.parametrize("script", [[{"sleep": 120, "content": COMPETENT_REPLY}],
                                    [{"status": 429, "headers": {"retry-after": "120"}, "times": 100}]],
                         ids=["replies-in-flight", "retries-waiting"])
def test_ctrl_c_stops_a_population_whose_calls_are_in_flight(tmp_path, script):
    """best-of-n asks its candidates' replies at once, in threads: a Ctrl-C there waited for every call in
    flight (a thread pool joins its threads on the way out: 121 s for a 120 s reply) and for its retries (a 429
    asking for 120 s, twice over), where the same press during one call stops the command at once."""
    env = _env(tmp_path)
    store = Store(tmp_path / "s.duckdb")
    with ScriptedModel(script, tmp_path / "model") as model:
        proc = subprocess.Popen([EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base",
                                 model.api_base, "--iterations", "1", "--strategy", "best-of-n", "--candidates", "2",
                                 "--audit-episodes", "0", *FAST, "--store", str(store.path)],
                                cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        while len(model.raw_requests()) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        assert len(model.raw_requests()) >= (2 if "sleep" in script[0] else 1), "iteration 1's calls are out"
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=60)  # before: a reply's 120 s (a retry's wait: 120 s, then another)
        finally:
            proc.kill()  # a command still waiting is not left behind the test
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("codearcade: interrupted: run "), err
    assert store.query("SELECT status FROM runs") == [("interrupted",)]


@pytest.mark.slow
def test_an_unreachable_api_base_is_one_line_before_anything_plays(tmp_path):
    url = f"http://127.0.0.1:{_closed_port()}/v1"
    done = _cli("optimize", "--game", "pong", "--model", "openai/local", "--api-base", url, "--store", "s.duckdb",
                cwd=tmp_path, env=_env(tmp_path))
    assert done.returncode == 2
    (line,) = done.stderr.strip().splitlines()
    assert f"--api-base {url} cannot be reached" in line and "start the server there" in line
    assert not (tmp_path / "s.duckdb").exists(), "nothing was stored: iteration 0 never played"
    # an ensemble's model with its own server: the message names where that URL was given
    done = _cli("optimize", "--game", "pong", "--model", "openai/a", "--model", f"openai/b,api_base={url}",
                "--store", "s.duckdb", cwd=tmp_path, env={**_env(tmp_path), "OPENAI_API_KEY": "sk-test"})
    assert done.returncode == 2 and f"the api_base of --model openai/b {url} cannot be reached" in done.stderr, \
        done.stderr
    from pipeline.llm.providers import UnreachableEndpointError, check_reachable

    with pytest.raises(UnreachableEndpointError, match="not an http"):
        check_reachable("127.0.0.1:8000")


@pytest.mark.parametrize("argv, said", [
    (["--game", "pongg"], "unknown game 'pongg'"),
    (["--game", "pong\x1b[2J"], "unknown game 'pong\\x1b[2J'"),  # shown as written, not as 'pong'
    (["missing.py"], "policy file 'missing.py' does not exist"),
    (["broken.py"], "broken.py:1: syntax error"),
    (["notrain.py"], "no trainable methods"),
])
def test_a_typo_in_optimize_is_said_before_the_model_is_reached(tmp_path, argv, said):
    """The policy file and the game are checked before anything model-side (the server's reachability here; the
    offline model's start-up, the credentials' use): a typo costs what it costs in `eval`."""
    (tmp_path / "broken.py").write_text("import x(\n")
    (tmp_path / "notrain.py").write_text("GAME = 'pong'\nclass Policy:\n    def __call__(self, obs):\n        return 0\n")
    url = f"http://127.0.0.1:{_closed_port()}/v1"
    done = _cli("optimize", *argv, "--model", "openai/local", "--api-base", url, "--store", "s.duckdb",
                cwd=tmp_path, env=_env(tmp_path))
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert said in line and "cannot be reached" not in line, line
    assert not (tmp_path / "s.duckdb").exists()


# ------------------------------------------------------------------------------------------------------ eval


@pytest.mark.slow
def test_eval_labels_its_run_says_its_id_and_speed(tmp_path):
    env = _env(tmp_path)
    done = _ok(_cli("eval", COMPETENT, "--episodes", "2", "--max-steps", "150", "--name", "first-look", "--store",
                    "s.duckdb", cwd=tmp_path, env=env))
    lines = done.stdout.splitlines()
    start = re.fullmatch(rf"run ({SHORT}) 'first-look' started: eval pong_competent.py, 2 episode\(s\); store "
                         r"s.duckdb \(given with --store\)", lines[0])
    assert start and lines[1].startswith(f"run {start.group(1)} 'first-look'  game pong"), lines
    # the mean with its interval's level, method and n, or why it has none (the paper's protocol: one game twice)
    speed = re.fullmatch(r"mean return \S+ (?:\[\S+, \S+\] 95% t, n=2|\(n=2: all equal, no interval\)); 300 steps "
                         r"in ([0-9.]+) s \(([0-9,]+) steps/s, setup and checks included\)", lines[-2])
    assert speed, lines[-2]
    assert lines[-1] == PAPER_PROTOCOL_NOTE, "repeated episodes of one seed's game are said to be one game"
    # the rate is the steps over the unrounded seconds: whatever those were, they round to the shown ones
    shown_s, rate = float(speed.group(1)), int(speed.group(2).replace(",", ""))
    assert 300 / (shown_s + 0.05) - 1 <= rate <= 300 / max(shown_s - 0.05, 1e-9) + 1, (shown_s, rate)
    store = Store(tmp_path / "s.duckdb")
    (run_id, name), = store.query("SELECT run_id, name FROM runs")
    assert name == "first-look" and run_id.startswith(start.group(1)) and run_id != start.group(1)

    summary = json.loads(_ok(_cli("eval", COMPETENT, "--max-steps", "100", "--json", "--store", "s.duckdb",
                                  cwd=tmp_path, env=env)).stdout)
    assert summary["steps"] == 100 and summary["elapsed_s"] > 0
    assert summary["steps_per_s"] == pytest.approx(100 / summary["elapsed_s"], rel=0.02)

    refused = _cli("eval", COMPETENT, "--name", "7up", "--store", "other.duckdb", cwd=tmp_path, env=env)
    assert refused.returncode == 2 and "run name '7up' cannot be used" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and not (tmp_path / "other.duckdb").exists()

    # an error names a run by its shortest unique prefix too
    wrong = _cli("optimize", "--resume", run_id, "--store", "s.duckdb", cwd=tmp_path, env=env)
    assert wrong.returncode == 2 and f"run {start.group(1)} is an eval run" in wrong.stderr
    assert run_id not in wrong.stderr


@pytest.mark.slow
def test_eval_names_the_store_once(tmp_path):
    """From a subdirectory the start line says which store and why, so no separate line on stderr says it again;
    with --json (no start line) the stderr line is the one that says it."""
    env = _env(tmp_path)
    sub = tmp_path / "sub"
    sub.mkdir()
    _ok(_cli("eval", COMPETENT, "--max-steps", "50", "--store", "codearcade.duckdb", cwd=tmp_path, env=env))
    done = _ok(_cli("eval", COMPETENT, "--max-steps", "50", cwd=sub, env=env))
    assert done.stdout.splitlines()[0].endswith(f"; store {tmp_path / 'codearcade.duckdb'} (the nearest in a "
                                                "parent directory)")
    assert "store" not in done.stderr, done.stderr
    quiet = _ok(_cli("eval", COMPETENT, "--max-steps", "50", "--json", cwd=sub, env=env))
    assert json.loads(quiet.stdout)["steps"] == 50
    assert said(quiet.stderr) == [f"codearcade: store {tmp_path / 'codearcade.duckdb'} (the nearest in a parent "
                                  "directory)"], quiet.stderr


# -------------------------------------------------------------------------------------------------- parsing


@pytest.mark.parametrize("argv, said", [
    (["eval", "--epsiodes", "3", "pong.py"], "codearcade eval: unknown flag --epsiodes; did you mean --episodes?"),
    (["evl", "pong.py"], "codearcade: unknown verb 'evl'; did you mean eval?"),
    (["blame", "--iteraton", "2"], "codearcade blame: unknown flag --iteraton; did you mean --iteration?"),
    (["runs", "--limt=3"], "codearcade runs: unknown flag --limt; did you mean --limit?"),
    (["sql", "--parma", "x", "SELECT 1"], "codearcade sql: unknown flag --parma; did you mean --param?"),
    (["optimize", "--strategy", "beem"], "codearcade optimize: argument --strategy: invalid choice 'beem'; did you "
                                         "mean beam? (choose from greedy, best-of-n, beam, map-elites)"),
    (["runs", "--zzz"], "codearcade runs: unknown flag --zzz; `codearcade runs --help` lists the flags"),
    # the dashes every long flag has are not a likeness: these named --store and --json
    (["report", "--lsat"], "codearcade report: unknown flag --lsat; `codearcade report --help` lists the flags"),
    (["games", "--store", "x"], "codearcade games: unknown flag --store; `codearcade games --help` lists the flags"),
])
def test_a_mistyped_flag_or_verb_gets_the_nearest_in_one_line(capsys, argv, said):
    code, out, err = _in_process(capsys, *argv)
    assert code == 2 and out == "" and err == said + "\n"


def test_the_console_script_answers_a_typo_the_same(tmp_path):
    done = _cli("eval", "--epsiodes", "3", "x.py", cwd=tmp_path, env=_env(tmp_path))
    assert done.returncode == 2 and done.stderr == "codearcade eval: unknown flag --epsiodes; did you mean --episodes?\n"


# ------------------------------------------------------------------------------------------------ runs, sql


@pytest.fixture
def four(store):
    from tests.test_runs import RUNS, _add

    for run_id, minutes, kind, game, name, made_by, config in RUNS:
        _add(store, run_id, minutes, kind, game, name, made_by, config)
    return store


def _table(out: str) -> list[list[str]]:
    return [line.split() for line in out.splitlines()[2:]]


def test_runs_newest_first_with_filters_and_without_compares_own(four, capsys):
    from pipeline.cli.runs import STATUSES
    from store.runs import RUN_STATUSES

    assert STATUSES == RUN_STATUSES
    code, out, _ = _in_process(capsys, "runs", "--store", four.path)
    assert code == 0
    header = out.splitlines()[0].split()
    assert header[:2] == ["run", "name"] and {"policy", "strategy", "feedback", "batch"} <= set(header)
    rows = _table(out)
    assert [r[0] for r in rows] == ["01JDX3K9", "01JDX3K2AC", "01JDX3K2AB"], "newest first, shortest prefixes"
    assert rows[2][1] == "baseline" and "beam" in rows[1] and "ablation" in rows[1] and "pong_start.py" in rows[2]
    _, out, _ = _in_process(capsys, "runs", "--all", "--store", four.path)
    assert _table(out)[0][0] == "01JDX3KZ" and "(compare)" in out.splitlines()[2]
    for argv, expected in [(["-n", "1"], ["01JDX3K9"]), (["--game", "Pong"], ["01JDX3K2AC", "01JDX3K2AB"]),
                           (["--kind", "eval"], ["01JDX3K9"]), (["--kind", "optimize", "--limit", "1"], ["01JDX3K2AC"]),
                           (["--status", "finished", "--game", "breakout"], ["01JDX3K9"])]:
        _, out, _ = _in_process(capsys, "runs", *argv, "--store", four.path)
        assert [r[0] for r in _table(out)] == expected, argv
    _, out, _ = _in_process(capsys, "runs", "--status", "failed", "--store", four.path)
    assert out.startswith("no runs match in")
    _, out, _ = _in_process(capsys, "runs", "--json", "-n", "2", "--store", four.path)
    listed = json.loads(out)
    assert [(r["short_id"], r["run_id"][:10]) for r in listed] == [("01JDX3K9", "01JDX3K9QQ"), ("01JDX3K2AC",
                                                                                                 "01JDX3K2AC")]
    assert listed[1]["strategy"] == "beam" and listed[1]["batch"] == "ablation"

    from tests.test_runs import _add

    _add(four, "01JDX3M000000000000000000E", 20, "replay", "pong", config={"strategy": "greedy"})
    _, out, _ = _in_process(capsys, "runs", "-n", "1", "--store", four.path)
    assert _table(out)[0][:5] == ["01JDX3M0", "2026-12-02", "14:20", "replay", "pong"]
    assert _table(out)[0][5] == "scaffold", "a replay of a run from the game's scaffold starts from it too"


def test_sql_params_and_schema(four, capsys):
    from store.views import TABLES, VIEWS

    def sql(*argv):
        code, out, err = _in_process(capsys, "sql", *argv, "--store", four.path, "--json")
        return code, (json.loads(out) if code == 0 else err)

    assert sql("SELECT name FROM runs WHERE run_id = run(?)", "--param", "last~2") == (0, [{"name": "baseline"}])
    assert sql("SELECT count(*) AS n FROM runs WHERE game = $game AND kind = $kind", "--param", "$game=pong",
               "--param", "kind=optimize") == (0, [{"n": 2}])
    code, err = sql("SELECT count(*) FROM runs WHERE game = ? AND kind = ?", "--param", "pong")
    assert code == 2 and "2 parameters" in err and len(err.strip().splitlines()) == 1
    code, err = sql("SELECT run_id FROM runs WHERE run_id = run('01JDX3K2A')")
    assert code == 2 and "ambiguous" in err
    code, out, err = _in_process(capsys, "sql", "--schema", "--store", four.path)
    assert code == 0
    names = {line.split()[0] for line in out.splitlines()[2:-1]}
    assert names >= set(TABLES) | set(VIEWS) | {"run(ref)", "run_matches(ref)"}
    code, _, err = _in_process(capsys, "sql", "--schema", "SELECT 1", "--store", four.path)
    assert code == 2 and "--schema" in err
    code, _, err = _in_process(capsys, "sql", "--store", four.path)
    assert code == 2 and "give a query" in err and "--schema" in err
    code, out, _ = _in_process(capsys, "sql", "--help")
    assert code == 0 and "--schema" in out and "run('last')" in out


def test_a_query_that_finds_nothing_by_a_short_id_says_how_to_name_the_run(four, capsys):
    """The short id `runs` prints, a label or `last` compared with run_id as a plain value finds nothing (ids are
    stored whole): one note on stderr says to write run(...); the rows asked for are still printed, and a value
    that is a whole id, or already inside run(...), or a query with rows, gets no note."""
    def sql(*argv):
        code, out, err = _in_process(capsys, "sql", *argv, "--store", four.path, "--json")
        assert code == 0, err
        return json.loads(out), err.strip().splitlines()

    rows, said = sql("SELECT kind FROM runs WHERE run_id = '01JDX3K2AC'")
    assert rows == [] and said == ["codearcade: note: no rows; '01JDX3K2AC' is the start of run 01JDX3K2AC's id, "
                                   "and the store keeps ids whole (26 characters): write run('01JDX3K2AC') where a "
                                   "run id goes, e.g. WHERE run_id = run('01JDX3K2AC')"]
    assert sql("SELECT kind FROM runs WHERE run_id = run('01JDX3K2AC')") == ([{"kind": "optimize"}], [])
    rows, said = sql("SELECT iteration FROM iterations WHERE run_id = ? AND iteration > ?", "--param", "baseline",
                     "--param", "1")
    assert rows == [] and len(said) == 1 and "'baseline' is run 01JDX3K2AB's label" in said[0]
    rows, said = sql("SELECT kind FROM runs WHERE run_id = 'last'")
    assert len(said) == 1 and "'last' names run 01JDX3K9 only through run(): write run('last')" in said[0]
    rows, said = sql("SELECT iteration FROM learning_curve WHERE run_id = run('last')")  # after an eval: its run
    assert rows == [] and said == ["codearcade: note: no rows; run('last') is eval run 01JDX3K9 (breakout): last "
                                   "counts runs of every kind"]
    rows, said = sql("SELECT kind FROM runs WHERE run_id = '01JDX3K2A'")
    assert len(said) == 1 and "'01JDX3K2A' is the start of 2 run ids" in said[0] and "run_matches(" in said[0]
    # nothing to say: a whole id, a value inside run(...) (no rows for another reason), too short a prefix, a
    # number (-1 is not taken for a run), and a query that found rows
    for argv in (["SELECT 1 FROM runs WHERE run_id = '01JDX3K2AB7Q000000000000A1' AND kind = 'eval'"],
                 ["SELECT 1 FROM iterations WHERE run_id = run('01JDX3K2AC') AND iteration = 7"],
                 ["SELECT 1 FROM iterations WHERE run_id = run(?) AND iteration = 7", "--param", "baseline"],
                 ["SELECT 1 FROM runs WHERE run_id = '01J'"], ["SELECT 1 FROM runs WHERE seed = ?", "--param", "-1"],
                 ["SELECT kind FROM runs WHERE kind = 'eval' OR run_id = '01JDX3K2AC'"]):
        assert sql(*argv)[1] == [], argv


def test_the_per_user_store_is_said_and_the_rule_is_in_the_help(tmp_path):
    from tests.test_runs import RUNS, _add

    env = _env(tmp_path)
    user = Store(user_store_path(env))
    user.path.parent.mkdir(parents=True)
    _add(user, *RUNS[0][:5])
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    done = _ok(_cli("runs", cwd=elsewhere, env=env))
    assert done.stderr == f"codearcade: store {user.path} (the per-user store: no codearcade.duckdb in this " \
                          "directory or a parent, no --store, no $CODEARCADE_STORE)\n"
    assert "baseline" in done.stdout
    quiet = _ok(_cli("runs", "--store", user.path, cwd=elsewhere, env=env))
    assert quiet.stderr == "", "a store given is not announced"
    helped = " ".join(_ok(_cli("runs", "--help", cwd=elsewhere, env=env)).stdout.split())
    assert "$CODEARCADE_STORE, else the nearest codearcade.duckdb in this directory or a parent" in helped
    assert "per-user" in helped


# ----------------------------------------------------------------------------------------------------- batch


@pytest.mark.slow
def test_batch_dry_run_shows_labels_and_warns_of_an_unset_key(tmp_path):
    ablation = ROOT / "examples" / "ablation.toml"
    env = _env(tmp_path)
    done = _ok(_cli("batch", ablation, "--dry-run", "--store", "a.duckdb", cwd=tmp_path, env=env))
    labels = re.findall(r"\[(\S+)\]", done.stdout)
    assert labels == [f"pong-ablation:pong,feedback={f},seed={s}" for f in ("rollout", "staged") for s in (0, 1, 2)]
    (warning,) = done.stderr.strip().splitlines()
    assert warning.startswith("codearcade: warning: anthropic/claude-sonnet-4-5 needs an API key: set "
                              "ANTHROPIC_API_KEY") and warning.endswith("(6 runs)")
    keyed = _ok(_cli("batch", ablation, "--dry-run", "--store", "a.duckdb", cwd=tmp_path,
                     env={**env, "ANTHROPIC_API_KEY": "sk-ant-x"}))
    assert keyed.stderr == ""
    refused = _cli("batch", ablation, "--store", "a.duckdb", cwd=tmp_path, env=env)
    assert refused.returncode == 2 and "ANTHROPIC_API_KEY" in refused.stderr and not (tmp_path / "a.duckdb").exists()

    down = tmp_path / "down.toml"
    down.write_text(textwrap.dedent(f"""
        name = "down"
        [defaults]
        model = "openai/local"
        api_base = "http://127.0.0.1:{_closed_port()}/v1"
        [matrix]
        game = ["pong", "breakout"]
    """))
    done = _ok(_cli("batch", down, "--dry-run", "--store", "a.duckdb", cwd=tmp_path, env=env))
    assert "cannot be reached" in done.stderr and done.stderr.strip().endswith("(2 runs)")


def test_batch_labels_follow_the_entries(tmp_path):
    from pipeline.jobs.experiments import ExperimentError, load_experiments

    path = tmp_path / "x.toml"
    path.write_text('name = "x"\n[[run]]\ngame = "pong"\n[[run]]\ngame = "pong"\nseed = 1\n'
                    '[[run]]\ngame = "breakout"\nname = "brk"\n')
    assert [r.name for r in load_experiments(path).runs] == ["x:pong#1", "x:pong#2", "brk"]
    path.write_text('name = "2024"\n[[run]]\ngame = "pong"\n')
    assert [r.name for r in load_experiments(path).runs] == [None], "a label must start with a letter"
    path.write_text('name = "x"\n[[run]]\ngame = "pong"\nname = "last"\n')
    with pytest.raises(ExperimentError, match=r"\[\[run\]\] #1: name: run name 'last' cannot be used"):
        load_experiments(path)


@pytest.mark.slow
def test_a_batch_stores_its_labels_and_they_name_the_runs(tmp_path, scripted, capsys):
    from pipeline.cli.compare import is_version_ref

    model = scripted([COMPETENT_REPLY])
    path = tmp_path / "tiny.toml"
    path.write_text(textwrap.dedent(f"""
        name = "tiny"
        [defaults]
        game = "pong"
        iterations = 0
        eval_max_steps = 100
        rollout_steps = 50
        audit_episodes = 0
        model = "{model.model}"
        api_base = "{model.api_base}"
        [matrix]
        seed = [0, 1]
        [[run]]
        seed = 5
        name = "mine"
    """))
    store = Store(tmp_path / "b.duckdb")
    _ok(_cli("batch", path, "--workers", "2", "--store", store.path, cwd=tmp_path, env=_env(tmp_path)))
    assert sorted(store.query("SELECT name, json_extract(config, '$.seed')::INT FROM runs")) == \
        [("mine", 5), ("tiny:pong,seed=0", 0), ("tiny:pong,seed=1", 1)]
    code, out, _ = _in_process(capsys, "sql", "SELECT seed FROM runs WHERE run_id = run(?)", "--param",
                               "tiny:pong,seed=1", "--store", store.path, "--json")
    assert code == 0 and json.loads(out) == [{"seed": 1}]
    assert not is_version_ref("tiny:pong,seed=1", store), "a label with a colon is a run, not RUN:VERSION"
    assert is_version_ref("tiny:pong,seed=1:best", store)
    code, out, _ = _in_process(capsys, "runs", "--store", store.path)
    assert "tiny:pong,seed=0" in out and "mine" in out


def test_run_ids_in_messages_are_shortened_but_episode_ids_are_not():
    from pipeline.cli.common import shorten_run_ids

    short = {"01JDX3K2AB7Q000000000000A1": "01JDX3K2AB"}
    text = "run 01JDX3K2AB7Q000000000000A1 failed in 01JDX3K2AB7Q000000000000A1.3.eval.0; see 01JDX3K2AB7Q000000000000B9"
    assert shorten_run_ids(text, short) == ("run 01JDX3K2AB failed in 01JDX3K2AB7Q000000000000A1.3.eval.0; see "
                                            "01JDX3K2AB7Q000000000000B9")


def test_long_work_is_never_silent_off_a_terminal():
    """Off a terminal (a CI log, `| tee`), where a bar would show nothing, playing episodes says so when it starts
    and as each tenth of them ends (``EpisodeProgress``: eval's bar on a terminal)."""
    import io

    from pipeline.cli.common import EpisodeProgress

    for total, expected in [(3, 1 + 3), (25, 1 + 10), (1, 1 + 1)]:
        stream = io.StringIO()
        progress = EpisodeProgress(total, "audit of 01ABCDEF", stream=stream)
        for i in range(total):
            progress.update(i, 50)
            progress.finished(i, 100)
        progress.close()
        lines = stream.getvalue().splitlines()
        assert len(lines) == expected and lines[0] == f"audit of 01ABCDEF: {total} episode{'s' * (total > 1)} to play"
        assert lines[-1] == f"audit of 01ABCDEF: {total} of {total} episodes played, {100 * total:,} steps", lines


@pytest.mark.parametrize("seed", range(6))
def test_off_a_terminal_no_stretch_of_play_is_longer_than_a_minute_without_a_line(seed):
    """A tenth of 100,000 short episodes took 5 minutes, one 15-minute episode was a tenth of ten: off a terminal
    the wait was silent that long. Over schedules of every shape (many short episodes, a few long ones, updates
    at random moments, on a clock of the test's), no stretch of play goes past QUIET_LINE_S (plus the gap to the
    next callback) without a line, and a brisk run still says a line a tenth."""
    import io
    import random

    from pipeline.cli.common import QUIET_LINE_S, EpisodeProgress

    rng = random.Random(seed)
    now = [0.0]
    episodes = rng.choice([1, 3, 10, 1000, 100_000])
    stream = io.StringIO()
    stamps: list[float] = []

    class Stamped(io.StringIO):
        def write(self, text: str) -> int:
            stamps.extend(now[0] for _ in range(text.count("\n")))
            return stream.write(text)

    progress = EpisodeProgress(episodes, "eval p.py", stream=Stamped(), clock=lambda: now[0])
    gaps = []
    per_episode = rng.choice([0.01, 1.0, 30.0, 900.0]) / max(1, episodes // 1000)
    for i in range(min(episodes, 20_000)):
        for played in range(1, rng.randint(1, 4)):
            gap = rng.uniform(0, min(per_episode, 5.0))
            gaps.append(gap)
            now[0] += gap
            progress.update(i, played * 100)
        now[0] += rng.uniform(0, per_episode)
        progress.finished(i, 400)
    lines = stream.getvalue().splitlines()
    assert lines[0] == f"eval p.py: {episodes} episode{'s' * (episodes > 1)} to play"
    silences = [b - a for a, b in zip([0.0, *stamps], [*stamps, now[0]])]
    assert max(silences) <= QUIET_LINE_S + max(per_episode, max(gaps, default=0)) + 1e-6, (max(silences), per_episode)
    assert len(lines) <= 1 + 10 + now[0] / QUIET_LINE_S + 1, "a line a tenth, and one a quiet minute: no more"


def test_progress_lines_are_told_apart_from_what_a_command_says():
    err = "eval p.py: 2 episodes to play\neval p.py: 1 of 2 episodes played, 1,234 steps\ncodearcade: error: x\n"
    assert said(err) == ["codearcade: error: x"]
    assert said("eval p.py: to play everything\n") == ["eval p.py: to play everything"]


def test_version_says_the_installed_version(capsys):
    """``codearcade --version`` (it was "unknown flag"): the version a run records of itself."""
    from importlib import metadata

    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.strip() == f"codearcade {metadata.version('codearcade')}"


def test_a_second_run_under_a_label_is_made_with_a_warning(tmp_path, capsys):
    """``eval --name dup`` twice: both ran silently, and ``report dup`` then said "2 runs are named 'dup'". The
    second run is still made (a batch's reruns share their labels), with a warning naming the first."""
    store = str(tmp_path / "s.duckdb")
    policy = str(ROOT / "games" / "scaffolds" / "pong.py")
    code, _, first = _in_process(capsys, "eval", policy, "--max-steps", "5", "--name", "dup", "--store", store)
    assert code == 0 and "warning" not in first
    code, _, second = _in_process(capsys, "eval", policy, "--max-steps", "5", "--name", "dup", "--store", store)
    (earlier,) = [r for (r,) in Store(Path(store)).query("SELECT run_id FROM runs ORDER BY created_at LIMIT 1")]
    assert code == 0 and "codearcade: warning: run " in second and "is named 'dup' too" in second, second
    assert earlier[:8] in second


def test_a_failed_optimize_says_its_error_once_with_how_to_continue(tmp_path, capsys, scripted):
    """A run the model's 401 stopped printed its error twice, on stdout's last line and in stderr's advice; once
    now, where the advice is (stderr), and stdout still ends with the run's status."""
    model = scripted([{"status": 401}])
    code, out, err = _in_process(capsys, "optimize", "--game", "pong", "--model", model.model, "--api-base",
                                 model.api_base, "--iterations", "1", "--eval-max-steps", "50", "--rollout-steps",
                                 "20", "--workers", "1", "--store", tmp_path / "s.duckdb")
    assert code == 1 and out.strip().splitlines()[-1].endswith(" failed"), out
    assert (out + err).count("invalid api key") == 1 and "continue it with `codearcade optimize --resume" in err, err


def test_help_as_a_verb_shows_the_help(capsys):
    """`codearcade help` answered "unknown verb 'help'; did you mean eval?"; `help [VERB]` is `[VERB] --help`."""
    for argv, usage in ((["help"], "usage: codearcade [-h]"), (["help", "optimize"], "usage: codearcade optimize")):
        with pytest.raises(SystemExit) as ended:
            main(argv)
        out = capsys.readouterr().out
        assert ended.value.code == 0 and out.startswith(usage), out[:200]


LOADED_AT_EXIT = """
import atexit, runpy, sys
atexit.register(lambda: print("loaded:", *[m for m in ("pandas", "litellm", "pyarrow", "numpy") if m in sys.modules],
                              file=sys.__stderr__))
sys.argv = ["codearcade", *sys.argv[1:]]
runpy.run_module("pipeline.cli", run_name="__main__")
"""
"""The command line, run as its console script runs it, saying at its exit which heavy packages it loaded."""


def test_a_command_that_writes_the_store_through_pyarrow_loads_no_pandas(tmp_path):
    """pyarrow imports pandas (0.3-0.45 s, 25 MB) the first time it is handed a list, to ask whether it is a
    DataFrame: the command line's process has it ask with pandas refused (``lists_are_not_dataframes``)."""
    store = tmp_path / "s.duckdb"
    done = subprocess.run([sys.executable, "-c", LOADED_AT_EXIT, "eval", "games/scaffolds/pong.py", "--episodes", "1",
                           "--max-steps", "30", "--store", str(store)], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=_env(tmp_path))
    assert done.returncode == 0, done.stderr
    assert Store(store).query("SELECT count(*) FROM steps")[0][0] == 30  # written as Arrow tables
    assert done.stderr.splitlines()[-1] == "loaded: pyarrow numpy", done.stderr[-2000:]


@pytest.mark.parametrize("argv, loaded", [
    (["runs"], "loaded:"),
    (["sql", "SELECT count(*) AS n FROM runs"], "loaded: numpy"),  # DuckDB's Python functions (`sql`'s statistics)
    (["--help"], "loaded:"),
], ids=["runs", "sql", "help"])
def test_a_command_that_handles_no_arrow_table_imports_neither_pyarrow_nor_numpy(argv, loaded, tmp_path):
    """Every command's process asked pyarrow its DataFrame question as it started (``lists_are_not_dataframes``),
    importing pyarrow and numpy for it, and the verbs' parsers reached both through the ``tracing`` package (the
    bounds of its values, its policy files: the package imports its node capture): ~0.09 s of every command, `runs`
    0.29-0.35 s -> 0.23-0.25 s. The question is now asked when pyarrow is first imported (the test above: an eval
    still loads no pandas), and node capture imports pyarrow where it makes a table."""
    store = tmp_path / "s.duckdb"
    Store(store).make_ready()
    given = argv if argv == ["--help"] else [*argv, "--store", str(store)]
    done = subprocess.run([sys.executable, "-c", LOADED_AT_EXIT, *given], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env=_env(tmp_path))
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines()[-1] == loaded, done.stderr[-2000:]


ASKED_ONCE = """
import sys
import pyarrow as pa
from pipeline.boundary.preload import lists_are_not_dataframes
lists_are_not_dataframes()
assert pa.table({"a": [1, 2]}).num_rows == 2 and pa.array(["x"]).to_pylist() == ["x"]
print("pandas" in sys.modules)
import pandas as pd
print(pa.table(pd.DataFrame({"a": [3]})).column("a").to_pylist(), pa.table({"a": [4]}).to_pandas()["a"].tolist())
"""


def test_pyarrow_asked_about_pandas_once_still_converts_a_dataframe_when_asked_to():
    done = subprocess.run([sys.executable, "-c", ASKED_ONCE], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["False", "[3] [4]"], done.stdout


def test_a_command_run_under_a_profiler_ends_as_python_does_so_the_profiler_reports(tmp_path):
    """A command's process ends once its exit handlers have run, past the interpreter's teardown
    (``pipeline.stopping.end_process``), and with it went what a profiler does as the interpreter exits: `python -m
    cProfile -o FILE -m pipeline.cli ...` wrote no FILE. Under a profiler or a debugger the command exits as Python
    does. Checked by its effect: the profile is written and holds the verb's handler."""
    import pstats

    profile = tmp_path / "games.prof"
    done = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(profile), "-m", "pipeline.cli", "games"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert profile.exists(), "the profiler wrote nothing"
    ran = {(Path(file).name, name) for file, _, name in pstats.Stats(str(profile)).stats}
    assert ("games.py", "run") in ran


def test_the_help_imports_no_database():
    """`codearcade --help` builds every verb's parser from the verbs' modules, and two of them import ``store.scores``:
    the ``store`` package took its ``Store`` from ``store.db`` as it was imported, and the help waited for DuckDB
    (0.30 s, 0.22 s without it). A module of the store that needs no database now imports none."""
    program = ("import sys\nfrom pipeline.cli import build_parser\nbuild_parser()\n"
               "print(sorted(m for m in ('duckdb', 'store.db') if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", program], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_every_count_a_verb_takes_is_refused_past_what_it_can_hold_in_one_line():
    """A verb's own counts (``runs -n``, ``sql --max-rows``, ``audit --episodes``, ``view --iteration``, ...) took any
    whole number: ``runs -n 99999999999999999999`` reached DuckDB and ended in a ConversionException's traceback,
    ``audit --episodes`` of as many said "Sample larger than population". Every flag of every verb whose type is
    a whole-number range refuses a number past it in the parser's one line, exit 2, before anything runs."""
    from pipeline.cli import build_parser

    parser = build_parser()
    verbs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    tried = []
    for verb, sub in verbs.items():
        for action in sub._actions:
            verb_own = getattr(action.type, "__name__", "") in ("positive_int", "non_negative_int") and \
                not hasattr(action.type, "kind")  # a declared setting's type holds it to its declared range
            if verb_own and action.option_strings:
                flag = action.option_strings[-1]
                code, out, err = run_main(verb, flag, "99999999999999999999")
                assert code == 2 and "Traceback" not in err, (verb, flag, err)
                (line,) = err.strip().splitlines()
                assert "must be within [" in line and "got 99999999999999999999" in line, (verb, flag, line)
                tried.append(f"{verb} {flag}")
    assert {"runs --limit", "audit --episodes", "sql --max-rows", "view --iteration"} <= set(tried), tried
