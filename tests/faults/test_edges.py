"""Bad inputs at the edges: each a one-line actionable error, and nothing already stored is lost."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.cli import main
from store import Store
from store.migrations import LATEST
from tests.conftest import EXAMPLES, said


def _eval(capsys, store_path, *extra):
    code = main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "40", "--store", str(store_path), *extra])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(err: str) -> str:
    lines = said(err)  # besides the progress of the episodes played before the disk filled
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture
def tmpfs(tmp_path):
    """A small tmpfs of our own (needs mount rights: root in a container; skipped elsewhere)."""
    mountpoint = tmp_path / "small"
    mountpoint.mkdir()

    def mount(size: str, read_only: bool = False) -> Path:
        options = f"size={size}" + (",ro" if read_only else "")
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(mountpoint)], capture_output=True)
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
        return mountpoint

    yield mount
    # lazy: a file something still holds there (a run's log closing as the test ends) made a plain umount fail
    # now and then, and the tmpfs stayed mounted under pytest's temporary folder, which it can then not remove
    subprocess.run(["umount", "-l", str(mountpoint)], capture_output=True)


def _fill(path: Path) -> None:
    """Fill the disk of ``path`` to its last byte (unbuffered: a buffer's close would raise what it could not
    write)."""
    with open(path, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError:
            pass


def test_store_that_is_not_duckdb(tmp_path, capsys):
    path = tmp_path / "notes.duckdb"
    path.write_bytes(b"\x89PNG not a database" * 100)
    code, _, err = _eval(capsys, path)
    assert code == 2 and "not a codearcade store" in _one_line(err)
    assert path.read_bytes().startswith(b"\x89PNG"), "the file is untouched"


def test_store_from_a_newer_schema(store, capsys):
    assert _eval(capsys, store.path)[0] == 0
    with store.write() as con:
        con.execute("INSERT INTO schema_migrations VALUES (?, 'from the future', now())", [LATEST + 1])
    code, _, err = _eval(capsys, store.path)
    assert code == 2 and "upgrade codearcade" in _one_line(err)


def test_read_only_directory(tmpfs, capsys):
    directory = tmpfs("1m", read_only=True)
    code, _, err = _eval(capsys, directory / "store.duckdb")
    assert code == 2
    line = _one_line(err)
    assert "store.duckdb" in line and ("writable" in line or "Read-only" in line)


@pytest.mark.slow
def test_full_disk_keeps_what_was_stored(tmpfs, capsys):
    directory = tmpfs("6m")
    path = directory / "store.duckdb"
    stored, failure = 0, None
    for _ in range(40):
        code = main(["eval", str(EXAMPLES / "space_invaders.py"), "--trace", "--max-steps", "600", "--store", str(path)])
        out, err = capsys.readouterr()
        if code != 0:
            failure = _one_line(err)
            break
        stored += 1
    assert failure is not None, "the 6 MB disk filled up"
    assert "the disk is full" in failure and "intact" in failure
    assert stored >= 1
    store = Store(path)
    complete = store.query("SELECT count(*) FROM episodes e WHERE length = (SELECT count(*) FROM steps s "
                           "WHERE s.episode_id = e.episode_id)")[0][0]
    assert complete >= stored, "every episode stored before the disk filled is still whole"


def test_experiment_file_with_a_typo(tmp_path, capsys):
    path = tmp_path / "typo.toml"
    path.write_text("[defaults]\niterations = 2\nmodle = 'openai/gpt-4o'\n[matrix]\ngame = ['pong']\n")
    code = main(["batch", str(path), "--dry-run", "--store", str(tmp_path / "s.duckdb")])
    _, err = capsys.readouterr()
    assert code == 2 and "did you mean 'model'" in _one_line(err)


def test_resume_of_a_run_that_does_not_exist(store, capsys):
    assert _eval(capsys, store.path)[0] == 0
    code = main(["optimize", "--resume", "01NOSUCHRUN", "--store", str(store.path)])
    _, err = capsys.readouterr()
    assert code == 2 and "no run 01NOSUCHRUN" in _one_line(err)


@pytest.mark.parametrize("free_kb", [40, 120, 260])
def test_a_store_made_on_a_full_disk_is_made_whole_or_not_at_all(tmpfs, capsys, free_kb):
    """A new store whose disk filled up while its schema was made was left at schema version 2 (each migration
    committed on its own), and the next command, once there was room, "upgraded" it from version 2. The schema is
    now made in one transaction: after the one-line error, the next command finds no schema or the whole of it,
    never part, and says nothing of an upgrade."""
    directory = tmpfs("3m")
    filler = directory / "filler"
    with open(filler, "wb") as f:  # all but free_kb of the disk
        try:
            f.write(b"\0" * (3 * 2**20 - free_kb * 1024))
        except OSError:
            pass
    path = directory / "s.duckdb"
    code, _, err = _eval(capsys, path)
    assert code == 2 and "the disk is full" in _one_line(err), err
    filler.unlink()
    if path.exists():
        assert main(["runs", "--store", str(path)]) in (0, 2)
        _, err = capsys.readouterr()
        assert "upgrading" not in err, err
    code, _, err = _eval(capsys, path)
    assert code == 0 and "upgrading" not in err, err
    from store.migrations import MIGRATIONS

    assert [v for (v,) in Store(path).query("SELECT version FROM schema_migrations ORDER BY version")] == \
        [m[0] for m in MIGRATIONS]


def test_a_report_cut_short_by_a_full_disk_leaves_no_file_that_looks_whole(tmpfs, tmp_path, capsys):
    """`report` wrote its plots and README.md under their own names: a disk that filled as a file was written left
    it cut short there (a PNG's last block missing, an empty README.md), beside a one-line error. Each file is now
    written as FILE.partial and renamed once whole: whatever the free space, every file the failed report leaves
    is byte for byte the one a report with room writes, and no partial file is left."""
    store = tmp_path / "s.duckdb"
    assert main(["eval", str(EXAMPLES / "pong.py"), "--episodes", "2", "--max-steps", "40", "--store", str(store)]) == 0
    whole = tmp_path / "whole"
    assert main(["report", "last", "--store", str(store), "--out", str(whole)]) == 0
    capsys.readouterr()
    expected = {p.name: p.read_bytes() for p in whole.iterdir()}
    assert sorted(expected) == ["README.md", "score.png"]
    directory = tmpfs("1m")
    sizes = sum(len(b) for b in expected.values())
    # free space from none to a little less than both files: each file in turn is cut, at its start or further on
    for free in sorted({0, 4096, len(expected["score.png"]) // 2, len(expected["score.png"]) - 1,
                        len(expected["score.png"]) + 1, sizes - 1}):
        filler = directory / "filler"
        with open(filler, "wb") as f:
            try:
                f.write(b"\0" * (2**20 - free))
            except OSError:
                pass
        out = directory / f"report{free}"
        code = main(["report", "last", "--store", str(store), "--out", str(out)])
        _, err = capsys.readouterr()
        if code == 0:  # a tmpfs counts in pages: what is left can hold more than `free`
            assert {p.name: p.read_bytes() for p in out.iterdir()} == expected
        else:
            line = err.strip().splitlines()[-1]  # after the stages it went through
            assert code == 2 and "Traceback" not in err and "No space left on device" in line, err
            assert line.split(": ")[2].endswith(("score.png", "README.md")), line  # the name asked for
            left = {p.name: p.read_bytes() for p in out.iterdir()} if out.exists() else {}
            assert all(expected.get(name) == data for name, data in left.items()), (free, sorted(left))
        filler.unlink()
        subprocess.run(["rm", "-rf", str(out)], check=True)


def test_a_batch_run_that_failed_on_a_full_disk_is_said_with_its_own_line(tmpfs, tmp_path, monkeypatch):
    """A batch's run process wrote its output into its log file, and the batch read the file's last line for why
    the run failed: with the store and the logs on a full disk, the file stayed empty (or stopped mid-traceback),
    and the batch said `failed pong seed=1: exit code 1` (or a line of `^^^^`) where the run had said which file
    it could not write. The batch now reads the run's output itself: its line is said whatever reached the disk,
    with the log that lost it."""
    from pipeline.jobs import batch as batches
    from pipeline.jobs.experiments import load_experiments

    experiments = tmp_path / "full.toml"
    experiments.write_text('name = "full"\n[matrix]\ngame = ["pong"]\nseed = [0, 1]\n')
    loaded = load_experiments(experiments)
    directory = tmpfs("1m")
    logs = directory / "runs"
    logs.mkdir()
    _fill(directory / "filler")
    said = "store.db.StoreError: cannot write /x/s.duckdb: the disk is full (No space left on device)"
    # each run process: the lines of a run that failed on the full disk, a traceback's last line last
    monkeypatch.setattr(batches, "worker_command", lambda *a: [sys.executable, "-c", (
        f"import sys; print('iteration 0: score -5 best -5 initial' * 200, flush=True); print({said!r}); "
        "sys.exit(1)")])
    store = Store(tmp_path / "s.duckdb")
    result = batches.run_local(loaded, store, batches.plan(loaded, store), 1, lambda line: None,
                               lambda progress: None, logs, poll_s=0.1)
    assert [p.state for p in result.progress] == ["failed", "failed"]
    for p in result.progress:
        assert p.note.startswith(said) and "lost lines: No space left on device" in p.note, p.note


def test_a_batch_whose_log_fills_the_disk_goes_on_and_says_so(tmpfs, tmp_path, monkeypatch, scripted, capsys):
    """The batch's own log on a full disk: the batch died at its first line with a traceback (an OSError of the
    log's flush), and, at a later line, with its runs (they die with the batch), each cut off in its iteration.
    The log is not the work: the batch says once that it cannot write it, and runs its runs to their end."""
    from pipeline.jobs import batch as batches

    model = scripted(["{}"])
    experiments = tmp_path / "full.toml"
    experiments.write_text(f'name = "full"\n[defaults]\nmodel = "{model.model}"\napi_base = "{model.api_base}"\n'
                           '[matrix]\ngame = ["pong"]\nseed = [0, 1]\n')
    directory = tmpfs("1m")
    log = directory / "batch.log"
    log.write_text("x" * 4096)  # a whole page: the next line needs another, and the disk has none
    _fill(directory / "filler")
    # each run process: one that finishes (what the batch does with the log is the test, not the runs)
    monkeypatch.setattr(batches, "worker_command", lambda *a: [sys.executable, "-c", "print('finished')"])
    code = main(["batch", str(experiments), "--store", str(tmp_path / "s.duckdb"), "--log", str(log), "--workers",
                 "1"])
    out, err = capsys.readouterr()
    assert code == 0 and "Traceback" not in err, err
    assert f"cannot write the batch's log {log}: No space left on device" in err, err
    assert "batch full done: 2 finished" in out, out


@pytest.mark.slow
def test_a_batch_stops_starting_runs_once_one_finds_the_store_disk_full(tmpfs, tmp_path, scripted, capsys):
    """A batch whose store's disk filled went on starting its remaining runs, each a process (and its zygotes)
    that failed at its first write with the same line. The run process that finds the disk full says the store's
    line (not a traceback) and exits with its own code; the batch starts no more runs, says so once, and exits
    non-zero. Checked by the processes that ran: one run log, not three."""
    from store import Store

    model = scripted(["{}"])
    experiments = tmp_path / "full.toml"
    experiments.write_text(f'name = "full"\n[defaults]\nmodel = "{model.model}"\napi_base = "{model.api_base}"\n'
                           '[matrix]\ngame = ["pong"]\nseed = [0, 1, 2]\n')
    directory = tmpfs("4m")
    store = Store(directory / "s.duckdb")
    with store.write():  # made, with its tables, while there was room
        pass
    _fill(directory / "filler")
    log = tmp_path / "batch.log"
    code = main(["batch", str(experiments), "--store", str(store.path), "--log", str(log), "--workers", "1"])
    out, err = capsys.readouterr()
    started = sorted((tmp_path / "batch.log.runs").glob("*.log"))
    assert len(started) == 1, (started, out)
    said = started[0].read_text()
    assert "the disk is full" in said and "Traceback" not in said, said
    assert code != 0 and "not starting the 2 runs left" in out, out
    assert "1 failed, 2 not started (the store's disk is full)" in out, out
