"""A run's rows as Arrow tables: to ship a run to another machine and back (the Ray executor).

:func:`export_run` collects every row that belongs to one run, in the store's own format: its ``runs`` row,
policy versions with their lines (blame), iterations and their candidates, feedback, LLM calls, episodes with
their steps and nodes, and the blobs they reference. :func:`import_run` writes such a bundle into a store in one
transaction, replacing any earlier rows of the same run, so a run finished elsewhere lands whole or not at all,
and never twice.
"""

from __future__ import annotations

import duckdb
import pyarrow as pa

from store.incoming import insert_arrow

Bundle = dict[str, pa.Table]

RUN_TABLES = ("runs", "policy_versions", "policy_lines", "iterations", "candidates", "feedback", "llm_calls",
              "audits", "episodes")
EPISODE_TABLES = ("steps", "nodes")

_BLOB_HASHES = """
    SELECT starter_policy_hash AS hash FROM runs WHERE run_id = $run
    UNION SELECT source_hash FROM policy_versions WHERE run_id = $run
    UNION SELECT f.source_hash FROM (SELECT unnest(functions) AS f FROM policy_versions WHERE run_id = $run)
    UNION SELECT prompt_hash FROM llm_calls WHERE run_id = $run
    UNION SELECT reply_hash FROM llm_calls WHERE run_id = $run
    UNION SELECT suggestion_hash FROM llm_calls WHERE run_id = $run
    UNION SELECT feedback_hash FROM candidates WHERE run_id = $run
"""


def export_run(con: duckdb.DuckDBPyConnection, run_id: str) -> Bundle:
    bundle: Bundle = {}
    for table in RUN_TABLES:
        bundle[table] = con.execute(f"SELECT * FROM {table} WHERE run_id = $run", {"run": run_id}).to_arrow_table()
    for table in EPISODE_TABLES:
        bundle[table] = con.execute(
            f"SELECT * FROM {table} WHERE episode_id IN (SELECT episode_id FROM episodes WHERE run_id = $run)",
            {"run": run_id}).to_arrow_table()
    bundle["blobs"] = con.execute(f"SELECT * FROM blobs WHERE hash IN ({_BLOB_HASHES})",
                                  {"run": run_id}).to_arrow_table()
    return bundle


def run_ids(bundle: Bundle) -> list[str]:
    return bundle["runs"].column("run_id").to_pylist()


def delete_run(con: duckdb.DuckDBPyConnection, run_id: str) -> None:
    """Remove every row of a run (blobs stay: they may be shared)."""
    for table in EPISODE_TABLES:
        con.execute(f"DELETE FROM {table} WHERE episode_id IN (SELECT episode_id FROM episodes WHERE run_id = ?)",
                    [run_id])
    for table in reversed(RUN_TABLES):
        con.execute(f"DELETE FROM {table} WHERE run_id = ?", [run_id])


def import_run(con: duckdb.DuckDBPyConnection, bundle: Bundle) -> None:
    """Write ``bundle`` (call inside ``store.write()``: one transaction), replacing the run's earlier rows."""
    for run_id in run_ids(bundle):
        delete_run(con, run_id)
    for name, table in bundle.items():
        if table.num_rows == 0:
            continue
        conflict = " ON CONFLICT DO NOTHING" if name == "blobs" else ""
        insert_arrow(con, "incoming_rows", table, f"INSERT INTO {name} BY NAME SELECT * FROM incoming_rows{conflict}")
