"""Intervals in a person's SQL: scalar functions, backed by ``store/scores.py``, on the connections such SQL runs on.

The statistics are not to be written twice, so the functions a query uses to print a mean or an interquartile
mean with its 95% interval are Python functions registered on the connection (DuckDB's ``create_function``) that
call :func:`store.statistics.mean_interval` (Student t) and :func:`store.statistics.iqm_interval` (rliable's stratified
bootstrap, with the module's fixed random state, given only from ``IQM_MIN_PER_STRATUM`` values a stratum: the
same values give the same interval). They take DuckDB lists, so a query aggregates with ``list(...)`` first::

    SELECT game, mean_ci(list(best)) AS best FROM per_run GROUP BY game          -- over the seeds of a game
    SELECT iqm_ci_strata(list(scores)) FROM (SELECT game, list(best) AS scores ... GROUP BY game)  -- over games

Each gives a struct: the value, ``low`` and ``high`` (NULL without an interval: fewer than two values, all equal,
or too few for an IQM interval), ``n``, ``missing``, and ``level``, ``method`` and ``text``, the interval as
:func:`store.statistics.interval_text` prints it (``-20.7 [-21.0, -20.3] 95% t, n=3``; without one, the value and
why). ``ci_text(ci)`` prints such a struct (its ``text``); ``ci_text(point, low, high)`` prints bare numbers as
``12.3 [10.1, 14.2]``, for intervals from elsewhere (it cannot know their level, method or n: prefer
``ci_text(ci)``). :data:`SQL_FUNCTIONS` names them with one line each (``codearcade sql --schema``;
docs/schema.md); :func:`create_sql_functions` makes them on a connection (``store/views.py``: the one
``codearcade sql`` and the examples run on). A list holding a NULL (or NaN) has no value, as a set of games with a
forfeit has no score (``store/scores.py``): the struct's value and bounds are NULL, ``missing`` counts the NULLs and
``text`` says so (``no score: 1 of 3 values NULL``); a query that means to leave them out says so
(``list(x) FILTER (WHERE x IS NOT NULL)``), so a seed whose every version forfeited never silently lifts a mean. An
empty list gives NULLs.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import duckdb

_DOUBLE = duckdb.sqltype("DOUBLE")
_INTEGER = duckdb.sqltype("INTEGER")


_VARCHAR = duckdb.sqltype("VARCHAR")


def _interval_type(point: str) -> Any:
    return duckdb.struct_type({point: _DOUBLE, "low": _DOUBLE, "high": _DOUBLE, "n": _INTEGER, "missing": _INTEGER,
                               "level": _DOUBLE, "method": _VARCHAR, "text": _VARCHAR})


def _struct(point: str, found: Any, missing: int = 0) -> dict[str, Any]:
    """A :class:`store.statistics.Interval` as the struct the SQL functions return (``text``: NULL without a value);
    with ``missing`` NULLs among the values, no value at all, and the text says why."""
    if missing:
        return {point: None, "low": None, "high": None, "n": found.n + missing, "missing": missing,
                "level": found.level, "method": found.method,
                "text": f"no score: {missing} of {found.n + missing} values NULL"}
    return {point: found.point, "low": found.low, "high": found.high, "n": found.n, "missing": 0,
            "level": found.level, "method": found.method, "text": found.text() if found.point is not None else None}


def _kept(values: list | None) -> tuple[list[float], int]:
    """The values of a DuckDB list as floats, and how many were NULL (or NaN): left out of ``kept``."""
    kept = [float(v) for v in values or () if v is not None and not math.isnan(v)]
    return kept, len(values or ()) - len(kept)


def mean_ci(values: list | None) -> dict[str, Any]:
    """``{mean, low, high, n, missing, level, method, text}``: the mean of ``values`` with its 95% Student-t interval
    (:func:`store.statistics.mean_interval`; none for fewer than two values or all equal; no mean with a NULL
    among them)."""
    from store.statistics import mean_interval

    kept, missing = _kept(values)
    return _struct("mean", mean_interval(kept), missing)


def iqm_ci(values: list | None) -> dict[str, Any]:
    """``{iqm, low, high, n, missing, level, method, text}``: the interquartile mean of ``values`` (one stratum,
    e.g. a game's seeds) with its 95% bootstrap interval (:func:`store.statistics.iqm_interval`; none below
    ``IQM_MIN_PER_STRATUM``)."""
    return iqm_ci_strata([values])


def iqm_ci_strata(strata: list | None) -> dict[str, Any]:
    """``{iqm, low, high, n, missing, level, method, text}``: the interquartile mean of the values of every
    stratum together (a list per game) with a stratified bootstrap interval (:func:`store.statistics.iqm_interval`: each
    stratum resampled on its own, as rliable does; none while a stratum holds fewer than ``IQM_MIN_PER_STRATUM``
    values)."""
    from store.statistics import iqm_interval

    kept = [_kept(s) for s in strata or ()]
    return _struct("iqm", iqm_interval([values for values, _ in kept]), sum(missing for _, missing in kept))


_LIST = duckdb.list_type(_DOUBLE)
SQL_FUNCTIONS: dict[str, tuple[str, str, Callable[..., Any], list[Any], Any]] = {
    "mean_ci": ("mean_ci(values)", "STRUCT(mean, low, high, n, missing, level, method, text): mean of a DOUBLE "
                "list with its 95% Student-t interval; none with a NULL in it", mean_ci, [_LIST],
                _interval_type("mean")),
    "iqm_ci": ("iqm_ci(values)", "STRUCT(iqm, low, high, n, missing, level, method, text): interquartile mean of a "
               "list (e.g. over seeds) with its 95% bootstrap interval (from 30 values)", iqm_ci, [_LIST],
               _interval_type("iqm")),
    "iqm_ci_strata": ("iqm_ci_strata(lists)", "STRUCT(iqm, low, high, n, missing, level, method, text): IQM over a "
                      "list of lists (one per game), stratified 95% bootstrap interval (from 30 values a list)",
                      iqm_ci_strata, [duckdb.list_type(_LIST)], _interval_type("iqm")),
}
"""The scipy-backed functions a person's SQL can use: name -> (signature, one line of help, the Python function,
its parameter types, its return type)."""

CI_TEXT = ("ci_text(point, low, high)", "bare numbers as text, as every interval is printed: 12.3 [10.1, 14.2], "
           "0.004 [-0.001, 0.020] (names no level, method or n: prefer ci_text(ci))",
           "CREATE TEMP MACRO ci_text(point, low, high) AS _ci_bounds_text(point, low, high), (ci) AS ci.text")
"""The macro that prints a value with its interval (signature, one line of help, the statement that makes it,
with its second form, :data:`CI_TEXT_STRUCT`)."""
CI_TEXT_STRUCT = ("ci_text(ci)", "a mean_ci / iqm_ci / iqm_ci_strata struct as text, naming level, method and n: "
                  "-20.7 [-21.0, -20.3] 95% t, n=3 (the value and why, without an interval)")
"""The macro's second form: one struct in, :func:`store.statistics.interval_text`'s line out."""


def function_listing() -> list[tuple[str, str, str]]:
    """(signature, kind, one line) of each function and the ``ci_text`` macro's two forms, as the schema listing
    shows them."""
    return ([(signature, "function", line) for signature, line, *_ in SQL_FUNCTIONS.values()]
            + [(CI_TEXT_STRUCT[0], "macro", CI_TEXT_STRUCT[1]), (CI_TEXT[0], "macro", CI_TEXT[1])])


def _ci_bounds_text(point: float | None, low: float | None, high: float | None) -> str | None:
    """The numbers of ``ci_text(point, low, high)``: :func:`store.statistics.bounds_text`'s (one rule of digits:
    the macro's own, two decimals, printed [-0.001, 0.02] as [0.00, 0.02]), NULL without a value."""
    from store.statistics import bounds_text

    if point is None or math.isnan(point):
        return None
    return bounds_text(point, *((low, high) if low is not None and high is not None else ()))


def create_sql_functions(con: duckdb.DuckDBPyConnection) -> None:
    """Make :data:`SQL_FUNCTIONS` and ``ci_text`` on ``con`` (they live as long as the connection; a read-only one
    may have them). Before ``lock_configuration``, like the macros."""
    for name, (_, _, function, parameters, returns) in SQL_FUNCTIONS.items():
        con.create_function(name, function, parameters, returns, null_handling="special", side_effects=False)
    con.create_function("_ci_bounds_text", _ci_bounds_text, ["DOUBLE"] * 3, "VARCHAR", null_handling="special",
                        side_effects=False)
    con.execute(CI_TEXT[2])
