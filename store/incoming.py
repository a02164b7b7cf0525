"""Arrow tables into the store's tables: one home for registering a table under a name, running the INSERT that
selects from it, and unregistering it, so that an insert that fails keeps its own error.

An error inside a transaction (a Ctrl-C that DuckDB turns into an interrupted query, a full disk, a constraint)
aborts it, and unregistering on the aborted transaction raises ``TransactionException`` in turn: in a ``finally``
that second error replaced the first, and a Ctrl-C reached the command as a traceback, not as a Ctrl-C."""

from __future__ import annotations

from typing import Any, Sequence

import duckdb
import pyarrow as pa


def insert_arrow(con: duckdb.DuckDBPyConnection, name: str, table: pa.Table, sql: str,
                 params: Sequence[Any] | None = None) -> None:
    """Run ``sql`` (an INSERT that selects FROM ``name``) with ``table`` registered as ``name`` for it; the name is
    unregistered however the insert ends, and when the insert raised, that error is the one raised."""
    con.register(name, table)
    try:
        con.execute(sql, params) if params is not None else con.execute(sql)
    except BaseException:
        try:
            con.unregister(name)
        except duckdb.Error:
            pass  # the transaction is aborted (the caller rolls it back); the insert's own error follows
        raise
    con.unregister(name)
