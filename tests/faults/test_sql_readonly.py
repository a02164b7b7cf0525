"""``codearcade sql`` is read-only for real (store/views.py ``run_user_query``), checked by effect.

Each attack is run through the command line; afterwards every table's row count is what it was, no file
appeared (neither where the attack aimed nor anywhere in the test's folder), and the refusal was one line
with exit code 2. Reading queries of every allowed kind still work.
"""

from __future__ import annotations

import json

import pytest

from pipeline.cli import main
from tests.conftest import EXAMPLES

TABLES = ("runs", "blobs", "policy_versions", "episodes", "steps", "nodes", "iterations", "feedback", "llm_calls",
          "schema_migrations")

ATTACKS = [
    "USE memory; ATTACH '{store}' AS w; DELETE FROM w.steps",
    "ATTACH '{store}' AS w",
    "ATTACH '{dir}/new.duckdb' AS n",
    "ATTACH ':memory:' AS m",
    "COPY (SELECT 1) TO '{dir}/out.csv'",
    "COPY steps TO '{dir}/steps.parquet' (FORMAT parquet)",
    "EXPORT DATABASE '{dir}/export'",
    "SELECT * FROM read_text('{dir}/secret.txt')",
    "SELECT * FROM read_csv('{dir}/secret.txt')",
    "SELECT * FROM glob('{dir}/*')",
    "DELETE FROM steps",
    "DROP TABLE steps",
    "UPDATE episodes SET \"return\" = 1000",
    "INSERT INTO runs (run_id) VALUES ('x')",
    "CREATE TABLE t AS SELECT 1",
    "CREATE TEMP TABLE t AS SELECT 1",
    "SET enable_external_access = true",
    "SET lock_configuration = false; COPY (SELECT 1) TO '{dir}/out.csv'",
    "PRAGMA profiling_output = '{dir}/profile.txt'",
    "INSTALL httpfs",
    "LOAD httpfs",
    "SELECT 1; SELECT 2",
    "-- only a comment",
    "/* nothing */  ",
    "SELEC nonsense",
]

QUERIES = [
    ("SELECT count(*) AS n FROM steps", [{"n": 60}]),
    ("WITH e AS (SELECT * FROM episodes) SELECT count(*) AS n FROM e", [{"n": 1}]),
    ("FROM run_summary SELECT kind", [{"kind": "eval"}]),
    ("SHOW TABLES", None),
    ("DESCRIBE episodes", None),
    ("PRAGMA table_info('episodes')", None),
    ("EXPLAIN SELECT * FROM steps", None),
    ("CALL pragma_version()", None),
    ("SELECT count(*) AS n FROM steps; -- a trailing comment", [{"n": 60}]),
]


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sql")
    path = folder / "store.duckdb"
    assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "60", "--store", str(path)]) == 0
    (folder / "secret.txt").write_text("a,b\n1,2\n")
    return folder, path


def _counts(path) -> dict[str, int]:
    import duckdb

    with duckdb.connect(str(path), read_only=True) as con:
        return {t: con.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in TABLES}


def _files(folder) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@pytest.mark.parametrize("attack", ATTACKS)
def test_an_attack_through_sql_changes_nothing(attack, target, capsys):
    folder, path = target
    before, files = _counts(path), _files(folder)
    code = main(["sql", attack.format(store=path, dir=folder), "--store", str(path)])
    out, err = capsys.readouterr()
    assert code == 2, (attack, out, err)
    assert len(err.strip().splitlines()) == 1 and err.startswith("codearcade: error: "), err
    assert _counts(path) == before, "no row changed"
    assert _files(folder) == files, "no file appeared"


@pytest.mark.parametrize("query, expected", QUERIES, ids=[q for q, _ in QUERIES])
def test_reading_queries_still_work(query, expected, target, capsys):
    _, path = target
    assert main(["sql", query, "--store", str(path), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows
    if expected is not None:
        assert rows == expected
