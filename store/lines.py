"""Line provenance in the store: each version's ``policy_lines`` rows (blame), written and read back.

Design: a version's blame is computed once, when its ``policy_versions`` row is written
(:func:`store.writer.insert_policy_version` calls :func:`write_version_lines` in the same transaction), and
stored, rather than recomputed at query time. It depends on the parent's blame, which is already stored
then (a parent is always written before its children), so each version costs one diff against one parent,
and SQL over ``policy_lines``, ``line_blame``, ``line_coverage`` and ``unrun_lines`` needs nothing else.
A version's blame is fixed by the first row stored for it in the run: a rollback (or any version whose code
recurs) keeps the origins it had, so a rollback carries its target's origins. The LLM call of an origin is
not stored here: the ``line_blame`` view takes it from the ``iterations`` row that evaluated the origin
version (or that iteration's last successful call), so it is right even for rows written before the
iteration's own row. Stores written before migration 7 have versions without lines: :func:`backfill_lines`
fills a run in, in the order its versions were written (``codearcade blame`` calls it).

The diff itself (what is carried, what is new) is :mod:`tracing.blame`'s.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any, Mapping

import duckdb
import pyarrow as pa

from store.incoming import insert_arrow
from store.readers import _rows
from tracing.blame import blame_version

Origin = tuple[str, int, str]
"""``(origin_version_id, origin_iteration, origin_produced_by)``."""

_LINE_SCHEMA = pa.schema([
    ("run_id", pa.string()), ("policy_version_id", pa.string()), ("function", pa.string()),
    ("line_no", pa.int32()), ("text", pa.string()), ("executable", pa.bool_()),
    ("origin_version_id", pa.string()), ("origin_iteration", pa.int32()), ("origin_produced_by", pa.string()),
])


def has_lines(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str) -> bool:
    return con.execute("SELECT count(*) FROM policy_lines WHERE run_id = ? AND policy_version_id = ?",
                       [run_id, version_id]).fetchall()[0][0] > 0


def line_origins(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str) -> dict[str, list[tuple[str, Origin]]]:
    """A version's stored lines per method, in order, as ``(text, origin)``."""
    found: dict[str, list[tuple[str, Origin]]] = defaultdict(list)
    for function, text, *origin in con.execute(
            "SELECT function, text, origin_version_id, origin_iteration, origin_produced_by FROM policy_lines "
            "WHERE run_id = ? AND policy_version_id = ? ORDER BY function, line_no", [run_id, version_id]).fetchall():
        found[function].append((text, tuple(origin)))
    return dict(found)


def write_version_lines(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str, iteration: int,
                        produced_by: str, parent_id: str | None, sources: Mapping[str, str]) -> int:
    """Store the blame of a version's trainable methods (``sources`` by name) against its parent's stored
    lines; nothing if the version already has lines in this run. Returns the rows written."""
    if not sources or has_lines(con, run_id, version_id):
        return 0
    parent = line_origins(con, run_id, parent_id) if parent_id else None
    blamed = blame_version(sources, parent, (version_id, iteration, produced_by))
    rows: dict[str, list[Any]] = {name: [] for name in _LINE_SCHEMA.names}
    for function, lines in blamed.items():
        for line in lines:
            for name, value in zip(_LINE_SCHEMA.names, (run_id, version_id, function, line.line_no, line.text,
                                                        line.executable, *line.origin)):
                rows[name].append(value)
    table = pa.table(rows, schema=_LINE_SCHEMA)
    if table.num_rows:
        insert_arrow(con, "incoming_lines", table,
                     "INSERT OR IGNORE INTO policy_lines BY NAME SELECT * FROM incoming_lines")
    return table.num_rows


def backfill_lines(con: duckdb.DuckDBPyConnection, run_id: str) -> int:
    """Write the lines of every version of ``run_id`` that has none (stores from before migration 7), parents
    first; returns the rows written."""
    versions = con.execute(
        """SELECT v.policy_version_id, v.iteration, v.produced_by, v.parent_id,
                  list({'name': f.name, 'source': b.text}) FILTER (WHERE f.trainable) AS sources
           FROM policy_versions v
           CROSS JOIN unnest(v.functions) AS u(f)
           JOIN blobs b ON b.hash = f.source_hash
           WHERE v.run_id = ? AND NOT EXISTS (SELECT 1 FROM policy_lines l WHERE l.run_id = v.run_id
                                              AND l.policy_version_id = v.policy_version_id)
           GROUP BY v.policy_version_id, v.iteration, v.produced_by, v.parent_id, v.created_at
           ORDER BY v.iteration, v.created_at""", [run_id]).fetchall()
    written = 0
    for version_id, iteration, produced_by, parent_id, sources in versions:
        written += write_version_lines(con, run_id, version_id, iteration, produced_by, parent_id,
                                       {s["name"]: s["source"] for s in sources or []})
    return written


def version_blame(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str) -> list[dict[str, Any]]:
    """The ``line_blame`` rows of a version, methods in the order the policy defines them, lines in order, each
    with ``times_ran``: the calls that ran it in the version's traced episodes of the run (NULL if none was
    traced with lines)."""
    cursor = con.execute(
        """SELECT b.function, b.line_no, b.text, b.executable, b.origin_version_id, b.origin_iteration,
                  b.origin_produced_by, b.origin_call_id, c.times_ran
           FROM line_blame b
           LEFT JOIN (SELECT list_transform(any_value(functions), lambda f: f.name) AS names FROM policy_versions
                      WHERE run_id = ? AND policy_version_id = ?) v ON true
           LEFT JOIN (SELECT function, line_no, sum(times_ran)::BIGINT AS times_ran FROM line_coverage
                      WHERE run_id = ? AND policy_version_id = ? GROUP BY function, line_no) c
                  ON c.function = b.function AND c.line_no = b.line_no
           WHERE b.run_id = ? AND b.policy_version_id = ?
           ORDER BY list_position(v.names, b.function), b.line_no""", [run_id, version_id] * 3)
    return _rows(cursor)
