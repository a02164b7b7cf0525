"""Corrupt stores: a one-line error (exit 2) from every command, a report from the doctor, no appends.

Damage tried: random bytes, a real store cut to half its length, a real store with a table dropped, and one
with a view dropped. Every command refuses with one line on stderr; ``codearcade doctor`` reports the damage of
a file it can open as findings (exit 1), with no traceback; ``codearcade eval`` never writes to the file.
"""

from __future__ import annotations

import os
import shutil

import duckdb
import pytest

from pipeline.cli import main
from tests.conftest import EXAMPLES


@pytest.fixture(scope="module")
def sound(tmp_path_factory):
    path = tmp_path_factory.mktemp("sound") / "sound.duckdb"
    assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "60", "--store", str(path)]) == 0
    run_id = duckdb.connect(str(path), read_only=True).execute("SELECT run_id FROM runs").fetchone()[0]
    return path, run_id


def _damage(kind: str, sound_path, target) -> None:
    if kind == "random bytes":
        target.write_bytes(os.urandom(300_000))
    elif kind == "truncated":
        data = sound_path.read_bytes()
        target.write_bytes(data[: len(data) // 2])
    else:
        shutil.copy(sound_path, target)
        with duckdb.connect(str(target)) as con:
            con.execute("DROP TABLE steps" if kind == "table dropped" else "DROP VIEW run_summary")


DAMAGE = ["random bytes", "truncated", "table dropped", "view dropped"]
OPENABLE = {"truncated", "table dropped", "view dropped"}


def _commands(path, run_id) -> list[list[str]]:
    store = ["--store", str(path)]
    return [
        ["eval", str(EXAMPLES / "pong.py"), "--max-steps", "20", *store],
        ["sql", "SELECT count(*) FROM runs", *store],
        ["runs", *store],
        ["report", run_id, "--out", str(path.parent / "report"), *store],
        ["replay", run_id, *store],
        ["optimize", "--resume", run_id, *store],
    ]


@pytest.mark.parametrize("kind", DAMAGE)
def test_every_command_refuses_a_damaged_store_in_one_line(kind, sound, tmp_path, capsys):
    sound_path, run_id = sound
    path = tmp_path / "damaged.duckdb"
    _damage(kind, sound_path, path)
    before = path.read_bytes()
    for argv in _commands(path, run_id):
        code = main(argv)
        out, err = capsys.readouterr()
        assert code == 2, (kind, argv[0], out, err)
        assert len(err.strip().splitlines()) == 1 and err.startswith("codearcade: error: "), (kind, argv[0], err)
        assert path.read_bytes() == before, f"{argv[0]} wrote to the damaged store"
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize("kind", DAMAGE)
def test_the_doctor_reports_damage_as_findings(kind, sound, tmp_path, capsys):
    sound_path, _ = sound
    path = tmp_path / "damaged.duckdb"
    _damage(kind, sound_path, path)
    code = main(["doctor", "--store", str(path)])
    out, err = capsys.readouterr()
    if kind in OPENABLE:
        assert code == 1, (out, err)
        assert "PROBLEM: damaged file" in out and "Traceback" not in out + err
        expected = {"truncated": "truncated", "table dropped": "table steps", "view dropped": "view run_summary"}
        assert expected[kind] in out
    else:
        assert code == 2 and len(err.strip().splitlines()) == 1


def test_a_sound_store_passes_the_checks_after_many_writes(sound, tmp_path, capsys):
    path = tmp_path / "copy.duckdb"
    shutil.copy(sound[0], path)
    for _ in range(3):
        assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "30", "--store", str(path)]) == 0
    assert main(["doctor", "--store", str(path)]) == 0
    assert "ok: no damage found" in capsys.readouterr().out


@pytest.mark.parametrize("kept", [0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.97])
def test_a_store_cut_anywhere_is_reported_truncated(kept, sound, tmp_path, capsys):
    """Wherever a copy is cut, the doctor finds it truncated (exit 1) and other commands refuse it in one line:
    a cut that keeps what DuckDB reads to open the file by the used blocks its header counts, one that does not
    by the read past the end that DuckDB fails with (with 64 KiB blocks the catalog of a small store may lie in
    its second half)."""
    data = sound[0].read_bytes()
    path = tmp_path / "cut.duckdb"
    path.write_bytes(data[: int(len(data) * kept)])
    code = main(["doctor", "--store", str(path)])
    out, err = capsys.readouterr()
    assert code == 1 and "PROBLEM: damaged file" in out and "truncated" in out, (out, err)
    assert main(["runs", "--store", str(path)]) == 2
    out, err = capsys.readouterr()
    assert len(err.strip().splitlines()) == 1 and "is damaged: the file is truncated" in err, err


def test_a_cut_store_whose_data_lies_past_its_used_blocks_is_refused(tmp_path, capsys):
    """The check compared the file's length with the used blocks DuckDB counts, as if they were at its front. A
    store that has freed blocks in its middle (here a big table made and dropped between two evaluations; over
    time, rows deleted and rewritten) holds data further out, and a copy cut past its used blocks but before that
    data passed the check: DuckDB then failed on its read past the end, or, where what was cut lay in a table the
    command did not read, the command appended to the file and left it worse (a failed checkpoint and a WAL beside
    it: found by hand on a store of 45 blocks cut at 34). The check now finds the cut, before DuckDB reads
    anything, wherever between the two it is; nothing is written to the file."""
    path = tmp_path / "s.duckdb"
    assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "20", "--store", str(path)]) == 0
    with duckdb.connect(str(path)) as con:  # blocks in the middle, freed once the data after them is written
        con.execute("CREATE TABLE filler AS SELECT range AS x, md5(range::VARCHAR) AS y FROM range(300000)")
    assert main(["eval", str(EXAMPLES / "pong.py"), "--episodes", "2", "--max-steps", "1500", "--store",
                 str(path)]) == 0
    with duckdb.connect(str(path)) as con:
        con.execute("DROP TABLE filler")
        con.execute("CHECKPOINT")
        block, used, total = con.execute("SELECT block_size, used_blocks, total_blocks FROM pragma_database_size() "
                                         "WHERE database_name = current_database()").fetchone()
    capsys.readouterr()
    data = path.read_bytes()
    header = 3 * 4096
    assert total > used + 4, (used, total)  # the freed blocks are in the middle: DuckDB did not cut them off
    for cut in (header + block * used, header + block * (used + total) // 2, len(data) - block):
        path.write_bytes(data[:cut])
        assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "20", "--store", str(path)]) == 2
        out, err = capsys.readouterr()
        if cut < len(data) - block:  # found by the check, before DuckDB reads what is gone
            assert "is damaged: the file is truncated" in err, (cut, out, err)
        else:  # the catalog's own blocks at the end: DuckDB's read of them fails first, said as damage
            assert err.startswith("codearcade: error: ") and "damaged" in err, (cut, out, err)
        assert path.read_bytes() == data[:cut] and not (tmp_path / "s.duckdb.wal").exists(), cut


@pytest.mark.skipif(shutil.which("setpriv") is None or os.geteuid() != 0, reason="needs root and setpriv")
def test_a_store_in_a_folder_it_cannot_write_is_refused_in_one_line(sound, tmp_path):
    """A store file that may be written, in a folder that may not: the commit creates the WAL beside the file and
    failed with DuckDB's traceback (exit 1). One line now names the folder; the file is as it was. Run as root
    without the capabilities that pass over file rights (as a user who does not own the folder)."""
    import subprocess
    import sys

    folder = tmp_path / "locked"
    folder.mkdir()
    path = folder / "s.duckdb"
    shutil.copy(sound[0], path)
    before = path.read_bytes()
    folder.chmod(0o555)
    try:
        exe = os.path.join(os.path.dirname(sys.executable), "codearcade")
        done = subprocess.run(["setpriv", "--bounding-set", "-dac_override,-dac_read_search,-fowner", "--", exe,
                               "eval", str(EXAMPLES / "pong.py"), "--max-steps", "20", "--store", str(path)],
                              capture_output=True, text=True, timeout=300)
    finally:
        folder.chmod(0o755)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert done.stderr.strip().splitlines()[-1].startswith(f"codearcade: error: cannot write {path}"), done.stderr
    assert str(folder) in done.stderr and "is not writable" in done.stderr
    assert path.read_bytes() == before and not (folder / "s.duckdb.wal").exists()
