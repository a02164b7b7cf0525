"""The interval functions of a person's SQL (``store/sql_stats.py``): what ``codearcade sql`` computes is what
``store/scores.py`` computes, on the read-only, locked connection people's queries run on."""

from __future__ import annotations

import pytest

from store.statistics import IQM_MIN_PER_STRATUM, iqm, iqm_interval, mean_interval
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
    t = mean_interval(values)
    assert mean == {"mean": sum(values) / 8, "low": t.low, "high": t.high, "n": 8, "missing": 0, "level": 0.95,
                    "method": "t", "text": t.text()}
    assert mean["text"] == "1.4 [-2.6, 5.3] 95% t, n=8", "the level, the method and n, always"
    assert (q["iqm"], q["low"], q["high"]) == iqm([values]) and q["n"] == 8
    assert q["low"] is None and q["text"] == f"2.5 (n=8: fewer than {IQM_MIN_PER_STRATUM} a stratum, no interval)"
    strata = [[1.0, 2.0, 3.0, 10.0], [-5.0, -4.0, 0.0], [7.0]]
    (s,) = one(opened, f"SELECT iqm_ci_strata({strata})")
    assert (s["iqm"], s["low"], s["high"]) == iqm(strata) and s["n"] == 8
    # from rows: one list per game, aggregated as examples/benchmarks.sql does over seeds
    (t2,) = one(opened, "SELECT iqm_ci_strata(list(v)) FROM (SELECT g, list(x::DOUBLE) AS v FROM "
                        "(VALUES ('a', 1), ('a', 2), ('a', 3), ('a', 10), ('b', -5), ('b', -4), ('b', 0), ('c', 7)) "
                        "t(g, x) GROUP BY g)")
    assert (t2["iqm"], t2["low"], t2["high"]) == iqm(strata)
    # enough values in every stratum: the stratified bootstrap's interval, named as such
    big = [[float(i % 7) for i in range(IQM_MIN_PER_STRATUM)], [float(i % 5 + 3) for i in range(IQM_MIN_PER_STRATUM)]]
    (b,) = one(opened, f"SELECT iqm_ci_strata({big})")
    found = iqm_interval(big)
    assert (b["iqm"], b["low"], b["high"]) == (found.point, found.low, found.high) and b["low"] < b["iqm"] < b["high"]
    assert b["text"] == found.text() and b["text"].endswith(f"95% stratified bootstrap, n={2 * IQM_MIN_PER_STRATUM}")


def test_a_null_leaves_no_value_and_the_text_shows_what_there_is(opened):
    """A NULL among the values (a run whose every version forfeited, an audit game forfeited) leaves no mean, as a
    set of games with a forfeit has no score: it was left out, and a seed that failed lifted the mean of the rest.
    Leaving NULLs out is the query's own choice, which it says (FILTER)."""
    c, empty, lone, same, text, alone, none = one(opened, """
        SELECT mean_ci([1.0, NULL, 3.0]), mean_ci([]), mean_ci([2.5]), mean_ci([-21.0, -21.0, -21.0]),
               ci_text(12.34, 10.06, 14.26), ci_text(2.5, NULL, NULL), ci_text(NULL, NULL, NULL)""")
    assert c == {"mean": None, "low": None, "high": None, "n": 3, "missing": 1, "level": 0.95, "method": "t",
                 "text": "no score: 1 of 3 values NULL"}
    for sql in ("iqm_ci([1.0, NULL, 3.0])", "iqm_ci_strata([[1.0, 2.0], [NULL, 3.0]])", "mean_ci([1.0, 'NaN'::DOUBLE, 3.0])"):
        (q,) = one(opened, f"SELECT {sql}")
        assert q["low"] is None and q["high"] is None and q["missing"] == 1 and q["text"].startswith("no score: 1 of"), \
            (sql, q)
    (kept,) = one(opened, "SELECT mean_ci(list(x) FILTER (WHERE x IS NOT NULL)) FROM unnest([1.0, NULL, 3.0]) t(x)")
    t = mean_interval([1.0, 3.0])
    assert kept == {"mean": 2.0, "low": t.low, "high": t.high, "n": 2, "missing": 0, "level": 0.95, "method": "t",
                    "text": "2.0 [-10.7, 14.7] 95% t, n=2"}, "left out when the query says so"
    assert empty == {"mean": None, "low": None, "high": None, "n": 0, "missing": 0, "level": 0.95, "method": "t",
                     "text": None}
    assert lone["low"] is None and lone["text"] == "2.5 (n=1: too few for an interval)"
    assert same["mean"] == -21.0 and same["low"] is None and same["high"] is None, "all equal: not an exact interval"
    assert same["text"] == "-21.0 (n=3: all equal, no interval)"
    assert (text, alone, none) == ("12.3 [10.1, 14.3]", "2.5", None)
    # ci_text of the struct prints its text: the level, the method and n, or why there is no interval
    shown = one(opened, """SELECT ci_text(mean_ci([1.0, 3.0])), ci_text(mean_ci([-21.0, -21.0, -21.0])),
                                  ci_text(iqm_ci([1.0, 2.0])), ci_text(mean_ci([]))""")
    assert shown == ("2.0 [-10.7, 14.7] 95% t, n=2", "-21.0 (n=3: all equal, no interval)",
                     f"1.5 (n=2: fewer than {IQM_MIN_PER_STRATUM} a stratum, no interval)", None)


def test_a_bound_near_zero_prints_on_its_side_of_zero_and_never_as_minus_zero(opened):
    """A sweep of intervals: every number printed (by ``interval_text`` and the ``ci_text`` macro) is never ``-0``
    and, when the value is not zero but at least 0.005 in size, never prints as zero (compare.md's example read
    ``[-1.6, -0.0]`` for an upper bound of -0.043: beyond zero, shown as touching it)."""
    import random
    import re

    from store.statistics import interval_text

    rng = random.Random(5)
    cases = []
    for _ in range(400):
        point = rng.choice([rng.uniform(-2, 2), rng.uniform(-0.09, 0.09), 0.0])
        low, high = point - rng.choice([rng.uniform(0, 2), rng.uniform(0, 0.1)]), point + rng.uniform(0, 2)
        cases.append((point, low, high))
    values = ", ".join(f"({i}, {p!r}::DOUBLE, {lo!r}::DOUBLE, {hi!r}::DOUBLE)"
                       for i, (p, lo, hi) in enumerate(cases[:120]))
    texts = [text for (text,) in run_user_query(  # one query of 120 rows: each query opens the store anew
        opened, f"SELECT ci_text(p, lo, hi) FROM (VALUES {values}) t(i, p, lo, hi) ORDER BY i").rows]
    texts += [interval_text(p, lo, hi, 3, "t") for p, lo, hi in cases]
    cases = cases[:120] + cases
    for (point, low, high), text in zip(cases, texts):
        shown = [float(x) for x in re.findall(r"-?\d+\.\d+", text)[:3]]
        assert not re.search(r"-0\.0+(?!\d*[1-9])", text), text
        for value, printed in zip((point, low, high), shown):
            if abs(value) >= 0.005:
                assert printed != 0 and (printed < 0) == (value < 0), (value, text)


def test_ci_text_of_bare_numbers_prints_them_as_every_interval_is_printed(opened):
    """``ci_text(point, low, high)`` had its own digits (two decimals at most): ``ci_text(0.004, -0.001, 0.02)``
    printed ``0.00 [0.00, 0.02]``, an interval that includes zero shown as one that starts at it. Over values of
    every size and sign, it prints the numbers ``interval_text`` prints, and none that is not zero as zero."""
    import random
    import re

    from store.statistics import interval_text

    rng = random.Random(11)
    cases = []
    for _ in range(300):
        scale = 10.0 ** rng.randint(-4, 5)
        point = rng.uniform(-1, 1) * scale
        cases.append((point, point - rng.uniform(0, 1) * scale, point + rng.uniform(0, 1) * scale))
    values = ", ".join(f"({i}, {p!r}::DOUBLE, {lo!r}::DOUBLE, {hi!r}::DOUBLE)" for i, (p, lo, hi) in enumerate(cases))
    texts = [text for (text,) in run_user_query(
        opened, f"SELECT ci_text(p, lo, hi) FROM (VALUES {values}) t(i, p, lo, hi) ORDER BY i").rows]
    for (point, low, high), text in zip(cases, texts, strict=True):
        assert interval_text(point, low, high, 3, "t") == f"{text} 95% t, n=3", (point, low, high)
        for value, printed in zip((point, low, high), re.findall(r"-?\d+\.\d+", text)):
            if abs(value) >= 0.0005:
                assert float(printed) != 0 and (float(printed) < 0) == (value < 0), (value, text)
    assert one(opened, "SELECT ci_text(0.004, -0.001, 0.02)") == ("0.004 [-0.001, 0.020]",)
