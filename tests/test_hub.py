"""The process's DuckDB instance that store files are attached to (store/hub.py)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from store import Store
from store.hub import HUB
from store.writer import put_blob

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_the_file_is_released_after_each_use(tmp_path):
    store = Store(tmp_path / "s.duckdb")
    with store.write() as con:
        put_blob(con, "note", "first")
    # another process can write at once: the file was detached, its lock released
    script = ("import sys\nfrom store import Store\nfrom store.writer import put_blob\n"
              "with Store(sys.argv[1], write_lock_timeout_s=0.1, lock_timeout_s=0.1).write() as con:\n"
              "    put_blob(con, 'note', 'second')\n")
    done = subprocess.run([sys.executable, "-c", script, str(store.path)], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert store.query("SELECT count(*) FROM blobs") == [(2,)]
    assert not os.path.exists(f"{store.path}.wal"), "detaching checkpoints the file"


def test_a_read_inside_a_write_shares_the_attachment_and_sees_the_open_transaction(tmp_path):
    store = Store(tmp_path / "s.duckdb")
    with store.write() as con:
        put_blob(con, "note", "inside")
        with store.read() as reader:
            assert reader.execute("SELECT count(*) FROM blobs").fetchone()[0] >= 0
    with store.read() as reader:
        with pytest.raises(RuntimeError, match="cannot nest inside a read"):
            with store.write():
                pass
        assert reader.execute("SELECT count(*) FROM blobs").fetchone() == (1,)


def test_an_idle_instance_is_closed_before_a_fork(tmp_path):
    store = Store(tmp_path / "s.duckdb")
    with store.write():
        pass
    assert HUB._con is not None
    pid = os.fork()
    if pid == 0:  # the child: the parent's instance is forgotten, a store opens with a fresh one
        try:
            ok = HUB._con is None and store.query("SELECT count(*) FROM runs") == [(0,)]
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WEXITSTATUS(status) == 0
    assert HUB._con is None, "closed before the fork: no DuckDB thread is forked"
    assert store.query("SELECT count(*) FROM runs") == [(0,)]


def test_appended_rows_go_into_small_row_groups(tmp_path):
    """Small row groups keep every commit's checkpoint small (store.hub.WRITE_ROW_GROUP_SIZE)."""
    from store.hub import WRITE_ROW_GROUP_SIZE

    store = Store(tmp_path / "s.duckdb")
    for batch in range(3):  # separate commits, as episodes are written
        with store.write() as con:
            con.execute("INSERT INTO steps BY NAME SELECT 'e' || ? AS episode_id, i AS step, 0.0 AS reward, "
                        "0.0 AS score, false AS terminated, false AS truncated FROM range(?) t(i)",
                        [batch, WRITE_ROW_GROUP_SIZE])
    rows_per_group = store.query(
        "SELECT max(count) FROM (SELECT row_group_id, max(count) AS count FROM pragma_storage_info('steps') "
        "GROUP BY row_group_id)")[0][0]
    assert store.query("SELECT count(*) FROM steps") == [(3 * WRITE_ROW_GROUP_SIZE,)]
    assert rows_per_group <= WRITE_ROW_GROUP_SIZE


def _pong_like_steps(n: int, seed: int):
    """``n`` step rows of a three-object observation that moves as Pong's does (deterministic per ``seed``)."""
    import numpy as np

    from tracing.steps import StepLog

    log, rng = StepLog(), np.random.default_rng(seed)
    for i in range(n):
        obs = {"Player": {"x": 140, "y": int(50 + 30 * np.sin(i / 9)), "w": 4, "h": 15, "dx": 0, "dy": 1},
               "Ball": {"x": i * 3 % 160, "y": i * 5 % 200, "w": 2, "h": 4, "dx": 3, "dy": 5},
               "Enemy": {"x": 16, "y": int(rng.integers(30, 190)), "w": 4, "h": 15, "dx": 0,
                         "dy": int(rng.integers(-4, 5))}}
        log.append(i, obs, int(rng.integers(0, 6)), 0.0, 0.0, False, False, None)
    return log.table()


@pytest.mark.slow
@pytest.mark.parametrize("steps_per_write", [500, 2000])
def test_a_store_written_episode_by_episode_stays_small(tmp_path, steps_per_write):
    """Each write commits and checkpoints, and DuckDB fills the blocks a checkpoint starts only within it: with
    DuckDB's 256 KiB blocks every write left its own partly filled blocks (170 and 147 bytes a step here); the
    64 KiB blocks of a new store (store.hub.NEW_STORE_BLOCK_SIZE) leave a quarter of that (39 and 37)."""
    from store.writer import write_episode

    path = tmp_path / "s.duckdb"
    store = Store(path)

    def episode(i: int) -> dict:
        return {"episode_id": f"r.0.eval.{i}", "run_id": "r", "iteration": 0, "kind": "eval", "episode_index": i,
                "game": "pong", "policy_version_id": "v", "return": 0.0, "length": steps_per_write,
                "lives_lost": 0, "end_reason": "terminated", "traced": False, "duration_s": 1.0}

    with store.write() as con:  # the first write: every table it touches claims its first blocks
        write_episode(con, episode(0), _pong_like_steps(steps_per_write, 0), None)
    before = os.path.getsize(path)
    writes = 40
    for i in range(1, writes + 1):
        with store.write() as con:
            write_episode(con, episode(i), _pong_like_steps(steps_per_write, i), None)
    per_step = (os.path.getsize(path) - before) / (writes * steps_per_write)
    assert per_step <= 60, f"{per_step:.0f} bytes a step"


def test_a_new_store_gets_the_small_blocks_and_an_old_one_keeps_its_own(tmp_path):
    """Block size is fixed when a file is made: a new store gets store.hub.NEW_STORE_BLOCK_SIZE, a store made with
    DuckDB's default (every store before issue 40) keeps 256 KiB blocks and is read and written as before."""
    import duckdb

    from store.hub import NEW_STORE_BLOCK_SIZE

    new = Store(tmp_path / "new.duckdb")
    with new.write():
        pass
    assert new.query("SELECT block_size FROM pragma_database_size() WHERE database_name = current_database()") \
        == [(NEW_STORE_BLOCK_SIZE,)]
    duckdb.connect(str(tmp_path / "old.duckdb")).close()  # DuckDB's default block size
    old = Store(tmp_path / "old.duckdb")
    with old.write() as con:
        put_blob(con, "note", "written")
    assert old.query("SELECT block_size FROM pragma_database_size() WHERE database_name = current_database()") \
        == [(262144,)]
    assert old.query("SELECT text FROM blobs WHERE kind = 'note'") == [("written",)]
