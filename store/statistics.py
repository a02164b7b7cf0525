"""The statistics behind every interval codearcade prints: means, differences and aggregates over returns.

:func:`mean_interval` gives one set of returns' mean with its 95% Student-t interval (scipy's
:func:`scipy.stats.ttest_1samp`). :func:`difference` says whether two independent sets differ by more than the
noise (Welch's t: :func:`scipy.stats.ttest_ind` with unequal variances, and its interval of the difference of the
means); :func:`paired_difference` does so for two sets played seed by seed with the same random draws (the paired t
of their differences, :func:`scipy.stats.ttest_rel`). :func:`iqm` aggregates over games or seeds as rliable
recommends: the interquartile mean with a stratified bootstrap interval (each stratum resampled on its own:
scipy's bootstrap with one sample per stratum), given only when every stratum holds at least
:data:`IQM_MIN_PER_STRATUM` values. The ``*_bounds`` functions take arrays of many samples at once, for the
calibration simulations. Which episodes count towards a score is :mod:`store.scores`' rule, not this module's.

**Why these methods.** An interval must keep its promise at the sample sizes people use: 3–10 episodes a
version, 3–5 seeds a game. Simulated on returns shaped like Atari's (discrete, skewed, bimodal, with ties;
tests/test_calibration.py, bench/calibration.py, figures in docs/benchmarks.md), the percentile bootstrap
codearcade used before covered the true mean 70–80% of the time at 3 episodes and 78–85% at 5, and called identical
policies different 15–21% of the time at 3 a side; the t-interval covers 93.6–99.7% at 3–10 episodes and Welch's
test errs 2.5–4.8% at 3–6 a side. Beyond those shapes the t-interval's promise ends (docs/benchmarks.md):
strongly skewed returns, as a Breakout policy's lives (``--one-life``), are covered 88–90% at 3–10, and a policy
that collapses in one game of twenty 28% at 5 (no interval from the sample alone can see a rare collapse).
The IQM's stratified bootstrap covers 83% with 3 values a stratum, 91% with 5,
92% with 10 and 92–95% with 20 (BCa and basic do no better): it keeps 93% from 30, so below
:data:`IQM_MIN_PER_STRATUM` the IQM is given alone, with why.

**Printing.** Every interval is printed by :func:`interval_text` (or :meth:`Interval.text`), which names its
level, method and n: ``-20.7 [-21.0, -20.3] 95% t, n=3``; without an interval, the value and why:
``-21.0 (n=3: all equal, no interval)``. The bootstrap runs with a fixed random state, so the same values always
give the same interval.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

CONFIDENCE = 0.95
"""The level of every interval codearcade computes and prints."""
RESAMPLES = 4999
SEED = 20250712
"""The bootstrap's random state: fixed, so that an interval is a function of the returns alone."""
MEAN_METHOD = "t"
"""One set of episodes' mean: a Student-t interval (:func:`scipy.stats.ttest_1samp`)."""
DIFFERENCE_METHOD = "Welch t"
"""Two sets' difference of means: Welch's t (:func:`scipy.stats.ttest_ind`, ``equal_var=False``)."""
PAIRED_METHOD = "paired t"
"""Two sets played on the same seeds with the same random draws, episode by episode: the t interval of the mean of
their differences (:func:`scipy.stats.ttest_rel`)."""
IQM_METHOD = "stratified bootstrap"
"""The interquartile mean over strata (games, seeds): rliable's stratified percentile bootstrap."""
IQM_MIN_PER_STRATUM = 30
"""The fewest values a stratum may hold for an IQM interval: below it the bootstrap covers less than 93% on
Atari-like returns (tests/test_calibration.py), so the IQM is given without one."""
TOO_FEW = "too few for an interval"
ALL_EQUAL = "all equal, no interval"
SAME_DIFFERENCE = "the same difference on every seed, no interval"
"""Why there is no interval: fewer than two values (on a side), or no spread among them."""



@dataclass(frozen=True)
class Interval:
    """A value with its ``level`` interval [``low``, ``high``] by ``method`` over ``n`` values, or, when ``low`` and
    ``high`` are None, the ``reason`` there is none (:data:`TOO_FEW`, :data:`ALL_EQUAL`, ...)."""

    point: float | None
    low: float | None
    high: float | None
    n: int | tuple[int, int]
    """How many values it is over (two counts for a difference: A's and B's)."""
    method: str
    level: float = CONFIDENCE
    reason: str | None = None

    def text(self, signed: bool = False) -> str:
        """``-20.7 [-21.0, -20.3] 95% t, n=3`` (:func:`interval_text`)."""
        return interval_text(self.point, self.low, self.high, self.n, self.method, self.level, self.reason, signed)


def interval_text(point: float | None, low: float | None, high: float | None, n: int | tuple[int, int],
                  method: str, level: float = CONFIDENCE, reason: str | None = None, signed: bool = False) -> str:
    """The one way an interval is printed, naming its level, method and n: ``-20.7 [-21.0, -20.3] 95% t, n=3``.
    Without an interval (``low`` None) the value alone and why: ``-21.0 (n=3: all equal, no interval)``; the reason
    defaults to :data:`TOO_FEW` (fewer than two values on a side) or :data:`ALL_EQUAL`. One decimal (three for
    values under 1 in size: normalized scores; up to three where a value that is not zero would print as zero, all
    the numbers of a line alike); ``signed`` puts a sign on each number (a difference)."""
    counts = n if isinstance(n, tuple) else (n,)
    shown_n = "n=" + " and ".join(str(c) for c in counts)
    if point is None or (isinstance(point, float) and math.isnan(point)):
        return f"none ({shown_n})"
    numbers = bounds_text(point, low, high, signed)
    if low is None or high is None:
        why = reason or (TOO_FEW if min(counts) < 2 else ALL_EQUAL)
        return f"{numbers} ({shown_n}: {why})"
    return f"{numbers} {level * 100:g}% {method}, {shown_n}"


def bounds_text(point: float, low: float | None = None, high: float | None = None, signed: bool = False) -> str:
    """The numbers of :func:`interval_text`, ``12.3 [10.1, 14.3]`` (the value alone without both bounds), to its
    digits: one (three for values under 1 in size; up to three where a value that is not zero would print as zero,
    all the numbers alike); ``signed``: a sign on each."""
    numbers = [x for x in (point, low, high) if x is not None]
    digits = 1 if max(abs(x) for x in numbers) >= 1 or all(x == 0 for x in numbers) else 3
    for more in range(digits, 4):  # a bound near zero is printed on its side of it: [-1.64, -0.04], not [-1.6, -0.0]
        if not any(x != 0 and round(x, more) == 0 for x in numbers):
            digits = more
            break
    sign = "+" if signed else ""

    def number(x: float) -> str:
        return f"{round(x, digits) + 0.0:{sign}.{digits}f}"  # + 0.0: a value that rounds to zero is 0, never -0

    if low is None or high is None:
        return number(point)
    return f"{number(point)} [{number(low)}, {number(high)}]"


def mean_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> Interval:
    """The mean of ``values`` with its ``confidence`` Student-t interval (:func:`mean_bounds`); none for fewer than
    two values or when they are all equal (no spread to measure: say so rather than print ``[x, x]``)."""
    kept = [float(v) for v in values]
    point = math.fsum(kept) / len(kept) if kept else None
    if len(kept) < 2 or min(kept) == max(kept):
        return Interval(point, None, None, len(kept), MEAN_METHOD, confidence, TOO_FEW if len(kept) < 2 else ALL_EQUAL)
    low, high = mean_bounds(kept, confidence)
    return Interval(point, float(low), float(high), len(kept), MEAN_METHOD, confidence)


def mean_bounds(samples: Any, confidence: float = CONFIDENCE) -> tuple[Any, Any]:
    """(low, high) of the Student-t interval of the mean of each sample along the last axis of ``samples`` (scipy's
    ``ttest_1samp(...).confidence_interval``), NaN where there is none (fewer than two values, or all equal).
    Arrays in, arrays out: :func:`mean_interval` uses it for one sample, tests/test_calibration.py for thousands."""
    import numpy as np
    from scipy import stats

    x = np.asarray(samples, dtype=float)
    if x.shape[-1] < 2:
        nothing = np.full(x.shape[:-1], np.nan)
        return nothing, nothing
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # scipy warns of all-equal samples, left out below
        found = stats.ttest_1samp(x, 0.0, axis=-1).confidence_interval(confidence)
    flat = x.min(axis=-1) == x.max(axis=-1)
    return np.where(flat, np.nan, found.low), np.where(flat, np.nan, found.high)


def interval(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float | None, float | None]:
    """(low, high) of :func:`mean_interval`: (None, None) for fewer than two values or all equal."""
    found = mean_interval(values, confidence)
    return found.low, found.high


@dataclass(frozen=True)
class Difference:
    """``mean(a) - mean(b)`` with its Welch-t interval, and whether the interval leaves out zero."""

    delta: float
    low: float | None
    high: float | None
    n_a: int
    n_b: int
    level: float = CONFIDENCE
    method: str = DIFFERENCE_METHOD
    reason: str | None = None
    """Why there is no interval (``low`` None): too few episodes on a side, or every return equal on both."""

    @property
    def significant(self) -> bool | None:
        """True when the interval of the difference excludes 0; None when there is no interval to say it."""
        if self.low is None:
            return None
        return self.low > 0 or self.high < 0

    @property
    def interval(self) -> Interval:
        return Interval(self.delta, self.low, self.high, (self.n_a, self.n_b), self.method, self.level, self.reason)

    def verdict(self) -> str:
        band = f"A - B = {self.interval.text(signed=True)}"
        if self.significant is None:
            if self.reason == ALL_EQUAL:
                return (f"{band}: cannot tell: every episode of each side returned the same, so there is no noise "
                        "to measure it against")
            if self.reason == SAME_DIFFERENCE:
                return (f"{band}: cannot tell: on every seed the two sides' returns differed by the same amount, so "
                        "there is no noise to measure it against")
            return f"{band}: too few episodes to tell (need at least 2 played out on each side)"
        if self.significant:
            return f"{band}: a difference beyond the noise (the interval excludes 0)"
        return f"{band}: no difference beyond the noise (the interval includes 0)"


def difference(a: Sequence[float], b: Sequence[float], confidence: float = CONFIDENCE) -> Difference:
    """The difference of the mean returns of two independent sets of episodes, with Welch's t interval
    (:func:`difference_bounds`). No interval with fewer than two episodes on a side, or when every return on both
    sides is the same (one constant side is fine: the other's spread is the noise)."""
    a, b = [float(x) for x in a], [float(x) for x in b]
    delta = (math.fsum(a) / len(a) - math.fsum(b) / len(b)) if a and b else math.nan
    if len(a) < 2 or len(b) < 2:
        return Difference(delta, None, None, len(a), len(b), confidence, reason=TOO_FEW)
    if min(a) == max(a) and min(b) == max(b):
        return Difference(delta, None, None, len(a), len(b), confidence, reason=ALL_EQUAL)
    low, high = difference_bounds(a, b, confidence)
    return Difference(delta, float(low), float(high), len(a), len(b), confidence)


def paired_difference(a: Sequence[float], b: Sequence[float], confidence: float = CONFIDENCE) -> Difference:
    """The mean of ``a[i] - b[i]`` for two sets played pair by pair (episode ``i`` of each on the same seed, drawing
    the same random numbers), with the t interval of that mean (:func:`paired_difference_bounds`): what the two
    games of a pair share drops out of the noise. No interval with fewer than two pairs, or when every pair
    differs by the same amount (two copies of one policy: 0 on every seed)."""
    a, b = [float(x) for x in a], [float(x) for x in b]
    if len(a) != len(b):
        raise ValueError(f"pairs need as many episodes on each side ({len(a)} and {len(b)})")
    differences = [x - y for x, y in zip(a, b)]
    delta = math.fsum(differences) / len(differences) if differences else math.nan
    if len(differences) < 2:
        return Difference(delta, None, None, len(a), len(b), confidence, PAIRED_METHOD, TOO_FEW)
    if min(a) == max(a) and min(b) == max(b):  # the more telling reason: nothing varied at all
        return Difference(delta, None, None, len(a), len(b), confidence, PAIRED_METHOD, ALL_EQUAL)
    if min(differences) == max(differences):
        return Difference(delta, None, None, len(a), len(b), confidence, PAIRED_METHOD, SAME_DIFFERENCE)
    low, high = paired_difference_bounds(a, b, confidence)
    return Difference(delta, float(low), float(high), len(a), len(b), confidence, PAIRED_METHOD)


def difference_bounds(a: Any, b: Any, confidence: float = CONFIDENCE) -> tuple[Any, Any]:
    """(low, high) of Welch's t interval of ``mean(a) - mean(b)`` along the last axis (scipy's
    ``ttest_ind(a, b, equal_var=False).confidence_interval``: the two sets' variances are not assumed equal), NaN
    where there is none (fewer than two on a side, or both sides all equal). Arrays in, arrays out, like
    :func:`mean_bounds`."""
    import numpy as np
    from scipy import stats

    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if x.shape[-1] < 2 or y.shape[-1] < 2:
        nothing = np.full(np.broadcast_shapes(x.shape[:-1], y.shape[:-1]), np.nan)
        return nothing, nothing
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # scipy warns of an all-equal side; one is fine
        found = stats.ttest_ind(x, y, axis=-1, equal_var=False).confidence_interval(confidence)
    flat = (x.min(axis=-1) == x.max(axis=-1)) & (y.min(axis=-1) == y.max(axis=-1))
    return np.where(flat, np.nan, found.low), np.where(flat, np.nan, found.high)


def paired_difference_bounds(a: Any, b: Any, confidence: float = CONFIDENCE) -> tuple[Any, Any]:
    """(low, high) of the t interval of the mean of ``a - b``, pair by pair along the last axis (scipy's
    ``ttest_rel(a, b).confidence_interval``), NaN where there is none (fewer than two pairs, or every pair
    differing by the same amount). Arrays in, arrays out, like :func:`difference_bounds`."""
    import numpy as np
    from scipy import stats

    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if x.shape[-1] < 2:
        nothing = np.full(np.broadcast_shapes(x.shape[:-1], y.shape[:-1]), np.nan)
        return nothing, nothing
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # scipy warns of differences that are all the same
        found = stats.ttest_rel(x, y, axis=-1).confidence_interval(confidence)
    d = x - y
    flat = d.min(axis=-1) == d.max(axis=-1)
    return np.where(flat, np.nan, found.low), np.where(flat, np.nan, found.high)


def iqm_interval(strata: Sequence[Sequence[float]], confidence: float = CONFIDENCE, resamples: int = RESAMPLES,
                 minimum: int = IQM_MIN_PER_STRATUM) -> Interval:
    """The interquartile mean of the values of all ``strata`` together (e.g. one stratum per game of normalized
    scores, or per seed) with a stratified bootstrap interval: each stratum is resampled on its own, as rliable
    does (scipy's ``bootstrap``, percentile, :data:`SEED`). Empty strata are left out. No interval when a stratum
    holds fewer than ``minimum`` values (:data:`IQM_MIN_PER_STRATUM`: the bootstrap does not keep its level below
    it; ``bench/calibration.py`` lowers it to measure that) or when nothing varies."""
    import numpy as np
    from scipy import stats

    kept = [np.asarray(s, dtype=float) for s in strata if len(s)]
    n = sum(len(s) for s in kept)
    if not kept:
        return Interval(None, None, None, 0, IQM_METHOD, confidence, TOO_FEW)
    values = np.concatenate(kept)
    point = float(stats.trim_mean(values, 0.25))
    if len(values) < 2:
        return Interval(point, None, None, n, IQM_METHOD, confidence, TOO_FEW)
    if values.min() == values.max():
        return Interval(point, None, None, n, IQM_METHOD, confidence, ALL_EQUAL)
    if min(len(s) for s in kept) < minimum:
        return Interval(point, None, None, n, IQM_METHOD, confidence, f"fewer than {minimum} a stratum, no interval")
    varying = [s for s in kept if s.min() != s.max()]
    fixed = np.concatenate([s for s in kept if s.min() == s.max()] or [np.empty(0)])

    def statistic(*samples, axis=-1):
        batch = samples[0].shape[:-1]
        whole = np.concatenate([*samples, np.broadcast_to(fixed, batch + fixed.shape)], axis=-1)
        return stats.trim_mean(whole, 0.25, axis=-1)

    result = stats.bootstrap(tuple(varying), statistic, vectorized=True, paired=False, confidence_level=confidence,
                             n_resamples=resamples, method="percentile", random_state=np.random.default_rng(SEED))
    return Interval(point, float(result.confidence_interval.low), float(result.confidence_interval.high), n,
                    IQM_METHOD, confidence)


def iqm(strata: Sequence[Sequence[float]], confidence: float = CONFIDENCE
        ) -> tuple[float | None, float | None, float | None]:
    """(interquartile mean, low, high) of :func:`iqm_interval`; low and high None where it gives no interval."""
    found = iqm_interval(strata, confidence)
    return found.point, found.low, found.high
