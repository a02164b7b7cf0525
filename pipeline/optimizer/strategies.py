"""Search strategies: which versions the optimizer improves next, and what it makes of the candidates.

A strategy is the third part of the optimizer (``pipeline/optimizer/loop.py`` drives; ``pipeline/optimizer/propose.py`` turns a
request into a candidate; ``pipeline/optimizer/assess.py`` scores it). Each iteration it

1. **plans**: a list of :class:`ProposalRequest` — the candidate to improve (its *parent*, a :class:`Ref` to a
   stored candidate), the earlier candidates the prompt's #Memory shows, and a note for #Feedback;
2. **decides**, once the candidates are assessed: which one stands for the iteration (its ``iterations`` row),
   whether it is the run's new best, and a decision per candidate (``best``, ``kept``, ``discarded``,
   ``rolled_back``, ``rejected``) with the notes that go into its feedback.

Strategies read only :class:`History` — the run's ``iterations`` and ``candidates`` rows, loaded from the store
before each iteration — so a resumed or replayed run makes the same plans. Nothing here speaks SQL or calls a
model.

- ``greedy``: the paper's loop. Improve the previous iteration's version; after a regression below
  ``best - (1 - rollback_fraction) * max(|best|, 1)`` roll back to the best. Memory: the last iterations.
- ``best-of-n``: N proposals from the best version each iteration; the best of them stands for the iteration.
- ``beam``: keep the ``beam_width`` best versions and expand each with N proposals per iteration.
- ``map-elites``: an archive of the best version per behaviour cell (code complexity × game length); each
  proposal improves a random elite, shown other elites as inspirations.

For ``best-of-n``, ``beam`` and ``map-elites`` the memory follows the lineage of the parent: the latest attempts to improve it
(what was tried from here and how it scored) and then its ancestors.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from typing import Any, Protocol

from pipeline.settings import EpisodeLimits
from store.scores import beats, rank_key

STRATEGIES = ("greedy", "best-of-n", "beam", "map-elites")


@dataclass(frozen=True, order=True)
class Ref:
    """A candidate in the store: (iteration, candidate index)."""

    iteration: int
    candidate: int = 0


@dataclass
class ProposalRequest:
    """One proposal to make: improve ``parent``, showing ``memory`` (newest first) and ``note`` in the prompt."""

    candidate: int
    parent: Ref
    memory: list[Ref] = field(default_factory=list)
    note: str = ""


@dataclass
class Assessed:
    """A candidate of this iteration, proposed and assessed: what a strategy decides on."""

    candidate: int
    parent: Ref | None
    version_id: str
    """The version that was played for it (the parent's when the proposal was rejected or unchanged)."""
    status: str
    """``initial``, ``accepted``, ``unchanged``, ``rejected`` (also: caught tampering) or ``llm_error``."""
    score: float | None
    """Its score (``store/scores.py``); None when it forfeited an evaluation game: never the best, ranked last."""
    tampered: str | None = None
    notes: list[str] = field(default_factory=list)
    """What the proposal step has to say in the candidate's feedback (a rejection reason, an LLM error)."""
    behaviour: dict[str, Any] = field(default_factory=dict)
    """Behaviour descriptors from the store: ``complexity`` (of its code), ``eval_length`` (mean length of its
    evaluation games)."""
    forfeit: str | None = None
    """What ended the evaluation game it forfeited (then ``score`` is None)."""


@dataclass
class Decision:
    chosen: int
    """The candidate whose version, episodes and score make the iteration's row."""
    decisions: dict[int, str]
    notes: dict[int, list[str]]
    """Each candidate's feedback notes, final."""
    new_best: int | None = None
    """The candidate that becomes the run's best, if any."""
    rolled_back: bool = False
    """``greedy`` only: the next iteration starts again from the best version."""


@dataclass
class History:
    """A run's completed iterations and their candidates, as stored (``store.readers.candidates``).

    The proposal pool (``pipeline/optimizer/pool.py``) also plans from a *basis* with ``pending`` candidates: ones
    already assessed whose iteration is not committed yet. Their rows are the last of ``candidates`` (decision
    ``pending``, or ``rejected``), memory and beams see them like any other, and :attr:`best` takes one that beats
    the committed best; ``iterations`` and :attr:`best_score` stay the committed ones, which strategies decide
    against."""

    iterations: list[dict[str, Any]]
    candidates: list[dict[str, Any]]
    pending: list[Ref] = field(default_factory=list)
    """Candidates assessed, not yet committed, in (iteration, candidate) order: the last rows of ``candidates``."""
    as_of: Any = None
    """When the proposal pool took this basis (a datetime; recorded with the calls made from it)."""

    def __post_init__(self) -> None:
        self._by_ref = {Ref(c["iteration"], c["candidate"]): c for c in self.candidates}

    def candidate(self, ref: Ref) -> dict[str, Any]:
        return self._by_ref[ref]

    def chosen(self, iteration: int) -> Ref:
        row = self.iterations[iteration]
        return Ref(row["iteration"], row.get("candidate") or 0)

    @property
    def best(self) -> Ref | None:
        """The candidate that holds the run's best score (the iteration the last row names, its chosen one); with
        ``pending`` candidates, the best of them if it beats that (``beats``; the first among equals; never one
        rejected or caught tampering)."""
        if not self.iterations:
            return None
        best, score = self.chosen(self.iterations[-1]["best_iteration"]), self.best_score
        for ref in self.pending:
            row = self._by_ref[ref]
            if row["decision"] != "rejected" and beats(row["score"], score, True):
                best, score = ref, row["score"]
        return best

    @property
    def best_score(self) -> float | None:
        return self.iterations[-1]["best_score"] if self.iterations else None

    def parent(self, ref: Ref) -> Ref | None:
        row = self.candidate(ref)
        if row["parent_iteration"] is None:
            return None
        return Ref(row["parent_iteration"], row["parent_candidate"] or 0)

    def ancestors(self, ref: Ref) -> list[Ref]:
        """The candidates ``ref`` descends from, nearest first."""
        found, seen = [], {ref}
        parent = self.parent(ref)
        while parent is not None and parent not in seen and parent in self._by_ref:
            found.append(parent)
            seen.add(parent)
            parent = self.parent(parent)
        return found

    def lineage_memory(self, ref: Ref, size: int) -> list[Ref]:
        """Memory along the lineage of ``ref``: the latest attempts to improve it, then its ancestors."""
        attempts = [Ref(c["iteration"], c["candidate"]) for c in reversed(self.candidates)
                    if c["parent_iteration"] == ref.iteration and (c["parent_candidate"] or 0) == ref.candidate]
        return (attempts + self.ancestors(ref))[:size]

    def assessed_versions(self) -> list[tuple[float | None, Ref]]:
        """Each distinct version that was played and not caught tampering, by its first candidate: (score, ref),
        best first (earlier first among equals); versions that forfeited (score None) after every other."""
        first: dict[str, tuple[float | None, Ref]] = {}
        for c in self.candidates:
            tampered = c["decision"] == "rejected" and c["policy_version_id"] == c["proposed_version_id"]
            unscored = c["score"] is None and c.get("forfeit") is None  # never assessed (no score, no forfeit)
            if tampered or unscored or c["policy_version_id"] in first:
                continue
            first[c["policy_version_id"]] = (c["score"], Ref(c["iteration"], c["candidate"]))
        return sorted(first.values(), key=lambda item: (_descending(item[0]), item[1]))

    def played_out_versions(self) -> list[tuple[float | None, Ref]]:
        """:meth:`assessed_versions` that a strategy may improve: those that played their games out (a forfeit is
        never ranked, so never a beam's member or an archive's elite); the forfeits only when no version played
        out (a starter that forfeits is all there is to improve)."""
        versions = self.assessed_versions()
        return [(score, ref) for score, ref in versions if score is not None] or versions

    def beaten_by(self, score: float | None) -> bool:
        """Whether a version that scored ``score`` takes the run's best (``store.scores.beats``)."""
        return beats(score, self.best_score, self.best is not None)


def _descending(score: float | None) -> tuple[bool, float]:
    """Sort key, best first: higher scores first, a forfeit (None) after every score."""
    present, value = rank_key(score)
    return (not present, -value)


def format_number(value: Any) -> str:
    return f"{value:.6g}" if isinstance(value, float) else str(value)


class Strategy(Protocol):
    name: str
    max_proposals: int
    """The most proposals (LLM calls) it makes in one iteration."""

    def plan(self, history: History, iteration: int) -> list[ProposalRequest]:
        """The proposals of iteration ``iteration`` (>= 1)."""

    def decide(self, history: History, iteration: int, assessed: list[Assessed]) -> Decision:
        """What the assessed candidates of iteration ``iteration`` mean for the run."""


def _rank(assessed: list[Assessed]) -> list[Assessed]:
    """Candidates best first; among equal scores, new code before a rejected proposal (which only re-played its
    parent), then the lowest index; tampered ones last."""
    return sorted(assessed, key=lambda a: (a.tampered is not None, _descending(a.score),
                                           a.status in ("rejected", "llm_error"), a.candidate))


def with_tampering(a: Assessed) -> list[str]:
    """A candidate's feedback notes, a note that it was caught tampering first (whatever is decided on it)."""
    notes = list(a.notes)
    if a.tampered:
        notes.insert(0, f"Your last suggestion was rejected: {a.tampered}")
    return notes


def decide_starter(assessed: list[Assessed]) -> Decision:
    """Iteration 0, whatever the strategy: the starting policy is the best so far."""
    (a,) = assessed
    return Decision(chosen=a.candidate, decisions={a.candidate: "best"}, notes={a.candidate: list(a.notes)},
                    new_best=a.candidate)


@dataclass
class Greedy:
    """The paper's loop: one proposal per iteration from the previous version, rollback after a regression."""

    memory: int = 5
    rollback: bool = True
    rollback_fraction: float = 0.5
    name: str = "greedy"
    max_proposals = 1

    def plan(self, history: History, iteration: int) -> list[ProposalRequest]:
        previous = history.iterations[iteration - 1]
        parent, note = history.chosen(iteration - 1), ""
        if previous["rolled_back"]:
            parent = history.chosen(previous["best_iteration"])
            note = (f"Iteration {previous['iteration']} scored {format_number(previous['score'])}, below the best "
                    f"{format_number(previous['best_score'])} of iteration {parent.iteration}, so its change was "
                    f"rolled back: you are improving iteration {parent.iteration}'s code again (see #Memory for what "
                    "regressed).\n")
        memory = [history.chosen(row["iteration"]) for row in reversed(history.iterations[:iteration])
                  if row["iteration"] != parent.iteration][:self.memory]
        return [ProposalRequest(0, parent, memory, note)]

    def decide(self, history: History, iteration: int, assessed: list[Assessed]) -> Decision:
        (a,) = assessed
        best_score, best = history.best_score, history.best
        best_version = history.candidate(best)["policy_version_id"] if best is not None else None
        notes = with_tampering(a)
        decision = Decision(chosen=a.candidate, decisions={a.candidate: "kept"}, notes={a.candidate: notes})
        if a.tampered:  # never the best; the next update starts from the best
            decision.decisions[a.candidate] = "rejected"
            decision.rolled_back = best_version is not None and a.version_id != best_version
        elif history.beaten_by(a.score):
            decision.new_best = a.candidate
            decision.decisions[a.candidate] = "best"
        else:
            regressed = None  # why the next update starts again from the best
            if a.score is None:  # a forfeit: a regression whatever it had scored when it stopped
                regressed = (f"did not play its evaluation game to the end ({a.forfeit}): a forfeit never counts as "
                             "an improvement, so")
            elif a.score < best_score - (1 - self.rollback_fraction) * max(abs(best_score), 1.0):
                regressed = f"scored {a.score:g}, below the best {best_score:g} (iteration {best.iteration}):"
            if regressed and self.rollback and a.version_id != best_version:
                decision.rolled_back = True
                decision.decisions[a.candidate] = "rolled_back"
                notes.append(f"This version {regressed} its change is rolled back, and the next update starts again "
                             f"from iteration {best.iteration}'s code.")
            if a.status == "rejected":
                decision.decisions[a.candidate] = "rejected"
        return decision


def _decide_by_rank(history: History, assessed: list[Assessed], kept: set[str]) -> Decision:
    """Shared by the population-style strategies: the iteration's best candidate stands for it and becomes the
    run's best if it beats it; candidates whose version is in ``kept`` are ``kept``, the others ``discarded``."""
    ranked = _rank(assessed)
    top = ranked[0]
    decision = Decision(chosen=top.candidate, decisions={}, notes={})
    if top.tampered is None and history.beaten_by(top.score):
        decision.new_best = top.candidate
    for a in assessed:
        notes = with_tampering(a)
        if a.tampered or a.status == "rejected":
            verdict = "rejected"
        elif a.candidate == decision.new_best:
            verdict = "best"
        else:
            verdict = "kept" if a.version_id in kept else "discarded"
        decision.decisions[a.candidate] = verdict
        decision.notes[a.candidate] = notes
    return decision


@dataclass
class BestOfN:
    """N proposals from the run's best version each iteration; the best of them stands for the iteration."""

    candidates: int = 4
    memory: int = 5
    name: str = "best-of-n"

    @property
    def max_proposals(self) -> int:
        return self.candidates

    def plan(self, history: History, iteration: int) -> list[ProposalRequest]:
        parent = history.best
        memory = history.lineage_memory(parent, self.memory)
        return [ProposalRequest(i, parent, memory) for i in range(self.candidates)]

    def decide(self, history: History, iteration: int, assessed: list[Assessed]) -> Decision:
        return _decide_by_rank(history, assessed, kept=set())


@dataclass
class Beam:
    """Keep the ``width`` best versions; expand each with ``candidates`` proposals per iteration."""

    width: int = 3
    candidates: int = 1
    memory: int = 5
    name: str = "beam"

    @property
    def max_proposals(self) -> int:
        return self.width * self.candidates

    def beam(self, history: History) -> list[Ref]:
        return [ref for _, ref in history.played_out_versions()[:self.width]]

    def plan(self, history: History, iteration: int) -> list[ProposalRequest]:
        requests = []
        for parent in self.beam(history):
            memory = history.lineage_memory(parent, self.memory)
            for _ in range(self.candidates):
                requests.append(ProposalRequest(len(requests), parent, memory))
        return requests

    def decide(self, history: History, iteration: int, assessed: list[Assessed]) -> Decision:
        scored = [(c["score"], c["policy_version_id"]) for c in (history.candidate(r) for r in self.beam(history))]
        scored += [(a.score, a.version_id) for a in assessed
                   if not a.tampered and a.status != "rejected" and a.score is not None]
        kept, seen = set(), set()
        for score, version in sorted(scored, key=lambda item: _descending(item[0])):
            if version not in seen and len(seen) < self.width:
                kept.add(version)
            seen.add(version)
        return _decide_by_rank(history, assessed, kept)


@dataclass
class MapElites:
    """A MAP-Elites archive over behaviour the store already has: the code's cyclomatic complexity (bins of
    ``COMPLEXITY_BIN``) × how long its evaluation games last (quarters of the evaluation cap). Each cell keeps
    its best version (its elite). Each iteration makes ``candidates`` proposals, each from an elite drawn at
    random (seeded by the run's seed and the iteration, so a resumed or replayed run draws the same), with other
    elites as inspirations in the prompt's #Memory: diverse strategies survive beside the best one."""

    candidates: int = 4
    memory: int = 5
    seed: int = 0
    eval_max_steps: int = EpisodeLimits.max_steps
    name: str = "map-elites"

    COMPLEXITY_BIN = 4

    @property
    def max_proposals(self) -> int:
        return self.candidates

    def cell(self, row: dict[str, Any]) -> tuple[int, int]:
        complexity = row.get("complexity") or 0
        length = row.get("eval_length") or 0
        return (int(complexity) // self.COMPLEXITY_BIN, min(3, int(4 * length / max(1, self.eval_max_steps))))

    def archive(self, history: History) -> dict[tuple[int, int], Ref]:
        """Cell -> its elite (the first candidate reaching the cell's best score; never a forfeit while a version
        played out: a game it ended early made a cell of its own, and the forfeit drew parents as any elite)."""
        elites: dict[tuple[int, int], tuple[float, Ref]] = {}
        for score, ref in history.played_out_versions():  # best first: a cell's first is its elite
            cell = self.cell(history.candidate(ref))
            if cell not in elites:
                elites[cell] = (score, ref)
        return {cell: ref for cell, (_, ref) in elites.items()}

    def plan(self, history: History, iteration: int) -> list[ProposalRequest]:
        elites = sorted(self.archive(history).values())
        rng = random.Random(self.seed * 1_000_003 + iteration)
        ranked = [ref for _, ref in history.assessed_versions() if ref in elites]
        requests = []
        for i in range(self.candidates):
            parent = rng.choice(elites)
            inspirations = [ref for ref in ranked if ref != parent][:max(1, self.memory // 2)]
            memory = (inspirations + history.lineage_memory(parent, self.memory))[:self.memory]
            requests.append(ProposalRequest(i, parent, list(dict.fromkeys(memory))))
        return requests

    def decide(self, history: History, iteration: int, assessed: list[Assessed]) -> Decision:
        archive = {cell: history.candidate(ref) for cell, ref in self.archive(history).items()}
        kept = set()
        for a in _rank(assessed):
            if a.tampered or a.status == "rejected" or a.score is None:
                continue
            cell = self.cell(a.behaviour)
            if cell not in archive or rank_key(a.score) > rank_key(archive[cell]["score"]):
                archive[cell] = {"score": a.score, "policy_version_id": a.version_id}
                kept.add(a.version_id)
        return _decide_by_rank(history, assessed, kept)


def make_strategy(config: Any, eval_max_steps: int | None = None) -> Strategy:
    """The strategy ``config.strategy`` names (``config``: an ``OptimizeConfig``; ``eval_max_steps``: the run's
    evaluation cap); ``candidates`` None takes the strategy's default (best-of-n and map-elites 4, beam 1)."""
    name, candidates = config.strategy, config.candidates
    if name == "greedy":
        if candidates not in (None, 1):
            raise ValueError("--candidates is for best-of-n, beam and map-elites: greedy makes one proposal per "
                             "iteration")
        return Greedy(config.memory, config.rollback, config.rollback_fraction)
    if name == "best-of-n":
        return BestOfN(candidates or 4, config.memory)
    if name == "beam":
        return Beam(config.beam_width, candidates or 1, config.memory)
    if name == "map-elites":
        return MapElites(candidates or 4, config.memory, config.seed, eval_max_steps or config.eval_max_steps or EpisodeLimits.max_steps)
    raise ValueError(f"--strategy must be one of {', '.join(STRATEGIES)}, not {name!r}")
