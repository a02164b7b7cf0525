"""The process that runs one query of a served agent's SQL (``codearcade serve``): its own address space, capped,
so that what the query makes DuckDB build costs this process, never the server.

A query of 60 bytes can make DuckDB build far more than its answer holds (``range(0, 10000000)`` as one list value:
855 MB; five values of ``repeat('a', 100000000)``: 0.9 GB); DuckDB's ``memory_limit`` covers only what its buffer
manager allocates. Here the process caps its own data segment (``RLIMIT_DATA``, which counts the heap and private
mappings: DuckDB's and Arrow's allocations) before it reads anything, so such a query fails as an out-of-memory
error inside this process, which then ends.

The server (:func:`store.serve.visible_query`) writes the visible tables as Arrow IPC files and ``query.json`` into
a private directory, starts this module's :func:`main` on it, and reads ``answer.json`` back within a byte bound.
This module imports only DuckDB and pyarrow: it starts in ~0.3 s.
"""

from __future__ import annotations

import decimal
import json
import math
import os
import resource
import sys
import threading
from pathlib import Path
from typing import Any

QUERY_FILE = "query.json"
ANSWER_FILE = "answer.json"
TABLE_SUFFIX = ".arrow"

TOO_LONG = "rows past {:,} bytes of JSON left out: ask for fewer or shorter values"
ARROW_BYTES_PER_JSON_BYTE = 16
"""A row's Arrow bytes per byte of its JSON, at most: a list of 16-byte integers takes 8 for ``0,`` (2 bytes of
JSON), one of 8-byte ones 4; text about 1. A row whose Arrow bytes pass this times what is left of the answer could
not fit in it, and is never made into Python objects."""

DUCKDB_SHARE = 0.5
"""DuckDB's own ``memory_limit``, as a share of the process's cap: its buffer manager then refuses first, with
DuckDB's message, and the cap catches what it does not manage."""


def main(directory: str) -> None:
    """Cap this process, run the query in ``directory``/query.json over its tables and write answer.json there:
    ``{"answer": {...}}``, or ``{"refused": why}`` (time limit, memory), or ``{"error": DuckDB's message}``."""
    work = Path(directory)
    asked = json.loads((work / QUERY_FILE).read_text())
    cap = int(asked["memory_mb"]) * 2**20
    resource.setrlimit(resource.RLIMIT_DATA, (cap, cap))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    os.chdir(work)  # DuckDB always allows its temp directory, ./.tmp: let that be this private one
    try:
        result: dict[str, Any] = {"answer": answer(work, asked)}
    except QueryRefused as exc:
        result = {"refused": str(exc)}
    except MemoryError:
        result = {"refused": _memory_refusal(asked)}
    except Exception as exc:  # DuckDB's errors, each with its own message
        text = str(exc)
        result = {"refused": _memory_refusal(asked)} if "Out of Memory" in text else {"error": text[:2000]}
    (work / ANSWER_FILE).write_text(json.dumps(result, allow_nan=False, default=str))  # dates, UUIDs: as text


class QueryRefused(Exception):
    """The query was stopped by one of its limits (its message says which, and what to ask instead)."""


def _memory_refusal(asked: dict[str, Any]) -> str:
    return (f"the query needed more memory than its process may have ({asked['memory_mb']:,} MB, the tables it reads "
            "included): ask for less (fewer rows, shorter values, a LIMIT before a large aggregate)")


def answer(work: Path, asked: dict[str, Any]) -> dict[str, Any]:
    """The query's columns and first rows within ``max_rows`` and ``max_bytes`` of JSON (``truncated``, ``note``)."""
    import duckdb
    import pyarrow as pa

    cap_mb = int(asked["memory_mb"])
    mem = duckdb.connect(":memory:", config={
        "memory_limit": f"{int(cap_mb * DUCKDB_SHARE)}MB", "threads": 1, "enable_external_access": False,
        "lock_configuration": True})
    timer = threading.Timer(float(asked["time_limit_s"]), mem.interrupt)  # a query may be endless: range(1e15)
    try:
        for table in sorted(work.glob(f"*{TABLE_SUFFIX}")):
            name = table.name[:-len(TABLE_SUFFIX)]
            with pa.memory_map(str(table)) as source:
                mem.register(f"_{name}", pa.ipc.open_file(source).read_all())
                mem.execute(f'CREATE TABLE "{name}" AS SELECT * FROM "_{name}"')
                mem.unregister(f"_{name}")
        timer.start()
        try:
            return _rows_within(mem, asked["sql"], int(asked["max_rows"]), int(asked["max_bytes"]))
        except duckdb.InterruptException:
            raise QueryRefused(f"the query ran past its limit of {float(asked['time_limit_s']):g} s: ask for less "
                               "(a LIMIT, fewer rows or columns)") from None
    finally:
        timer.cancel()
        mem.close()


def _rows_within(mem: Any, sql: str, max_rows: int, max_bytes: int) -> dict[str, Any]:
    relation = mem.sql(sql)
    columns = list(relation.columns) if relation is not None else []
    # row by row, as Arrow first: a row's values become Python objects only once their Arrow size says its JSON could
    # fit (one row of 8 million structs was 65 MB of Arrow and 6 GB as Python objects)
    reader = relation.to_arrow_reader(1) if relation is not None else iter(())
    rows: list[list[Any]] = []
    size, note, more = 0, None, False
    for batch in reader:
        if batch.num_rows == 0:
            continue
        if len(rows) == max_rows:
            more = True
            break
        if batch.nbytes > ARROW_BYTES_PER_JSON_BYTE * (max_bytes - size):
            more, note = True, TOO_LONG.format(max_bytes)
            break
        row = [_json_value(value) for value in (batch.column(i)[0].as_py() for i in range(batch.num_columns))]
        # its texts' lengths first: a value of 100 MB is not encoded only to learn that it does not fit
        texts = sum(len(v) for v in row if isinstance(v, (str, bytes)))
        # + 2: the ", " between rows in the answer's list
        size += 2 + (texts if size + texts > max_bytes else len(json.dumps(row, default=str)))
        if size > max_bytes:
            more, note = True, TOO_LONG.format(max_bytes)
            break
        rows.append(row)
    return {"columns": columns, "rows": rows, "truncated": more,
            **({"note": note} if note is not None else {})}


def _json_value(value: Any) -> Any:
    """``value`` as standard JSON holds it: a float that is not finite as None, a DECIMAL (DuckDB's type of a
    literal such as 1.5) as a number, inside lists and structs too."""
    if isinstance(value, decimal.Decimal):
        value = float(value)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    if isinstance(value, dict):
        return {k: _json_value(v) for k, v in value.items()}
    return value


if __name__ == "__main__":
    main(sys.argv[1])
