"""The interval functions of a person's SQL (``store/sql_stats.py``): what ``codearcade sql`` computes is what
``store/scores.py`` computes, on the read-only, locked connection people's queries run on."""

from __future__ import annotations

import pytest

from store.scores import interval, iqm
from store.views import run_user_query


def one(store, sql: str):
    (row,) = run_user_query(store, sql).rows
    return row


@pytest.fixture
def opened(store):
    with store.write():  # an empty store of the current schema
        pass
    return store


def test_mean_and_iqm_intervals_are_store_scores_own(opened):
    values = [3.0, -1.0, 4.0, 1.0, 5.0, -9.0, 2.0, 6.0]
    mean, q = one(opened, f"SELECT mean_ci({values}), iqm_ci({values})")
    assert (mean["low"], mean["high"]) == interval(values) and mean["mean"] == sum(values) / 8 and mean["n"] == 8
    assert (q["iqm"], q["low"], q["high"]) == iqm([values]) and q["n"] == 8
    strata = [[1.0, 2.0, 3.0, 10.0], [-5.0, -4.0, 0.0], [7.0]]
    (s,) = one(opened, f"SELECT iqm_ci_strata({strata})")
    assert (s["iqm"], s["low"], s["high"]) == iqm(strata) and s["n"] == 8
    # from rows: one list per game, aggregated as examples/benchmarks.sql does over seeds
    (t,) = one(opened, "SELECT iqm_ci_strata(list(v)) FROM (SELECT g, list(x::DOUBLE) AS v FROM "
                       "(VALUES ('a', 1), ('a', 2), ('a', 3), ('a', 10), ('b', -5), ('b', -4), ('b', 0), ('c', 7)) "
                       "t(g, x) GROUP BY g)")
    assert (t["iqm"], t["low"], t["high"]) == iqm(strata)


def test_nulls_are_left_out_and_the_text_shows_what_there_is(opened):
    c, empty, lone, text, alone, none = one(opened, """
        SELECT mean_ci([1.0, NULL, 3.0]), mean_ci([]), mean_ci([2.5]),
               ci_text(12.34, 10.06, 14.26), ci_text(2.5, NULL, NULL), ci_text(NULL, NULL, NULL)""")
    low, high = interval([1.0, 3.0])
    assert c == {"mean": 2.0, "low": low, "high": high, "n": 2}, "a forfeited assessment's NULL score is left out"
    assert empty == {"mean": None, "low": None, "high": None, "n": 0}
    assert lone == {"mean": 2.5, "low": None, "high": None, "n": 1}
    assert (text, alone, none) == ("12.3 [10.1, 14.3]", "2.5", None)
