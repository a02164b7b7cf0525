"""Read-only queries for people: the SQL views, ad-hoc SQL, and run-id lookup.

The views themselves are created by migration 3 (``store/migrations.py``) and documented in docs/schema.md;
:data:`VIEWS` names them for the CLI and the tests. A store an older codearcade wrote gets them the first time
:meth:`store.Store.read` opens it (it applies pending migrations). :func:`run_query` runs one statement through
:meth:`store.Store.read`, which retries while a writer holds the file, and returns every row at once, so the
file is held only while DuckDB computes the result, never while the caller prints it. A person's SQL
(``codearcade sql``) goes through :func:`run_user_query` instead, which makes it read-only for real: one
reading statement, on a read-only connection of its own with DuckDB's external access off and its
configuration locked (no ATTACH, COPY, EXPORT, INSTALL, no reading or writing of other files).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import time

import duckdb

from store.db import Store, StoreError

VIEWS = ("learning_curve", "code_metrics", "llm_usage", "rejected_candidates", "run_summary", "lineage", "frontier",
         "line_blame", "node_lines", "line_coverage", "unrun_lines")
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


def _result(cursor: duckdb.DuckDBPyConnection) -> Result:
    """Every row of an executed statement, with its column names and types (none for SET, a silent PRAGMA)."""
    if cursor.description is None:
        return Result([], [], [])
    return Result([d[0] for d in cursor.description], [str(d[1]) for d in cursor.description], cursor.fetchall())


def run_query(store: Store, sql: str, params: list[Any] | None = None) -> Result:
    """Run ``sql`` on a read-only connection; :class:`QueryError` if DuckDB refuses it."""
    with store.read() as con:
        try:
            return _result(con.execute(sql, params or []))
        except duckdb.Error as exc:
            raise QueryError(one_line(exc)) from None


USER_STATEMENT_TYPES = {
    duckdb.StatementType.SELECT: "SELECT",  # also WITH, FROM-first, VALUES, SHOW, DESCRIBE, SUMMARIZE
    duckdb.StatementType.EXPLAIN: "EXPLAIN",
    duckdb.StatementType.PRAGMA: "PRAGMA",  # PRAGMA table_info(...); a PRAGMA that sets something is a SET
    duckdb.StatementType.CALL: "CALL",  # table functions: CALL pragma_version()
}
"""Statement types ``codearcade sql`` runs; everything else (DML, DDL, ATTACH, COPY, SET, INSTALL, ...) is refused."""

USER_CONFIG = {
    "enable_external_access": False,  # no ATTACH, COPY TO, EXPORT, read_text/read_csv/glob of files, INSTALL
    "autoinstall_known_extensions": False,
    "autoload_known_extensions": False,
}
"""The DuckDB configuration of the connection user SQL runs on (then ``lock_configuration`` is set)."""


def check_user_sql(sql: str) -> None:
    """:class:`QueryError` unless ``sql`` is exactly one statement of a type in :data:`USER_STATEMENT_TYPES`."""
    try:
        statements = duckdb.extract_statements(sql)
    except duckdb.Error as exc:
        raise QueryError(one_line(exc)) from None
    if not statements:
        raise QueryError("no SQL statement in the query (only comments or white space)")
    if len(statements) > 1:
        raise QueryError(f"one statement per call, got {len(statements)}; run them one by one")
    kind = statements[0].type
    if kind not in USER_STATEMENT_TYPES:
        name = str(kind).rsplit(".", 1)[-1].replace("_STATEMENT", "")
        raise QueryError(f"codearcade sql is read-only: {name} statements are refused; use SELECT (WITH, FROM, "
                         "VALUES, SHOW, DESCRIBE, SUMMARIZE), EXPLAIN, PRAGMA or CALL")


def run_user_query(store: Store, sql: str) -> Result:
    """Run a person's SQL (``codearcade sql``) so that it can only read the store.

    One statement of a reading type (:func:`check_user_sql`), on a connection of its own that opens the store
    file read-only, with external access off (DuckDB then refuses ATTACH, COPY ... TO, EXPORT, INSTALL/LOAD,
    and every function that reads a file: read_text, read_csv, glob, ...) and the configuration locked, so the
    statement cannot turn any of it back on. The store is opened (and migrated) first through
    :meth:`Store.read`, which gives the usual one-line errors for a missing, foreign or locked file.
    """
    check_user_sql(sql)
    with store.read():
        pass
    con = _user_connection(store)
    try:
        return _result(con.execute(sql))
    except duckdb.Error as exc:
        raise QueryError(one_line(exc)) from None
    finally:
        con.close()


def _user_connection(store: Store) -> duckdb.DuckDBPyConnection:
    """A fresh read-only, external-access-free, locked connection to the store; retries while it is locked."""
    deadline = time.monotonic() + store.lock_timeout_s
    while True:
        try:
            con = duckdb.connect(str(store.path), read_only=True, config=dict(USER_CONFIG))
            break
        except duckdb.Error as exc:
            if ("lock" in str(exc).lower()) and time.monotonic() < deadline:
                time.sleep(0.05)
                continue
            raise StoreError(f"cannot open {store.path}: {one_line(exc)}") from None
    con.execute("SET lock_configuration = true")
    return con


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
