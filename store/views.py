"""Read-only queries for people: the SQL views, ad-hoc SQL with parameters, and the list of what a store holds.

The views themselves are created by migrations (``store/migrations.py``) and documented in docs/schema.md;
:data:`VIEWS` names them for the CLI and the tests. A store an older codearcade wrote gets them the first time
:meth:`store.Store.read` opens it (it applies pending migrations). :func:`run_query` runs one statement through
:meth:`store.Store.read`, which retries while a writer holds the file, and returns every row at once, so the
file is held only while DuckDB computes the result, never while the caller prints it. A person's SQL
(``codearcade sql``) goes through :func:`run_user_query` instead, which makes it read-only for real: one
reading statement, on a read-only connection of its own with DuckDB's external access off and its
configuration locked (no ATTACH, COPY, EXPORT, INSTALL, no reading or writing of other files); it may
have parameters (:func:`bind_params`: ``?``, ``$1`` or ``$name``) and use the macros ``run(ref)`` and
``run_matches(ref)`` (``store/runs.py``, which also resolves run references for every verb), and the interval
functions ``mean_ci``, ``iqm_ci``, ``iqm_ci_strata`` and ``ci_text`` (``store/sql_stats.py``). :func:`schema_listing`
lists the tables, views and macros with one line each (the tables' and views' DuckDB comments, set by migration 10).
:func:`run_references_by_value` finds the values of a query that name a run without being its id (the short id
``codearcade runs`` prints, compared with ``run_id`` as it is), for the note a query that found nothing gets.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from typing import Any, Sequence

import duckdb

from store.db import Store, StoreError, interrupted_by_ctrl_c, is_corrupt_block, is_ctrl_c
from store.runs import SQL_MACROS, create_sql_macros, references_by_value, resolve_run_id  # noqa: F401 (resolve_run_id: for callers)
from store.sql_stats import create_sql_functions, function_listing

TABLES = ("runs", "blobs", "policy_versions", "episodes", "steps", "nodes", "policy_lines", "iterations", "candidates",
          "feedback", "llm_calls", "audits", "published_scores", "schema_migrations")
"""The tables, in the order docs/schema.md documents them."""

VIEWS = ("learning_curve", "code_metrics", "llm_usage", "rejected_candidates", "run_summary", "run_best", "lineage",
         "frontier", "line_blame", "node_lines", "line_coverage", "unrun_lines", "model_stats", "model_choices")
"""The views over the store, in the order docs/schema.md documents them."""


class QueryError(ValueError):
    """A query DuckDB refused (syntax, unknown table, a write on the read-only connection); one-line message."""


@dataclass
class Result:
    """Columns (names and DuckDB type names) and rows of one query."""

    columns: list[str]
    types: list[str]
    rows: list[tuple]
    total: int | None = None
    """The rows the query gave, where only the first of them were kept (``rows``); None: ``rows`` are all."""


def one_line(exc: BaseException) -> str:
    """A DuckDB error as one line: its lines joined, without the ``LINE 1:`` excerpt and caret."""
    lines = [line.strip() for line in str(exc).splitlines()]
    kept = [line for line in lines if line and not line.startswith("LINE ") and set(line) != {"^"}]
    return " ".join(kept) or type(exc).__name__


FETCH_BATCH_ROWS = 10_000
"""Rows fetched at a time where only the first are kept: memory stays that of a batch, however many rows come."""


def _result(cursor: duckdb.DuckDBPyConnection, keep: int | None = None) -> Result:
    """The rows of an executed statement, with its column names and types (none for SET, a silent PRAGMA): all of
    them, or the first ``keep`` and the count of all (those after them fetched a batch at a time and let go)."""
    if cursor.description is None:
        return Result([], [], [])
    columns, types = [d[0] for d in cursor.description], [str(d[1]) for d in cursor.description]
    if keep is None:
        return Result(columns, types, cursor.fetchall())
    rows = cursor.fetchmany(keep) if keep else []
    total = len(rows)
    while batch := cursor.fetchmany(FETCH_BATCH_ROWS):
        total += len(batch)
    return Result(columns, types, rows, total)


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


def check_user_sql(sql: str, refuser: str = "codearcade sql") -> None:
    """:class:`QueryError` unless ``sql`` is exactly one statement of a type in :data:`USER_STATEMENT_TYPES`;
    ``refuser`` names what refuses it in the message."""
    try:
        sql.encode("utf-8")
    except UnicodeEncodeError as exc:  # a lone surrogate ("\ud800" in JSON): DuckDB's parser raised TypeError
        raise QueryError(f"the query is not valid Unicode (character {exc.start + 1} is a lone surrogate)") from None
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
        words = statements[0].query.split()  # INSTALL is DuckDB's LOAD type: name what the person wrote
        name = words[0].upper() if words and words[0].isalpha() else str(kind).rsplit(".", 1)[-1].replace(
            "_STATEMENT", "")
        raise QueryError(f"{refuser} is read-only: {name} statements are refused; use SELECT (WITH, FROM, "
                         "VALUES, SHOW, DESCRIBE, SUMMARIZE), EXPLAIN, PRAGMA or CALL")


_NAMED = re.compile(r"\$?([A-Za-z_][A-Za-z0-9_]*)=(.*)", re.S)


def bind_params(sql: str, values: Sequence[str]) -> list[str] | dict[str, str]:
    """The parameters of a person's query from ``--param`` texts: for ``?`` or ``$1, $2, ...`` one value per
    parameter, in order, each taken as written; for ``$name`` one ``name=value`` (or ``$name=value``) each. DuckDB
    casts each text to the type its place in the query asks for (``iteration = ?`` with ``3``). :class:`QueryError`
    naming what is missing or extra."""
    check_user_sql(sql)
    wanted = duckdb.extract_statements(sql)[0].named_parameters
    if not wanted:
        if values:
            raise QueryError(f"the query has no parameters (? or $name), but {len(values)} --param "
                             f"value{'s were' if len(values) != 1 else ' was'} given; drop them or add ? to the query")
        return []
    if all(name.isdigit() for name in wanted):
        if len(values) != len(wanted):
            raise QueryError(f"the query has {len(wanted)} parameter{'s' * (len(wanted) != 1)} (? or $1..), "
                             f"{len(values)} --param value{'s' * (len(values) != 1)} given: give one --param VALUE "
                             "for each, in order")
        return list(values)
    named: dict[str, str] = {}
    for text in values:
        match = _NAMED.fullmatch(text)
        if match is None or match.group(1) not in wanted:
            known = ", ".join(f"${n}" for n in sorted(wanted))
            raise QueryError(f"--param {text!r} names no parameter of the query ({known}); give --param NAME=VALUE "
                             "for each")
        named[match.group(1)] = match.group(2)
    missing = sorted(set(wanted) - set(named))
    if missing:
        raise QueryError(f"no value for {', '.join('$' + n for n in missing)}; give --param "
                         f"{missing[0]}=VALUE")
    return named


def run_user_query(store: Store, sql: str, params: Sequence[str] | None = None, keep: int | None = None) -> Result:
    """Run a person's SQL (``codearcade sql``) so that it can only read the store.

    One statement of a reading type (:func:`check_user_sql`), on a connection of its own that opens the store
    file read-only, with external access off (DuckDB then refuses ATTACH, COPY ... TO, EXPORT, INSTALL/LOAD,
    and every function that reads a file: read_text, read_csv, glob, ...) and the configuration locked, so the
    statement cannot turn any of it back on. ``params`` are the ``--param`` texts (:func:`bind_params`); the
    macros of ``store/runs.py`` are there (``WHERE run_id = run('last')``). The store is opened (and migrated)
    first through :meth:`Store.read`, which gives the usual one-line errors for a missing, foreign or locked file.
    ``keep``: only the first rows are wanted (``--max-rows``); the others are counted, not held.
    """
    bound = bind_params(sql, list(params or []))
    with store.read():
        pass
    con = _user_connection(store)
    try:
        with interrupted_by_ctrl_c(con):  # a press stops even a query whose Python functions hold DuckDB's threads
            return _result(con.execute(sql, bound), keep)
    except Exception as exc:
        if is_ctrl_c(exc):  # on a connection of its own, outside Store.read(): given back as itself here
            raise KeyboardInterrupt from None
        if not isinstance(exc, duckdb.Error):
            raise
        if is_corrupt_block(exc):
            raise  # not the query's fault: the store's damage, as every command reports it
        if "attached in read-only mode" in str(exc):  # a write inside a SELECT (WITH x AS (DELETE ...) ...)
            raise QueryError("codearcade sql is read-only: the query writes to the store (a DELETE, INSERT or "
                             "UPDATE inside it); nothing was changed") from None
        raise QueryError(one_line(exc)) from None
    finally:
        con.close()


def values_compared_as_written(sql: str, params: Sequence[str] | None = None) -> list[str]:
    """The string values of a person's query that stand as themselves: its quoted literals and the ``--param``
    values of its ``?`` placeholders, leaving out those given to ``run(...)`` or ``run_matches(...)``, which are
    resolved as run references already (:func:`store.runs.references_by_value` looks at the rest)."""
    tokens = duckdb.tokenize(sql)
    texts = [sql[pos:(tokens[k + 1][0] if k + 1 < len(tokens) else len(sql))].rstrip()
             for k, (pos, _) in enumerate(tokens)]
    values, placeholders = [], 0
    for k, ((_, kind), text) in enumerate(zip(tokens, texts)):
        resolved = k >= 2 and texts[k - 1] == "(" and texts[k - 2].lower() in ("run", "run_matches")
        if kind == duckdb.token_type.string_const and text[:1] == "'" and text[-1:] == "'" and len(text) > 1:
            value = text[1:-1].replace("''", "'")
        elif text == "?":
            value = params[placeholders] if params and placeholders < len(params) else None
            placeholders += 1
        else:
            continue
        if value is not None and not resolved:
            values.append(value)
    return values


def run_references_by_value(store: Store, sql: str, params: Sequence[str] | None = None
                            ) -> list[tuple[str, str, list[str]]]:
    """The values of ``sql`` (:func:`values_compared_as_written`) that name runs but are no run id, with how and
    which (:func:`store.runs.references_by_value`): why a query that compares ``run_id`` with the short id
    ``codearcade runs`` printed found no rows."""
    values = values_compared_as_written(sql, params)
    if not values:
        return []
    with store.read() as con:
        return references_by_value(con, values)


def schema_listing(store: Store) -> list[tuple[str, str, str]]:
    """(name, kind, one line) of every table, view, macro and function a person's SQL can use: tables and views
    with their DuckDB comment (set by the migrations), in the order docs/schema.md describes them, then the macros,
    then the interval functions (``store/sql_stats.py``)."""
    with store.read() as con:
        rows = con.execute(
            "SELECT table_name, 'table', coalesce(comment, '') FROM duckdb_tables() "
            "WHERE database_name = current_database() AND schema_name = 'main' "
            "UNION ALL SELECT view_name, 'view', coalesce(comment, '') FROM duckdb_views() "
            "WHERE database_name = current_database() AND schema_name = 'main' AND NOT internal").fetchall()
    order = {name: k for k, name in enumerate(TABLES + VIEWS)}
    rows.sort(key=lambda r: (r[1] != "table", order.get(r[0], len(order)), r[0]))
    return (rows + [(signature, "macro", help_line) for signature, help_line, _ in SQL_MACROS.values()]
            + function_listing())


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
    create_sql_macros(con)  # temporary macros and functions, before the configuration is locked
    create_sql_functions(con)
    # the interval functions import scipy on first use, which may take seconds: no progress bar on the terminal
    con.execute("SET enable_progress_bar = false")
    con.execute("SET lock_configuration = true")
    return con
