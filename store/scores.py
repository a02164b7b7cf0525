"""How episodes become a score: the one rule every reader of scores uses.

An episode is **played out** when the game ended it (``terminated``) or the step cap did (``truncated``). Any
other end is the policy's doing — it raised or returned an illegal action (``policy_error``), overran a time
limit (``timeout``), its process died or broke the protocol (``crashed``, memory limits included), or its score
was caught tampered (``tampered``) — and the episode is a **forfeit**: its partial return and end reason stay in
the ``episodes`` table, but it is never averaged into a score as if the game had been played.

:func:`score_episodes` turns a set of episodes into a :class:`Score`:

- ``mean``: the mean return of the episodes played out, with a 95% Student-t interval over those episodes
  (scipy's :func:`scipy.stats.ttest_1samp`); none for fewer than two episodes, and none when every episode
  returned the same (there is no spread to measure: under the paper's protocol every seed is the same game);
- ``forfeits``: the forfeited episodes, each with where and why it ended;
- ``ranked``: the score the version competes with — ``mean`` when nothing was forfeited, and **None** when
  anything was. A version with a forfeited assessment therefore never is a run's best and never ranks above a
  version that played its games out, whatever its partial return; in SQL its ``score`` is NULL, so
  ``max(score)`` and ``ORDER BY score DESC NULLS LAST`` read the rule without knowing it;
- ``partial``: the mean return of all the episodes, forfeits at their partial return: what the model is told the
  policy had scored when it stopped, kept in ``candidates.forfeit_score``.

**Every reader.** Whatever shows or ranks a score takes it from here: ``eval``'s headline (:meth:`Score.summary`:
``no score: 5 of 8 episodes forfeited (RuntimeError at step 300 in all 5); the 3 played out averaged 1, not a
score``) and every ``--json`` (:func:`score_json`, :func:`score_data`: ``score`` null with a forfeit), ``compare``
of versions and of runs (:func:`compare_scores`: a side that forfeited is not compared; it says why, and a
sensitivity line counts each forfeit at the game's worst return, :func:`worst_return`), ``report``'s tables and
figures, the OTLP export, and the SQL views, which hold the same rule (a forfeited set's ``score`` is NULL:
``candidates``, ``audits``, ``run_summary.best_score`` of an eval run). The statistics themselves (intervals,
differences, the IQM), and why they are these, are :mod:`store.statistics`'.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Iterable, Mapping, Sequence

from store.statistics import (ALL_EQUAL, CONFIDENCE, DIFFERENCE_METHOD, MEAN_METHOD, TOO_FEW, Difference, Interval,
                              difference, mean_interval, paired_difference)

PLAYED_OUT = ("terminated", "truncated")
"""End reasons of an episode the game or the step cap ended."""
FORFEIT_END_REASONS = ("policy_error", "timeout", "crashed", "tampered")
"""End reasons of an episode the policy ended: a forfeit."""

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
    """The 95% Student-t interval of ``mean`` (None with fewer than two episodes played out, or all equal)."""
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

    @property
    def interval(self) -> Interval:
        """``mean`` with its interval, its level, method and n, or why it has none (:func:`mean_interval`)."""
        reason = None if self.low is not None else TOO_FEW if self.played < 2 else ALL_EQUAL
        return Interval(self.mean, self.low, self.high, self.played, MEAN_METHOD, CONFIDENCE, reason)

    def forfeited_text(self, unit: str = "episode") -> str | None:
        """How many of how many were forfeited and how (None when none was): ``5 of 8 episodes forfeited
        (RuntimeError at step 300 in all 5)``, ``2 of 4 games forfeited (RuntimeError at step 300, timeout at step
        12)``: each way it ended once, the first three."""
        if not self.forfeits:
            return None
        ways: dict[str, int] = {}
        for f in self.forfeits:
            ways[f.describe()] = ways.get(f.describe(), 0) + 1
        if len(ways) == 1 and len(self.forfeits) > 1:
            how = f"{next(iter(ways))} in {'both' if len(self.forfeits) == 2 else f'all {len(self.forfeits)}'}"
        else:
            how = ", ".join(list(ways)[:3]) + (", ..." if len(ways) > 3 else "")
        return f"{len(self.forfeits)} of {self.episodes} {unit}{'s' * (self.episodes != 1)} forfeited ({how})"

    @property
    def no_score(self) -> str | None:
        """Why there is no score (None when there is one): ``no score: 5 of 8 episodes forfeited (RuntimeError at
        step 300 in all 5)``."""
        return None if not self.forfeits else f"no score: {self.forfeited_text()}"

    def played_out_text(self) -> str | None:
        """With forfeits, what the episodes played out averaged, labelled as what it is: ``the 3 played out
        averaged 1.33, not a score`` (None without forfeits, or when none was played out). The one place a
        forfeited set's played-out mean is printed: beside "no score", never as one."""
        if not self.forfeits or self.mean is None:
            return None
        return f"the {self.played} played out averaged {round(self.mean, 2):g}, not a score"

    def summary(self) -> str:
        """The headline of a set of episodes, for people. Its score: ``mean return -20.7 [-21.0, -20.3] 95% t,
        n=3`` (n: the episodes; without an interval, why: ``mean return -21.0 (n=3: all equal, no interval)``);
        with any forfeit, none: ``no score: 5 of 8 episodes forfeited (RuntimeError at step 300 in all 5); the 3
        played out averaged 1.33, not a score``."""
        if self.forfeits:
            return "; ".join(t for t in (self.no_score, self.played_out_text()) if t)
        if self.mean is None:
            return "no episode"
        return f"mean return {self.interval.text()}"


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
    found = mean_interval(played)
    return Score(found.point, found.low, found.high, len(played), tuple(forfeits),
                 math.fsum(partial) / len(partial) if partial else None, tuple(played))


def score_data(score: Score) -> dict[str, Any]:
    """A score's mean and interval as plain data (``--json``): ``mean``, ``low``, ``high``, ``played`` (n), and the
    interval's ``level``, ``method``, ``reason`` (why there is none) and ``interval``, the line people read. With
    any forfeit there is no score: ``mean``, ``low``, ``high`` and ``interval`` are None and ``reason`` is
    ``forfeited`` (:func:`score_json` adds what the episodes played out averaged, labelled as not a score)."""
    found = score.interval
    if score.forfeits:
        return {"mean": None, "low": None, "high": None, "played": score.played, "level": found.level,
                "method": found.method, "reason": "forfeited", "interval": None}
    return {"mean": score.mean, "low": score.low, "high": score.high, "played": score.played, "level": found.level,
            "method": found.method, "reason": found.reason,
            "interval": found.text() if score.mean is not None else None}


def score_json(score: Score) -> dict[str, Any]:
    """A set's score as every ``--json`` gives it, by the rule: ``score``, :func:`score_data` of the ranked score,
    or **None** with any forfeit; ``no_score``, why there is none (:attr:`Score.no_score`); ``forfeits``, each
    forfeited episode (``end_reason``, ``step``, ``error``, ``describe``); and with forfeits ``played_out``, the
    mean and number of the episodes played out, with ``note`` saying it is not a score."""
    return {"score": None if score.forfeits else score_data(score), "no_score": score.no_score,
            "forfeits": [{"end_reason": f.end_reason, "step": f.step, "error": f.error, "describe": f.describe()}
                         for f in score.forfeits],
            **({"played_out": {"mean": score.mean, "episodes": score.played, "note": "not a score"}}
               if score.forfeits else {})}


def score_text(value: float) -> str:
    """A score or return as people read it beside the others: at most two decimals, no trailing zeros (``66.67``,
    ``-20.5``, ``3``), where a mean of three games would otherwise print as ``66.6667``."""
    return f"{round(value, 2) + 0.0:g}"  # + 0.0: -0.004 is 0, not -0



NO_BEST = "no score: every version it assessed forfeited a game"
"""Why a run has no best score: a played-out score beats any forfeit, so none was played out."""


def rank_key(score: float | None) -> tuple[bool, float]:
    """Sort key, best last, for a stored ``score`` (NULL for a forfeited assessment): any score above none."""
    return (score is not None, score if score is not None else -math.inf)


def beats(score: float | None, best: float | None, best_exists: bool = True) -> bool:
    """Whether a version scored ``score`` (:attr:`Score.ranked`) takes the best from one scored ``best``:
    a forfeit never does; any played-out score beats a forfeited best (or no best yet: ``best_exists`` False)."""
    if score is None:
        return False
    return not best_exists or best is None or score > best


@dataclass(frozen=True)
class Comparison:
    """Two sets of episodes compared by the one rule: when both played every episode out, :attr:`difference` says
    whether they differ beyond the noise; when either forfeited one, there is no score to compare and
    :meth:`verdict` says so and why (``A forfeited 2 of 4 games: no score to compare``), never which is better.
    :attr:`sensitivity` (with a worst return) is the difference with every forfeit counted at that return: how
    much the refusal could hide, printed as a sensitivity check without a verdict."""

    a: Score
    b: Score
    labels: tuple[str, str] = ("A", "B")
    worst: float | None = None
    worst_source: str | None = None
    """The return a forfeit is counted at in :attr:`sensitivity`, and where it comes from (the game module's,
    or the lowest return played out in the comparison)."""
    paired: bool = False
    """Whether episode ``i`` of each side was played on the same seed with the same random draws: the difference
    is then :func:`paired_difference` (the sensitivity line, whose forfeits break the pairs, stays Welch's)."""

    @property
    def forfeited(self) -> bool:
        return bool(self.a.forfeits or self.b.forfeits)

    @cached_property  # a t-test: data() and verdict() each read it (a frozen dataclass keeps its __dict__)
    def difference(self) -> Difference | None:
        """:func:`difference` of the two sets' returns; None when either forfeited (no score to compare)."""
        if self.forfeited:
            return None
        if self.paired:
            return paired_difference(self.a.returns, self.b.returns)
        return difference(self.a.returns, self.b.returns)

    @cached_property
    def sensitivity(self) -> Difference | None:
        """With a forfeit and a worst return: the difference with each forfeit counted at ``worst`` (the played-out
        returns as they are); None otherwise."""
        if not self.forfeited or self.worst is None:
            return None
        return difference(self.a.returns + (self.worst,) * len(self.a.forfeits),
                          self.b.returns + (self.worst,) * len(self.b.forfeits))

    @property
    def significant(self) -> bool | None:
        """Whether the difference is beyond the noise; None when there is no call to make (a forfeit, too few)."""
        found = self.difference
        return None if found is None else found.significant

    def refusal(self) -> str | None:
        """Why the two cannot be compared: ``A forfeited 2 of 4 games: no score to compare`` (None: they can)."""
        sides = [(label, s) for label, s in zip(self.labels, (self.a, self.b)) if s.forfeits]
        if not sides:
            return None
        said = " and ".join(f"{label} forfeited {len(s.forfeits)} of {s.episodes} game{'s' * (s.episodes != 1)}"
                            for label, s in sides)
        return f"{said}: no score to compare"

    def verdict(self) -> str:
        """The difference's verdict (:meth:`Difference.verdict`), or the refusal: ``cannot compare: A forfeited 2
        of 4 games: no score to compare (a forfeit is never scored, so neither side is called better)``."""
        if self.forfeited:
            return f"cannot compare: {self.refusal()} (a forfeit is never scored, so neither side is called better)"
        return self.difference.verdict()

    def sensitivity_text(self) -> str | None:
        """``sensitivity, not a score: with each forfeit counted at -21 (the game's worst return, games/pong.py),
        A - B = -4.0 [-9.1, +1.1] 95% Welch t, n=4 and 4``; None without one."""
        found = self.sensitivity
        if found is None:
            return None
        return (f"sensitivity, not a score: with each forfeit counted at {self.worst:g} ({self.worst_source}), "
                f"{self.labels[0]} - {self.labels[1]} = {found.interval.text(signed=True)}")

    def data(self) -> dict[str, Any]:
        """As plain data (``--json``): ``delta``, ``low``, ``high``, ``level``, ``method``, ``n``, ``reason``,
        ``significant`` (all None when a side forfeited: ``reason`` ``forfeited``), ``verdict``, ``forfeited``
        (per side with a forfeit: how many of how many) and ``sensitivity`` (None, or its ``worst``, where that
        comes from, the difference and the line)."""
        found = self.difference
        if found is None:
            base = {"delta": None, "low": None, "high": None, "level": CONFIDENCE, "method": DIFFERENCE_METHOD,
                    "n": [self.a.played, self.b.played], "reason": "forfeited", "significant": None}
        else:
            base = {"delta": found.delta, "low": found.low, "high": found.high, "level": found.level,
                    "method": found.method, "n": [found.n_a, found.n_b], "reason": found.reason,
                    "significant": found.significant}
        shifted = self.sensitivity
        return {**base, "verdict": self.verdict(),
                "forfeited": {label: s.forfeited_text("game") for label, s in zip(self.labels, (self.a, self.b))
                              if s.forfeits} or None,
                "sensitivity": None if shifted is None else {
                    "worst": self.worst, "worst_source": self.worst_source, "delta": shifted.delta,
                    "low": shifted.low, "high": shifted.high, "n": [shifted.n_a, shifted.n_b],
                    "text": self.sensitivity_text()}}


def worst_return(known: float | None, game: str, scores: Sequence[Score]) -> tuple[float | None, str | None]:
    """The return a forfeit is counted at in a sensitivity check, and where it comes from: the game module's
    worst return (``known``: ``Game.worst_return``), else the lowest return played out among ``scores`` (said so);
    (None, None) when neither is there."""
    if known is not None:
        return float(known), f"the game's worst return, games/{game}.py"
    seen = [r for s in scores for r in s.returns]
    if not seen:
        return None, None
    return min(seen), f"the lowest return played out here: games/{game}.py gives no worst return"


def compare_scores(a: Score, b: Score, worst: float | None = None, worst_source: str | None = None,
                   labels: tuple[str, str] = ("A", "B"), paired: bool = False) -> Comparison:
    """:class:`Comparison` of two scored sets of episodes (the rule: no verdict when either forfeited); ``paired``:
    played pair by pair (:attr:`Comparison.paired`)."""
    return Comparison(a, b, labels, worst, worst_source, paired)


def overfit(tuning_best: float | None, tuning_starter: float | None, audit_best: float | None,
            audit_starter: float | None) -> bool | None:
    """Whether a run's held-out audit says its best version was fitted to the tuning games: the best forfeited
    an audit game, or less than half of the gain it showed over the starting policy on the tuning seeds is left
    on the audit seeds (both measured against the starter on the same games, so a harder protocol alone, where
    every policy scores less, is not taken for overfitting). A run whose best did not beat its starter claims no
    gain and is never flagged. **None: no reference**, when the starter forfeited its audit games (no score, by
    the rule) and the best played its out: the only other starter score is its tuning one, on other games under
    the run's own protocol, and the best's held-out score against it would read a harder protocol as lost gain
    (or an easier one as gain kept), the very comparison across protocols this rule is built to avoid."""
    if tuning_best is None or tuning_starter is None or tuning_best <= tuning_starter:
        return False
    if audit_best is None:
        return True
    if audit_starter is None:
        return None
    return audit_best - audit_starter < (tuning_best - tuning_starter) / 2


NO_REFERENCE = ("no reference: the starting policy forfeited its held-out games, so the best's gain over it cannot "
                "be measured there (its tuning score is other games, under another protocol)")
"""What is said of a run whose overfit check has no reference (:func:`overfit` None)."""


_ERROR_NAME = re.compile(r"\s*([^\W\d]\w*…?)(?=: | at line [0-9]|$)")
"""The name at the start of an error that ``pipeline/boundary/policy.py``'s ``describe_exception`` wrote: ``Name:
message at line N: `text```, ``Name at line N`` or ``Name`` (a message-less exception), the name an identifier
(cut to ``capture.MAX_NAME_CHARS`` with ``…``). Read by that structure, not by how the name ends: ``class
Boom(Exception)`` is ``Boom`` (a suffix list named it ``policy_error``); the host's own errors (``malformed trace
at step 3: ...``, ``the policy process ended ...``, ``policy.py:3: ...``) begin with no such name."""


def _error_name(error: str | None) -> str | None:
    """The exception's name at the start of a policy error (``RuntimeError: boom at line 3`` -> RuntimeError,
    ``Boom at line 3`` -> Boom)."""
    if not error:
        return None
    match = _ERROR_NAME.match(error)
    return match.group(1) if match else None
