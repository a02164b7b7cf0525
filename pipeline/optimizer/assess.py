"""*assess*: versions → a traced training rollout and the evaluation episodes → a score.

Every version of an iteration is assessed at once: the episodes of all of them go to one pool of game hosts, each
with a confined policy process (``pipeline/play/episodes.py``), so candidates are played concurrently. The host
computes every score where no policy code runs, so a score needs no replay to be trusted (runs stored before the
game host may hold episodes a replay caught, end reason ``tampered``: such a version is never taken as the best).
Episodes are written to the store as they finish.

**Cascade evaluation** (``screen_steps``): a new version first plays the first evaluation game for that many
steps (kind ``screen``); one that trails its parent's score at the same step of the same game (deterministic:
the same seed) by more than ``screen_margin`` is screened out before its full assessment (:func:`screen`).

Under the authors' one-life protocol (``one_life = "continue"``) the evaluation episodes are the lives of one
game, played in order by one game host and policy process (``pipeline/play/episodes.py``).

With ``robust_episodes``, each version also plays that many evaluation episodes under the standard protocol
(sticky actions, no-op starts; kind ``robust``, seeded like the others): both scores are recorded, and
``optimize_protocol`` says which one the strategy optimizes.

The **evaluation cache**: episodes are deterministic given the policy's code and the run's settings (seeds,
caps, protocol; fixed for a run), so a version already assessed in this run reuses that assessment's stored
episodes instead of playing them again — a rejected or unchanged proposal, which falls back to its parent's
code, costs no environment step. Only assessments whose every episode was verified and ended by the game or
the step cap are reused (a time limit depends on the machine's load, not on the code). A version appearing
twice in one iteration is played once, and in the proposal pool one assessed in an iteration not committed yet is
not played again (``pending``).
"""

from __future__ import annotations

import statistics
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Iterator, Sequence

from games.base import ONE_LIFE_CONTINUE, STANDARD_NOOP_MAX, STANDARD_STICKY
from pipeline.boundary.workers import DeadlinePassed
from pipeline.optimizer.budgets import BudgetExhausted
from pipeline.optimizer.state import RunState
from pipeline.play.episodes import run_episodes
from pipeline.play.rollout import EpisodeOutcome
from pipeline.play.runinfo import episode_id
from pipeline.play.spec import EpisodeSpec
from pipeline.play.verify import TAMPERED, checked_outcome, tampering
from store import Store
from store.readers import earlier_screen, policy_text, reusable_assessment, score_at_step
from store.scores import score_episodes
from store.writer import EpisodeWriter


@dataclass
class Assessment:
    version_id: str
    train_episode_id: str
    eval_episode_ids: list[str]
    train_return: float
    train_length: int
    score: float | None
    """The score the run optimizes: ``deterministic_score`` or ``standard_score`` (``optimize_protocol``); None
    when any of the version's evaluation games was forfeited (``store/scores.py``: a forfeit has no score to rank)."""
    evaluation: str
    """``played``, or ``cached``: the episodes of an earlier assessment of the same version."""
    deterministic_score: float | None
    """The score of the evaluation episodes under the paper's protocol (None: one was forfeited)."""
    standard_score: float | None = None
    """The score of the ``robust`` episodes under the standard protocol (None: none played, or one forfeited)."""
    robust_episode_ids: list[str] = field(default_factory=list)
    tampered: str | None = None
    eval_length: float = 0.0
    """Mean length of the evaluation games (a behaviour descriptor for ``map-elites``)."""
    forfeit: str | None = None
    """What ended a forfeited evaluation game (``1 of 3 episodes forfeited: RuntimeError at step 300
    (policy_error)``); None when every one was played out."""
    forfeit_score: float | None = None
    """With a forfeit: the mean return of the optimized protocol's games, forfeits at their partial return."""
    score_low: float | None = None
    score_high: float | None = None
    """The 95% Student-t interval of ``score`` over its episodes (None: fewer than two, all equal, or forfeited)."""


@dataclass
class AssessTimes:
    train_s: float = 0.0
    """Until the first training rollout finished."""
    eval_s: float = 0.0
    """Until every episode finished."""


def episode_specs(state: "RunState", iteration: int, candidate: int, text: str, version_id: str) -> list[EpisodeSpec]:
    """The traced training rollout and the evaluation episodes of one version, as the run's settings say."""
    c = state.config
    common = dict(run_id=state.run_id, game=state.game, policy_text=text, policy_version_id=version_id,
                  policy_name="policy.py", iteration=iteration, call_time_limit_s=c.call_time_limit_s,
                  episode_time_limit_s=c.episode_time_limit_s, rerun=state.rerun, one_life=c.one_life,
                  observation=c.observation, rng_key=state.rng_key)
    train = EpisodeSpec(episode_id=episode_id(state.run_id, iteration, "train", 0, candidate), kind="train",
                        index=0, seed=c.seed, max_steps=state.settings["rollout_steps"], trace=True, **common)
    one_game = c.one_life == ONE_LIFE_CONTINUE  # the authors' protocol: the evaluation episodes are one game's lives
    evals = [EpisodeSpec(episode_id=episode_id(state.run_id, iteration, "eval", i, candidate), kind="eval", index=i,
                         seed=c.seed if one_game else c.seed + i, max_steps=state.settings["eval_max_steps"],
                         continues=episode_id(state.run_id, iteration, "eval", i - 1, candidate) if one_game and i
                         else None, **common)
             for i in range(c.eval_episodes)]
    robust = [EpisodeSpec(episode_id=episode_id(state.run_id, iteration, "robust", i, candidate), kind="robust",
                          index=i, seed=c.seed + i, max_steps=state.settings["eval_max_steps"], sticky=STANDARD_STICKY,
                          noop_max=STANDARD_NOOP_MAX, **common)
              for i in range(c.robust_episodes)]
    return [train] + evals + robust


def assess(store: Store, state: "RunState", iteration: int, versions: dict[int, str],
           progress: Callable[[int, int], None] | None = None,
           texts: dict[str, str] | None = None,
           before_play: Callable[[], None] = lambda: None,
           after_play: Callable[[], None] = lambda: None,
           pending: Sequence[Assessment] = ()) -> tuple[dict[int, Assessment], AssessTimes]:
    """Assess ``versions`` (candidate → version id) of iteration ``iteration``: an :class:`Assessment` per
    candidate, and how long the playing took. ``texts``: the policy files of versions not stored yet (this
    iteration's new ones); the others are read from the store. ``before_play`` is called before any episode
    is played (the optimizer lets go of its hold on the store: playing takes a while), ``after_play`` once the
    last has ended, before the last of them are written (the optimizer takes its hold again: that write shares
    its attachment, and the file is checkpointed once, when the hold is let go, not twice). ``pending``: the
    proposal pool's assessments whose iterations are not committed yet (their episodes are stored), which the
    evaluation cache may reuse too: a rejected candidate falls back to its parent's code, often a pending one."""
    owner: dict[str, int] = {}  # version -> the candidate whose episodes stand for it in this iteration
    for candidate, version in sorted(versions.items()):
        owner.setdefault(version, candidate)
    found: dict[str, Assessment] = {}
    if state.config.eval_cache:
        with store.read() as con:
            for version in owner:
                row = reusable_assessment(con, state.run_id, version, pending_rows(pending, version))
                if row is not None:
                    found[version] = _cached(version, row)
    to_play = [(candidate, version) for version, candidate in owner.items() if version not in found]
    times = AssessTimes()
    if to_play:
        before_play()
        found.update(_play(store, state, iteration, to_play, progress, times, texts or {}, after_play))
    return {candidate: found[version] for candidate, version in versions.items()}, times


@dataclass
class Screen:
    """Cascade evaluation: how a new version did in the first ``steps`` steps of the first evaluation game."""

    episode_id: str
    steps: int
    score: float
    """Its (verified) return in those steps."""
    bar: float
    """Its parent's score at the same step of the same game, less ``screen_margin``: what it had to reach."""
    tampered: bool = False
    forfeit: str | None = None
    """The policy ended the screening game itself (an error, a time limit, tampering): it cannot pass."""

    @property
    def passed(self) -> bool:
        return not self.tampered and self.forfeit is None and self.score >= self.bar


def screen(store: Store, state: "RunState", iteration: int, history, proposals: list,
           progress: Callable[[int, int], None] | None = None,
           before_play: Callable[[], None] = lambda: None, pending: Sequence[Assessment] = ()) -> dict[int, Screen]:
    """(``proposals``: this iteration's accepted ones, each with the ``text`` of its new version.)"""
    """Play the screening game of each new version in ``proposals``, all at once; a :class:`Screen` per
    candidate screened. With the evaluation cache, a version already assessed needs no screen, and one already
    screened in the run reuses that game."""
    c = state.config
    specs, owners = [], []
    found: dict[int, Screen] = {}
    with store.read() as con:
        for p in proposals:
            if c.eval_cache and reusable_assessment(con, state.run_id, p.version_id,
                                                    pending_rows(pending, p.version_id)) is not None:
                continue
            parent = history.candidate(p.parent)
            bar = score_at_step(con, parent["eval_episode_ids"][0], c.screen_steps - 1) - c.screen_margin
            earlier = earlier_screen(con, state.run_id, p.version_id) if c.eval_cache else None
            if earlier is not None:  # screened before in this run: the same game, the same score
                found[p.candidate] = Screen(earlier["episode_id"], c.screen_steps, earlier["score"], bar,
                                            tampered=earlier["end_reason"] == TAMPERED,
                                            forfeit=score_episodes([earlier]).forfeit)
                continue
            text = p.text if p.text is not None else policy_text(con, state.run_id, p.version_id)
            specs.append(EpisodeSpec(
                episode_id=episode_id(state.run_id, iteration, "screen", 0, p.candidate), run_id=state.run_id,
                game=state.game, policy_text=text, policy_version_id=p.version_id, iteration=iteration, kind="screen",
                index=0, seed=c.seed, max_steps=c.screen_steps, call_time_limit_s=c.call_time_limit_s,
                episode_time_limit_s=c.episode_time_limit_s, one_life=c.one_life, observation=c.observation,
                rng_key=state.rng_key))
            owners.append((p.candidate, bar))
    if not specs:
        return found
    before_play()
    with EpisodeWriter(store, replace=True) as writer, _within_the_time_budget(state, iteration):
        for i, outcome in run_episodes(specs, workers=max(1, c.workers), progress=progress,
                                       deadline=state.wall_deadline):
            outcome = checked_outcome(specs[i], outcome)
            writer.add(outcome.episode, outcome.steps, outcome.nodes)
            candidate, bar = owners[i]
            found[candidate] = Screen(outcome.episode["episode_id"], c.screen_steps, outcome.episode["return"], bar,
                                      tampered=outcome.episode["end_reason"] == TAMPERED,
                                      forfeit=score_episodes([outcome.episode]).forfeit)
    return found


@contextmanager
def _within_the_time_budget(state: "RunState", iteration: int) -> Iterator[None]:
    """Games that pass the run's time budget (``--max-wall``) are stopped there and the run ends ``budget``: a
    candidate that hung (its call limit off) held the run until its episodes' time limit, 15 minutes each. Being
    stopped is not the candidate's doing, so nothing of the iteration is scored or committed; ``--resume`` with
    more time plays it again."""
    try:
        yield
    except DeadlinePassed:
        raise BudgetExhausted(f"time budget: --max-wall {state.config.max_wall_minutes:g} min ran out while "
                              f"iteration {iteration}'s games played (stopped there: none of them counts)",
                              "max_wall_minutes") from None


def pending_rows(pending: Sequence[Assessment], version: str) -> list[dict]:
    """The assessments of ``version`` among ``pending`` that the evaluation cache may reuse (played, not caught
    tampering: the rest is checked on their stored episodes), in the shape of the ``candidates`` rows it reads."""
    return [dict(train_episode_id=a.train_episode_id, eval_episode_ids=a.eval_episode_ids,
                 robust_episode_ids=a.robust_episode_ids, train_return=a.train_return, score=a.score,
                 deterministic_score=a.deterministic_score, standard_score=a.standard_score,
                 score_low=a.score_low, score_high=a.score_high)
            for a in pending if a.version_id == version and a.evaluation == "played" and a.tampered is None]


def _cached(version: str, row: dict) -> Assessment:
    return Assessment(version, row["train_episode_id"], list(row["eval_episode_ids"]), row["train_return"],
                      row["train_length"], row["score"], "cached", row["deterministic_score"], row["standard_score"],
                      list(row["robust_episode_ids"] or []), eval_length=float(row["eval_length"]),
                      score_low=row.get("score_low"), score_high=row.get("score_high"))


def _play(store: Store, state: "RunState", iteration: int, to_play: list[tuple[int, str]],
          progress: Callable[[int, int], None] | None, times: AssessTimes,
          texts: dict[str, str], after_play: Callable[[], None]) -> dict[str, Assessment]:
    specs: list[EpisodeSpec] = []
    groups: list[tuple[str, list[int]]] = []  # version -> indices of its specs (train first)
    missing = {version for _, version in to_play if version not in texts}
    if missing:
        with store.read() as con:
            texts = {**texts, **{version: policy_text(con, state.run_id, version) for version in missing}}
    for candidate, version in to_play:
        own = episode_specs(state, iteration, candidate, texts[version], version)
        groups.append((version, list(range(len(specs), len(specs) + len(own)))))
        specs.extend(own)
    outcomes: list[EpisodeOutcome | None] = [None] * len(specs)
    started = time.monotonic()
    trains = {indices[0] for _, indices in groups}
    with EpisodeWriter(store, replace=True) as writer, _within_the_time_budget(state, iteration):
        for i, outcome in run_episodes(specs, workers=max(1, state.config.workers), progress=progress,
                                       deadline=state.wall_deadline):
            outcome = checked_outcome(specs[i], outcome)
            writer.add(outcome.episode, outcome.steps, outcome.nodes)
            outcomes[i] = outcome
            trains.discard(i)
            if not trains and not times.train_s:
                times.train_s = time.monotonic() - started
                writer.flush()  # the training rollouts are stored before the evaluations go on
        after_play()
    times.eval_s = time.monotonic() - started
    found = {}
    for version, indices in groups:
        train = outcomes[indices[0]]
        evals = [outcomes[i] for i in indices[1:] if specs[i].kind == "eval"]
        robust = [outcomes[i] for i in indices[1:] if specs[i].kind == "robust"]
        deterministic = score_episodes(o.episode for o in evals)
        standard = score_episodes(o.episode for o in robust) if robust else None
        optimized = standard if state.config.optimize_protocol == "standard" else deterministic
        forfeit = deterministic.forfeit or (standard.forfeit if standard is not None else None)
        found[version] = Assessment(
            version, train.episode["episode_id"], [o.episode["episode_id"] for o in evals], train.episode["return"],
            train.episode["length"], None if forfeit else optimized.ranked, "played", deterministic.ranked,
            standard.ranked if standard is not None else None, [o.episode["episode_id"] for o in robust],
            tampering([train] + evals + robust), statistics.fmean(o.episode["length"] for o in evals),
            forfeit=forfeit, forfeit_score=optimized.partial if forfeit else None,
            score_low=None if forfeit else optimized.low, score_high=None if forfeit else optimized.high)
    return found
