"""The DuckDB store: migrations, locking, errors, batched writes and slice readers."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import duckdb
import pytest

from games import list_widths
from pipeline.play.rollout import run_episode
from pipeline.play.spec import EpisodeSpec
from store import Store, StoreError
from store.migrations import LATEST, MIGRATIONS
from store.readers import episode_steps, run_episodes, step_nodes
from store.writer import EpisodeWriter, put_blob, write_episode
from tests.conftest import EXAMPLES
from tracing.capture import NODE_SCHEMA
from tracing.steps import STEP_SCHEMA

ROOT = Path(__file__).resolve().parents[1]


def test_migrations_are_recorded_once(store):
    with store.write():
        pass
    with store.write():
        pass
    rows = store.query("SELECT version, name FROM schema_migrations ORDER BY version")
    assert [r[0] for r in rows] == [m[0] for m in MIGRATIONS] and rows[-1][0] == LATEST


def test_arrow_schemas_match_tables(store):
    with store.write():
        pass
    for table, schema, added in (("steps", STEP_SCHEMA, {"episode_id"}),
                                 ("nodes", NODE_SCHEMA, {"episode_id", "policy_version_id"})):
        columns = {r[0] for r in store.query(f"SELECT column_name FROM information_schema.columns WHERE table_name = '{table}'")}
        assert columns == set(schema.names) | added


def test_schema_doc_names_every_column(store):
    doc = (ROOT / "docs" / "schema.md").read_text()
    with store.write():
        pass
    for table, column in store.query(
        "SELECT table_name, column_name FROM information_schema.columns WHERE table_schema = 'main'"
    ):
        assert re.search(rf"`{column}`", doc), f"docs/schema.md does not describe {table}.{column}"


def test_newer_schema_is_refused(store):
    with store.write() as con:
        con.execute("INSERT INTO schema_migrations VALUES (?, 'from the future', now())", [LATEST + 1])
    with pytest.raises(StoreError, match="newer than this codearcade"):
        with store.read():
            pass


def test_not_a_duckdb_file(tmp_path):
    path = tmp_path / "notes.duckdb"
    path.write_text("these are my notes\n" * 100)
    with pytest.raises(StoreError, match="not a codearcade store"):
        with Store(path).write():
            pass
    assert path.read_text().startswith("these are my notes"), "the file is left as it was"


def test_missing_store_for_reading(tmp_path):
    with pytest.raises(StoreError, match="no store at"):
        Store(tmp_path / "none.duckdb").query("SELECT 1")


def test_missing_directory(tmp_path):
    with pytest.raises(StoreError, match="does not exist"):
        with Store(tmp_path / "no" / "such" / "dir.duckdb").write():
            pass


def test_reader_waits_for_a_writer_in_another_process(store):
    with store.write() as con:
        put_blob(con, "note", "hello")
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import duckdb, sys, time; c = duckdb.connect(sys.argv[1]); print('held', flush=True); time.sleep(1.5)",
         str(store.path)],
        stdout=subprocess.PIPE, text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    start = time.monotonic()
    assert store.query("SELECT text FROM blobs")[0][0] == "hello"
    waited = time.monotonic() - start
    holder.wait(10)
    assert waited > 0.5, "the read had to wait for the other process to let go"


def test_lock_timeout_is_a_clear_error(tmp_path):
    path = tmp_path / "locked.duckdb"
    duckdb.connect(str(path)).close()
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import duckdb, sys, time; c = duckdb.connect(sys.argv[1]); print('held', flush=True); time.sleep(10)",
         str(path)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(StoreError, match="stayed locked"):
            Store(path, lock_timeout_s=0.5).query("SELECT 1")
    finally:
        holder.kill()
        holder.wait()


def test_blobs_are_content_addressed(store):
    with store.write() as con:
        a = put_blob(con, "prompt", "same text")
        b = put_blob(con, "prompt", "same text")
    assert a == b
    assert store.query("SELECT count(*) FROM blobs")[0][0] == 1


def test_episode_roundtrip_and_slices(store):
    text = (EXAMPLES / "breakout.py").read_text()
    outcome = run_episode(EpisodeSpec("ep", "run", "breakout", text, "v1", max_steps=120, trace=True))
    with store.write() as con:
        write_episode(con, outcome.episode, outcome.steps, outcome.nodes)
        write_episode(con, outcome.episode, outcome.steps, outcome.nodes, replace=True)  # a re-played episode
    assert store.query("SELECT count(*) FROM steps")[0][0] == 120
    assert store.query("SELECT count(*) FROM nodes")[0][0] == 120 * 3
    with store.read() as con:
        rows = episode_steps(con, "ep", 10, 20, list_widths=list_widths("breakout"))
        nodes = step_nodes(con, "ep", 10, 12)
        episodes = run_episodes(con, "run")
    originals = outcome.steps.slice(10, 10).to_pylist()
    assert [r["step"] for r in rows] == list(range(10, 20))
    from tracing.steps import objects_to_obs

    for row, original in zip(rows, originals):
        assert row["obs"] == objects_to_obs(original["objects"], list_widths("breakout"))
        assert len(row["obs"]["RB"]) + len(row["obs"]["BB"]) > 0
    assert [(n["step"], n["call_index"]) for n in nodes] == [(10, 0), (10, 1), (10, 2), (11, 0), (11, 1), (11, 2)]
    assert nodes[2]["parents"] == [1] and nodes[1]["parents"] == [0]
    assert episodes[0]["length"] == 120 and episodes[0]["end_reason"] == "truncated"


def test_episode_writer_groups_episodes_and_lets_other_processes_in_between(store):
    """EpisodeWriter: episodes queued within ``every_s`` go in one write; the file is free for another process
    between writes; a run's end lands with the last group; a re-played group replaces its rows."""
    text = (EXAMPLES / "breakout.py").read_text()
    outcomes = [run_episode(EpisodeSpec(f"ep{i}", "run", "breakout", text, "v1", seed=i, max_steps=30))
                for i in range(3)]
    with store.write() as con:
        con.execute("INSERT INTO runs (run_id, created_at, kind, game, config, status) VALUES ('run', now(), 'eval', "
                    "'breakout', '{}', 'running')")
    writer = EpisodeWriter(store, every_s=3600)
    writer.add(outcomes[0].episode, outcomes[0].steps, outcomes[0].nodes)
    writer.add(outcomes[1].episode, outcomes[1].steps, outcomes[1].nodes)
    assert store.query("SELECT count(*) FROM episodes") == [(0,)], "queued, not yet written"
    other = subprocess.run([sys.executable, "-c", "import duckdb, sys; c = duckdb.connect(sys.argv[1]); "
                            "print(c.execute('SELECT count(*) FROM episodes').fetchone()[0])", str(store.path)],
                           capture_output=True, text=True, timeout=60)
    assert other.stdout.strip() == "0", other.stderr
    writer.every_s = 0.0
    writer.add(outcomes[2].episode, outcomes[2].steps, outcomes[2].nodes)  # the last write is old: all three go
    assert store.query("SELECT count(*), sum(length) FROM episodes") == [(3, 90)]
    writer.every_s = 3600
    writer.add(outcomes[2].episode, outcomes[2].steps, outcomes[2].nodes)
    with pytest.raises(duckdb.ConstraintException):  # a fresh writer never deletes: the same episode twice fails
        writer.flush()
    with EpisodeWriter(store, replace=True, every_s=3600) as again:
        again.add(outcomes[2].episode, outcomes[2].steps, outcomes[2].nodes)
        again.flush(also=lambda con: con.execute("UPDATE runs SET status = 'finished' WHERE run_id = 'run'"))
    assert store.query("SELECT count(*) FROM steps") == [(90,)], "replaced, not duplicated"
    assert store.query("SELECT status FROM runs") == [("finished",)]


def test_unrelated_duckdb_database_is_refused_and_untouched(tmp_path):
    path = tmp_path / "analytics.duckdb"
    con = duckdb.connect(str(path))
    con.execute("CREATE TABLE sales (amount INTEGER)")
    con.close()
    for use in (lambda s: s.query("SELECT 1"), lambda s: s.write().__enter__()):
        with pytest.raises(StoreError, match="not a codearcade store"):
            use(Store(path))
    con = duckdb.connect(str(path), read_only=True)
    assert [r[0] for r in con.execute("SELECT table_name FROM information_schema.tables").fetchall()] == ["sales"]
    con.close()


def test_an_insert_that_fails_keeps_its_own_error_and_leaves_the_store_usable(store):
    """An INSERT from an Arrow table that fails inside a transaction aborts it, and unregistering the table then
    raises a TransactionException of its own: the insert's error (here a constraint; a Ctrl-C is an interrupted
    query the same way) must be the one the command sees, and the store must take the same rows afterwards."""
    import duckdb
    import pyarrow as pa

    from store.incoming import insert_arrow

    twice = pa.table({"hash": ["h", "h"], "content": ["a", "a"]})
    with pytest.raises(duckdb.ConstraintException):
        with store.write() as con:
            con.execute("CREATE TEMP TABLE unique_blobs (hash VARCHAR PRIMARY KEY, content VARCHAR)")
            insert_arrow(con, "incoming_rows", twice, "INSERT INTO unique_blobs SELECT * FROM incoming_rows")
    with store.write() as con:
        con.execute("CREATE TEMP TABLE unique_blobs (hash VARCHAR PRIMARY KEY, content VARCHAR)")
        insert_arrow(con, "incoming_rows", twice.slice(0, 1), "INSERT INTO unique_blobs SELECT * FROM incoming_rows")
        assert con.execute("SELECT count(*) FROM unique_blobs").fetchone() == (1,)


class _PressedWhileRead:
    """An Arrow stream that Ctrl-C interrupts as DuckDB reads it: DuckDB calls into Python for the schema, the
    KeyboardInterrupt is raised there, and DuckDB wraps it in an error of its own."""

    def __arrow_c_stream__(self, requested_schema=None):
        raise KeyboardInterrupt


def _python_function_pressed(x: int) -> int:
    raise KeyboardInterrupt


@pytest.mark.parametrize("where", ["registering an Arrow table", "a Python function in a query"])
def test_a_ctrl_c_while_duckdb_calls_python_is_a_ctrl_c_and_rolls_the_write_back(store, where):
    """A Ctrl-C can land while DuckDB is inside Python it called (a CI run pressed Ctrl-C while an evaluation's
    steps were being registered): DuckDB raises it as ``InvalidInputException ... failed: KeyboardInterrupt:``.
    The store gives it back as the KeyboardInterrupt it was, so the command winds down as after any Ctrl-C (exit
    130, the run interrupted), and the transaction it cut leaves nothing behind. An error that merely mentions the
    word is still the error it is."""
    with store.write():
        pass
    with pytest.raises(KeyboardInterrupt):
        with store.write() as con:
            con.execute("INSERT INTO blobs (hash, kind, text, chars) VALUES ('before', 'prompt', 'x', 1)")
            if where == "registering an Arrow table":
                con.register("incoming_steps", _PressedWhileRead())
            else:
                con.create_function("pressed", _python_function_pressed, ["BIGINT"], "BIGINT")
                con.execute("SELECT pressed(1)").fetchall()
    assert store.query("SELECT count(*) FROM blobs WHERE hash = 'before'") == [(0,)], "rolled back"
    with pytest.raises(duckdb.ConversionException):
        with store.write() as con:
            con.execute("SELECT 'failed: KeyboardInterrupt:'::INTEGER")


def test_a_store_upgraded_by_any_verb_says_so_once(tmp_path, capsys):
    """Opening an older store upgrades it for good (an older codearcade then refuses it), even from a verb that
    only reads (`runs`): a reviewer saw the file change with nothing said. One line on stderr says it, the first
    time only; a new store is made without a word."""
    import gzip
    import shutil

    path = tmp_path / "old.duckdb"
    with gzip.open(ROOT / "tests" / "fixtures" / "greedy_run.duckdb.gz") as packed, open(path, "wb") as out:
        shutil.copyfileobj(packed, out)
    runs = [sys.executable, "-m", "pipeline.cli", "runs", "--store", str(path)]
    first, again = (subprocess.run(runs, cwd=ROOT, capture_output=True, text=True, timeout=120) for _ in range(2))
    assert first.returncode == again.returncode == 0, first.stderr
    said = [line for line in first.stderr.splitlines() if "upgrading" in line]
    assert len(said) == 1 and f"to {LATEST}" in said[0] and "older codearcade will refuse" in said[0], first.stderr
    assert "upgrading" not in again.stderr
    with Store(tmp_path / "new.duckdb").write():
        pass
    assert capsys.readouterr().err == ""


def test_a_ctrl_c_while_a_hold_checkpoints_is_a_ctrl_c(store, monkeypatch):
    """The optimizer lets its hold on the store go (detaching it: the checkpoint) as its run ends. A CI run pressed
    Ctrl-C right then, and DuckDB's ``Query interrupted`` left a traceback in a batch run's log instead of the line
    ``interrupted``: the hold gives a press back as the KeyboardInterrupt it was; a full disk stays ignored there
    and any other error stays itself."""
    import store.db as db

    real_release = db.HUB.release

    def interrupted(path, cursor):
        real_release(path, cursor)
        raise RuntimeError("Query interrupted")

    hold = db.Hold(store)
    hold.take()
    monkeypatch.setattr(db.HUB, "release", interrupted)
    with pytest.raises(KeyboardInterrupt):
        hold.release()
    monkeypatch.undo()
    assert store.query("SELECT count(*) FROM runs") == [(0,)], "the store is usable after it"

    def failed(path, cursor):
        real_release(path, cursor)
        raise RuntimeError("something else")

    hold.take()
    monkeypatch.setattr(db.HUB, "release", failed)
    with pytest.raises(RuntimeError, match="something else"):
        hold.release()
