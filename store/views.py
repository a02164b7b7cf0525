"""Read-only queries for people: the SQL views, ad-hoc SQL, and run-id lookup.

The views themselves are created by migration 3 (``store/migrations.py``) and documented in docs/schema.md;
:data:`VIEWS` names them for the CLI and the tests. A store an older codearcade wrote gets them the first time
:meth:`store.Store.read` opens it (it applies pending migrations). :func:`run_query` runs one statement through
:meth:`store.Store.read`, which retries while a writer holds the file, and returns every row at once, so the
file is held only while DuckDB computes the result, never while the caller prints it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import duckdb

from store.db import Store

VIEWS = ("learning_curve", "code_metrics", "llm_usage", "rejected_candidates", "run_summary")
"""The views over the store, in the order docs/schema.md documents them."""


class QueryError(ValueError):
    """A query DuckDB refused (syntax, unknown table, a write on the read-only connection); one-line message."""


@dataclass
class Result:
    """Columns (names and DuckDB type names) and rows of one query."""

    columns: list[str]
    types: list[str]
    rows: list[tuple]


def one_line(exc: BaseException) -> str:
    """A DuckDB error as one line: its lines joined, without the ``LINE 1:`` excerpt and caret."""
    lines = [line.strip() for line in str(exc).splitlines()]
    kept = [line for line in lines if line and not line.startswith("LINE ") and set(line) != {"^"}]
    return " ".join(kept) or type(exc).__name__


def run_query(store: Store, sql: str, params: list[Any] | None = None) -> Result:
    """Run ``sql`` on a read-only connection; :class:`QueryError` if DuckDB refuses it."""
    with store.read() as con:
        try:
            cursor = con.execute(sql, params or [])
            if cursor.description is None:  # SET, PRAGMA without output, ...
                return Result([], [], [])
            columns = [d[0] for d in cursor.description]
            types = [str(d[1]) for d in cursor.description]
            return Result(columns, types, cursor.fetchall())
        except duckdb.Error as exc:
            raise QueryError(one_line(exc)) from None


def resolve_run_id(con: duckdb.DuckDBPyConnection, text: str, store: Store | None = None) -> str:
    """The run whose id is ``text`` or starts with it; ValueError if none or several match."""
    matches = [r[0] for r in con.execute(
        "SELECT run_id FROM runs WHERE starts_with(run_id, ?) ORDER BY run_id LIMIT 6", [text.strip()]).fetchall()]
    where = f" in {store.path}" if store is not None else ""
    if not matches or not text.strip():
        raise ValueError(f"no run {text.strip() or repr(text)}{where}; `codearcade runs` lists the runs")
    if text.strip() in matches:
        return text.strip()
    if len(matches) > 1:
        raise ValueError(f"run {text!r} is ambiguous{where}: {', '.join(matches[:5])}...; give more of the id")
    return matches[0]
