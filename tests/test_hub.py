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
