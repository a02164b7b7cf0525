"""Intervals in a person's SQL: scalar functions, backed by ``store/scores.py``, on the connections such SQL runs on.

SQL cannot bootstrap, and the statistics are not to be written twice, so the functions a query uses to print a
mean or an interquartile mean with its 95% interval are Python functions registered on the connection
(DuckDB's ``create_function``) that call :func:`store.scores.interval` and :func:`store.scores.iqm` (scipy's
bootstrap, with the module's fixed random state: the same values give the same interval). They take DuckDB lists,
so a query aggregates with ``list(...)`` first::

    SELECT game, mean_ci(list(best)) AS best FROM per_run GROUP BY game          -- over the seeds of a game
    SELECT iqm_ci_strata(list(scores)) FROM (SELECT game, list(best) AS scores ... GROUP BY game)  -- over games

and ``ci_text(...)`` prints one as ``12.3 [10.1, 14.2]`` (an interval is not symmetric, so no ``±``).
:data:`SQL_FUNCTIONS` names them with one line each (``codearcade sql --schema``; docs/schema.md);
:func:`create_sql_functions` makes them on a connection (``store/views.py``: the one ``codearcade sql`` and the
examples run on). A NULL in a list is left out (a forfeited assessment has no score); an empty list gives NULLs.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import duckdb

_DOUBLE = duckdb.sqltype("DOUBLE")
_INTEGER = duckdb.sqltype("INTEGER")


def _interval_type(point: str) -> Any:
    return duckdb.struct_type({point: _DOUBLE, "low": _DOUBLE, "high": _DOUBLE, "n": _INTEGER})


def _kept(values: list | None) -> list[float]:
    """The values of a DuckDB list as floats, NULLs (and NaN) left out."""
    return [float(v) for v in values or () if v is not None and not math.isnan(v)]


def mean_ci(values: list | None) -> dict[str, Any]:
    """``{mean, low, high, n}``: the mean of ``values`` with its 95% bootstrap interval (:func:`scores.interval`)."""
    from store.scores import interval

    kept = _kept(values)
    low, high = interval(kept)
    return {"mean": math.fsum(kept) / len(kept) if kept else None, "low": low, "high": high, "n": len(kept)}


def iqm_ci(values: list | None) -> dict[str, Any]:
    """``{iqm, low, high, n}``: the interquartile mean of ``values`` (one stratum, e.g. a game's seeds) with its
    95% bootstrap interval (:func:`scores.iqm`)."""
    return iqm_ci_strata([values])


def iqm_ci_strata(strata: list | None) -> dict[str, Any]:
    """``{iqm, low, high, n}``: the interquartile mean of the values of every stratum together (a list per game)
    with a stratified bootstrap interval (:func:`scores.iqm`: each stratum resampled on its own, as rliable does)."""
    from store.scores import iqm

    kept = [_kept(s) for s in strata or ()]
    point, low, high = iqm(kept)
    return {"iqm": point, "low": low, "high": high, "n": sum(len(s) for s in kept)}


_LIST = duckdb.list_type(_DOUBLE)
SQL_FUNCTIONS: dict[str, tuple[str, str, Callable[..., Any], list[Any], Any]] = {
    "mean_ci": ("mean_ci(values)", "STRUCT(mean, low, high, n): mean of a list of DOUBLE with its 95% bootstrap "
                "interval (mean_ci(list(score)))", mean_ci, [_LIST], _interval_type("mean")),
    "iqm_ci": ("iqm_ci(values)", "STRUCT(iqm, low, high, n): interquartile mean of a list (e.g. over seeds) with its "
               "95% bootstrap interval", iqm_ci, [_LIST], _interval_type("iqm")),
    "iqm_ci_strata": ("iqm_ci_strata(lists)", "STRUCT(iqm, low, high, n): IQM over a list of lists (one per game) "
                      "with a stratified 95% bootstrap interval", iqm_ci_strata, [duckdb.list_type(_LIST)],
                      _interval_type("iqm")),
}
"""The scipy-backed functions a person's SQL can use: name -> (signature, one line of help, the Python function,
its parameter types, its return type)."""

CI_TEXT = ("ci_text(point, low, high)", "a value and its interval as text, one decimal: 12.3 [10.1, 14.2] "
           "(ci_text(c.mean, c.low, c.high))",
           "CREATE TEMP MACRO ci_text(point, low, high) AS CASE WHEN point IS NULL THEN NULL "
           "WHEN low IS NULL THEN printf('%.1f', point) "
           "ELSE printf('%.1f [%.1f, %.1f]', point, low, high) END")
"""The macro that prints a value with its interval (signature, one line of help, the statement that makes it)."""


def function_listing() -> list[tuple[str, str, str]]:
    """(signature, kind, one line) of each function and the ``ci_text`` macro, as the schema listing shows them."""
    return ([(signature, "function", line) for signature, line, *_ in SQL_FUNCTIONS.values()]
            + [(CI_TEXT[0], "macro", CI_TEXT[1])])


def create_sql_functions(con: duckdb.DuckDBPyConnection) -> None:
    """Make :data:`SQL_FUNCTIONS` and ``ci_text`` on ``con`` (they live as long as the connection; a read-only one
    may have them). Before ``lock_configuration``, like the macros."""
    for name, (_, _, function, parameters, returns) in SQL_FUNCTIONS.items():
        con.create_function(name, function, parameters, returns, null_handling="special", side_effects=False)
    con.execute(CI_TEXT[2])
