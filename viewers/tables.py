"""Query results as text: an aligned table for people, CSV and JSON for programs.

Shared by ``codearcade sql``, ``codearcade runs`` and the Markdown reports. Values keep their meaning across
formats: NULL is ``NULL`` in a table, an empty field in CSV and ``null`` in JSON; DuckDB ``JSON`` columns are
embedded as JSON (not as strings) in JSON output and as their text elsewhere; lists and structs are JSON text
in tables and CSV; timestamps are ISO 8601; non-finite floats are ``"NaN"``, ``"Infinity"``, ``"-Infinity"``
in JSON (as in the store's own JSON columns). A ``JSON`` value that is not JSON, or is nested deeper than
``tracing/bounded.py`` allows, is embedded as its text (a string), so every stored character is still there.
"""

from __future__ import annotations

import csv
import datetime as dt
import decimal
import json
import math
import uuid
from typing import IO, Any, Sequence

from tracing.bounded import MAX_DEPTH, deeper_than
from viewers.safe_text import terminal_text

DEFAULT_MAX_WIDTH = 40


def to_json_value(value: Any, duck_type: str = "") -> Any:
    """A query value as a JSON-ready Python value (see the module docstring)."""
    if value is None or isinstance(value, (bool, int, str)) and duck_type != "JSON":
        return value
    if duck_type == "JSON" and isinstance(value, str):
        try:
            parsed = json.loads(value)
        except (ValueError, RecursionError):
            return value
        # nested deeper than a reader can follow (tracing/bounded.py): the stored text itself, as a string
        return value if deeper_than(parsed, MAX_DEPTH) else parsed
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return value
    if isinstance(value, decimal.Decimal):
        return to_json_value(float(value))
    if isinstance(value, (dt.datetime, dt.date, dt.time)):
        return value.isoformat()
    if isinstance(value, dt.timedelta):
        return value.total_seconds()
    if isinstance(value, dict):
        return {str(k): to_json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json_value(v) for v in value]
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    if isinstance(value, uuid.UUID):
        return str(value)
    return str(value)


def money(value: float | None) -> str:
    """An amount of US dollars to read: cents and up to the cent, below a cent to two significant figures (an
    LLM call costs fractions of a cent, and ``0.00`` would say it was free); ``–`` when it has no price."""
    if value is None:
        return "–"
    if value == 0 or abs(value) >= 0.995:
        return f"{value:,.2f}"
    return f"{value:.2g}" if abs(value) < 0.01 else f"{value:.3g}"


def cell_text(value: Any, null: str = "NULL", exact: bool = False) -> str:
    """A value as the one-line text of a table cell or, ``exact``, of a CSV field. A float in a cell: six
    significant digits, a whole number of up to 15 figures written out (-9300000, not -9.3e+06); in a field,
    every digit (the shortest text that reads back as the same float: a program gets what was stored)."""
    if value is None:
        return null
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if exact or not math.isfinite(value):
            return repr(value)
        shown = f"{value:.6g}"
        if "e" in shown and 1 <= abs(value) < 1e15:
            return f"{value:.0f}"  # 6 significant digits of a number of 7 to 15 figures: the whole number
        return shown
    if isinstance(value, dt.datetime):
        return value.isoformat(sep=" ")
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(to_json_value(value), ensure_ascii=False)
    return str(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, decimal.Decimal)) and not isinstance(value, bool)


def _clip(text: str, width: int) -> str:
    text = terminal_text(text)  # one line, no control characters: a cell may hold anything a policy wrote
    if width and len(text) > width:
        return text[: max(width - 1, 1)] + "…"
    return text


def format_table(columns: Sequence[str], rows: Sequence[Sequence[Any]], max_width: int = DEFAULT_MAX_WIDTH,
                 null: str = "NULL", whole: Sequence[str] = ()) -> str:
    """Rows as an aligned text table (numbers right-aligned); cells wider than ``max_width`` end in "…", but those
    of the columns named in ``whole`` (a score with its interval: cut, it lost the n it names); every cell and name
    is made terminal-safe (``viewers/safe_text.py``: one line, no escape sequences)."""
    limits = [0 if c in whole else max_width for c in columns]
    texts = [[_clip(cell_text(v, null), limit) for v, limit in zip(row, limits)] for row in rows]
    headers = [_clip(str(c), 0) for c in columns]  # names are never cut
    widths = [max([len(h)] + [len(r[i]) for r in texts]) for i, h in enumerate(headers)]
    numeric = [bool(rows) and all(_is_number(r[i]) or r[i] is None for r in rows) for i in range(len(columns))]

    def line(cells: Sequence[str]) -> str:
        parts = [c.rjust(w) if num else c.ljust(w) for c, w, num in zip(cells, widths, numeric)]
        return "  ".join(parts).rstrip()

    out = [line(headers), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in texts]
    return "\n".join(out)


def write_csv(stream: IO[str], columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """RFC 4180 CSV with a header row; NULL is an empty field, newlines inside fields are kept (quoted). Written to
    a terminal, each field is made safe for it (``terminal_text``: a policy's error may hold escape sequences);
    to a file or a pipe, it is the data as stored."""
    safe = stream.isatty() if hasattr(stream, "isatty") else False
    writer = csv.writer(stream, lineterminator="\n")
    # a field holding a lone \r is quoted only where \r ends lines: such a row is written with every field quoted
    quoted = csv.writer(stream, lineterminator="\n", quoting=csv.QUOTE_ALL)
    fields = (["" if v is None else cell_text(v, exact=True) for v in row] for row in rows)
    for cells in ([str(c) for c in columns], *fields):
        if safe:
            cells = [terminal_text(c, multiline=True) for c in cells]
        (quoted if any("\r" in c for c in cells) else writer).writerow(cells)


def records(columns: Sequence[str], types: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[dict[str, Any]]:
    """Rows as JSON-ready dicts, one per row."""
    types = list(types) or [""] * len(columns)
    return [{c: to_json_value(v, t) for c, t, v in zip(columns, types, row)} for row in rows]
