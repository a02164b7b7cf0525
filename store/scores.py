"""How episodes become a score: the one rule every reader of scores uses.

An episode is **played out** when the game ended it (``terminated``) or the step cap did (``truncated``). Any
other end is the policy's doing — it raised or returned an illegal action (``policy_error``), overran a time
limit (``timeout``), its process died or broke the protocol (``crashed``, memory limits included), or its score
was caught tampered (``tampered``) — and the episode is a **forfeit**: its partial return and end reason stay in
the ``episodes`` table, but it is never averaged into a score as if the game had been played.

:func:`score_episodes` turns a set of episodes into a :class:`Score`:

- ``mean``: the mean return of the episodes played out, with a 95% interval (a percentile bootstrap over those
  episodes, scipy's :func:`scipy.stats.bootstrap`; none for fewer than two episodes);
- ``forfeits``: the forfeited episodes, each with where and why it ended;
- ``ranked``: the score the version competes with — ``mean`` when nothing was forfeited, and **None** when
  anything was. A version with a forfeited assessment therefore never is a run's best and never ranks above a
  version that played its games out, whatever its partial return; in SQL its ``score`` is NULL, so
  ``max(score)`` and ``ORDER BY score DESC NULLS LAST`` read the rule without knowing it;
- ``partial``: the mean return of all the episodes, forfeits at their partial return: what the model is told the
  policy had scored when it stopped, kept in ``candidates.forfeit_score``.

``codearcade eval`` prints the mean and names the forfeits beside it (``mean return -20 over 2 episodes; 1 forfeit:
RuntimeError at step 300``). :func:`difference` says whether two sets of returns differ by more than the noise
(a bootstrap interval of the difference of their means), and :func:`iqm` aggregates over games or seeds as
rliable recommends: the interquartile mean with a stratified bootstrap interval (each stratum resampled on its
own: scipy's bootstrap with one sample per stratum).

Intervals are computed with a fixed random state, so the same episodes always give the same interval.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

PLAYED_OUT = ("terminated", "truncated")
"""End reasons of an episode the game or the step cap ended."""
FORFEIT_END_REASONS = ("policy_error", "timeout", "crashed", "tampered")
"""End reasons of an episode the policy ended: a forfeit."""
CONFIDENCE = 0.95
RESAMPLES = 4999
SEED = 20250712
"""The bootstrap's random state: fixed, so that an interval is a function of the returns alone."""


def is_forfeit(end_reason: str | None) -> bool:
    """Whether an episode that ended so is a forfeit (anything but the game's or the step cap's end)."""
    return end_reason not in PLAYED_OUT


@dataclass(frozen=True)
class Forfeit:
    """One forfeited episode: how it ended, on which step, and the error the policy left (first line)."""

    end_reason: str
    step: int
    error: str | None = None

    def describe(self) -> str:
        """``RuntimeError at step 300`` (the exception's name when the error names one), else
        ``timeout at step 300``."""
        return f"{_error_name(self.error) or self.end_reason} at step {self.step}"


@dataclass(frozen=True)
class Score:
    """A set of episodes scored by the rule of this module (see the module docstring)."""

    mean: float | None
    """Mean return of the episodes played out (None: none was)."""
    low: float | None
    high: float | None
    """The 95% bootstrap interval of ``mean`` (None with fewer than two episodes played out)."""
    played: int
    forfeits: tuple[Forfeit, ...] = ()
    partial: float | None = None
    """Mean return of every episode, forfeits at their partial return."""
    returns: tuple[float, ...] = field(default=(), repr=False)
    """The returns of the episodes played out, in order (for :func:`difference`)."""

    @property
    def episodes(self) -> int:
        return self.played + len(self.forfeits)

    @property
    def forfeited(self) -> bool:
        return bool(self.forfeits)

    @property
    def ranked(self) -> float | None:
        """The score a version competes with: ``mean``, or None when any episode was forfeited."""
        return None if self.forfeits else self.mean

    @property
    def forfeit(self) -> str | None:
        """One line naming the forfeits (None when there were none): ``1 of 3 episodes forfeited: RuntimeError at
        step 300 (policy_error)``."""
        if not self.forfeits:
            return None
        first = self.forfeits[0]
        more = f"; {len(self.forfeits) - 1} more" if len(self.forfeits) > 1 else ""
        return (f"{len(self.forfeits)} of {self.episodes} episode{'s' * (self.episodes != 1)} forfeited: "
                f"{first.describe()} ({first.end_reason}){more}")

    def summary(self) -> str:
        """``mean return -19.5 [-20, -19] over 2 episodes; 1 forfeit: RuntimeError at step 300`` for people (the
        95% interval when the returns differ)."""
        if self.mean is None:
            text = f"no episode played out of {self.episodes}"
        else:
            band = f" [{self.low:g}, {self.high:g}]" if self.low is not None and self.low != self.high else ""
            text = f"mean return {self.mean:g}{band} over {self.played} episode{'s' * (self.played != 1)}"
        if self.forfeits:
            names = ", ".join(f.describe() for f in self.forfeits[:3]) + (", ..." if len(self.forfeits) > 3 else "")
            text += f"; {len(self.forfeits)} forfeit{'s' * (len(self.forfeits) != 1)}: {names}"
        return text


def score_episodes(episodes: Iterable[Mapping[str, Any]]) -> Score:
    """The :class:`Score` of ``episodes`` (rows or dicts with ``return``, ``end_reason``, ``length`` and
    optionally ``error``), in their order."""
    played, partial, forfeits = [], [], []
    for e in episodes:
        value = float(e["return"])
        partial.append(value)
        if is_forfeit(e.get("end_reason")):
            forfeits.append(Forfeit(str(e.get("end_reason")), int(e.get("length") or 0), e.get("error")))
        else:
            played.append(value)
    mean = math.fsum(played) / len(played) if played else None
    low, high = interval(played)
    return Score(mean, low, high, len(played), tuple(forfeits),
                 math.fsum(partial) / len(partial) if partial else None, tuple(played))


def rank_key(score: float | None) -> tuple[bool, float]:
    """Sort key, best last, for a stored ``score`` (NULL for a forfeited assessment): any score above none."""
    return (score is not None, score if score is not None else -math.inf)


def beats(score: float | None, best: float | None, best_exists: bool = True) -> bool:
    """Whether a version scored ``score`` (:attr:`Score.ranked`) takes the best from one scored ``best``:
    a forfeit never does; any played-out score beats a forfeited best (or no best yet: ``best_exists`` False)."""
    if score is None:
        return False
    return not best_exists or best is None or score > best


def interval(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float | None, float | None]:
    """The ``confidence`` percentile-bootstrap interval of the mean of ``values``; (None, None) for fewer than
    two, the value itself twice when they are all equal (nothing to resample)."""
    if len(values) < 2:
        return None, None
    if min(values) == max(values):
        return float(values[0]), float(values[0])
    import numpy as np
    from scipy import stats

    result = stats.bootstrap((np.asarray(values, dtype=float),), np.mean, confidence_level=confidence,
                             n_resamples=RESAMPLES, method="percentile", random_state=np.random.default_rng(SEED))
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


@dataclass(frozen=True)
class Difference:
    """``mean(a) - mean(b)`` with its bootstrap interval, and whether the interval leaves out zero."""

    delta: float
    low: float | None
    high: float | None
    n_a: int
    n_b: int

    @property
    def significant(self) -> bool | None:
        """True when the 95% interval of the difference excludes 0; None when there are too few episodes to say."""
        if self.low is None:
            return None
        return self.low > 0 or self.high < 0

    def verdict(self) -> str:
        if self.significant is None:
            return "too few episodes to tell (need at least 2 played out on each side)"
        band = f"{self.delta:+g} [{self.low:+g}, {self.high:+g}]"
        if self.significant:
            return f"A - B = {band}: a difference beyond the noise (95% interval excludes 0)"
        return f"A - B = {band}: no difference beyond the noise (95% interval includes 0)"


def difference(a: Sequence[float], b: Sequence[float], confidence: float = CONFIDENCE) -> Difference:
    """The difference of the mean returns of two independent sets of episodes, with a bootstrap interval that
    resamples each set on its own."""
    import numpy as np

    delta = (float(np.mean(a)) - float(np.mean(b))) if len(a) and len(b) else math.nan
    if len(a) < 2 or len(b) < 2:
        return Difference(delta, None, None, len(a), len(b))
    if min(a) == max(a) and min(b) == max(b):  # nothing varies: the difference is exact
        return Difference(delta, delta, delta, len(a), len(b))
    from scipy import stats

    result = stats.bootstrap((np.asarray(a, dtype=float), np.asarray(b, dtype=float)),
                             lambda x, y, axis: np.mean(x, axis=axis) - np.mean(y, axis=axis),
                             vectorized=True, paired=False, confidence_level=confidence, n_resamples=RESAMPLES,
                             method="percentile", random_state=np.random.default_rng(SEED))
    return Difference(delta, float(result.confidence_interval.low), float(result.confidence_interval.high),
                      len(a), len(b))


def iqm(strata: Sequence[Sequence[float]], confidence: float = CONFIDENCE
        ) -> tuple[float | None, float | None, float | None]:
    """(interquartile mean, low, high) of the values of all ``strata`` together (e.g. one stratum per game of
    normalized scores, or per seed), with a stratified bootstrap interval: each stratum is resampled on its own,
    as rliable does. Empty strata are left out; (None, None, None) when nothing is left."""
    import numpy as np
    from scipy import stats

    kept = [np.asarray(s, dtype=float) for s in strata if len(s)]
    if not kept:
        return None, None, None
    values = np.concatenate(kept)
    point = float(stats.trim_mean(values, 0.25))
    if len(values) < 2:
        return point, None, None
    varying = [s for s in kept if len(s) >= 2 and s.min() != s.max()]
    fixed = np.concatenate([s for s in kept if not (len(s) >= 2 and s.min() != s.max())] or [np.empty(0)])
    if not varying:  # no stratum has anything to resample: the aggregate is exact
        return point, point, point

    def statistic(*samples, axis=-1):
        batch = samples[0].shape[:-1]
        whole = np.concatenate([*samples, np.broadcast_to(fixed, batch + fixed.shape)], axis=-1)
        return stats.trim_mean(whole, 0.25, axis=-1)

    result = stats.bootstrap(tuple(varying), statistic, vectorized=True, paired=False, confidence_level=confidence,
                             n_resamples=RESAMPLES, method="percentile", random_state=np.random.default_rng(SEED))
    return point, float(result.confidence_interval.low), float(result.confidence_interval.high)


def overfit(tuning_best: float | None, tuning_starter: float | None, audit_best: float | None,
            audit_starter: float | None) -> bool:
    """Whether a run's held-out audit says its best version was fitted to the tuning games: the best forfeited
    an audit game, or less than half of the gain it showed over the starting policy on the tuning seeds is left
    on the audit seeds (both measured against the starter on the same games, so a harder protocol alone, where
    every policy scores less, is not taken for overfitting). A run whose best did not beat its starter claims no
    gain and is never flagged."""
    if tuning_best is None or tuning_starter is None or tuning_best <= tuning_starter:
        return False
    if audit_best is None:
        return True
    gain = tuning_best - tuning_starter
    reference = audit_starter if audit_starter is not None else tuning_starter
    return audit_best - reference < gain / 2


_ERROR_NAME = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_.]*(?:Error|Exception|Exit|Interrupt|Timeout|Warning))\b")


def _error_name(error: str | None) -> str | None:
    """The exception's name at the start of a policy error (``RuntimeError: boom at line 3`` -> RuntimeError)."""
    if not error:
        return None
    match = _ERROR_NAME.match(error)
    return match.group(1) if match else None
