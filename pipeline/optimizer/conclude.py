"""The end of an iteration whose candidates are proposed and assessed: the strategy decides on them, the run's best
moves, and the iteration is committed in one transaction — the same for the barrier loop (``loop.py``) and the
proposal pool (``pool.py``)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.feedback import compose_feedback
from pipeline.optimizer.propose import Proposal
from pipeline.optimizer.state import RunState
from pipeline.optimizer.strategies import Assessed, History, decide_starter, with_tampering
from pipeline.play.versions import policy_version_row
from store import Store
from store.db import utcnow
from store.readers import HISTORY_CANDIDATE_COLUMNS, HISTORY_ITERATION_COLUMNS, model_spending, policy_text, \
    version_complexity
from store.writer import insert_candidate, insert_feedback, insert_iteration, insert_policy_version, \
    reject_policy_version
from tracing.policy_file import inspect_policy


@dataclass
class IterationResult:
    run_id: str
    iteration: int
    policy_version_id: str
    update_status: str
    score: float | None
    """The chosen candidate's score; None when it forfeited (``forfeit`` says how)."""
    best_score: float | None
    best_iteration: int
    rolled_back: bool
    detail: str = ""
    prompt_tokens: int | None = None
    candidates: int = 1
    """How many candidates the iteration assessed."""
    standard_score: float | None = None
    """The chosen candidate's score under the standard protocol, when the run measures it."""
    forfeit: str | None = None
    """What ended the evaluation game the chosen candidate forfeited (``store/scores.py``)."""
    forfeit_score: float | None = None
    repairs: int = 0
    """Repair turns the chosen candidate's reply took (``--repairs``)."""
    pool: str = ""
    """The proposal pool (``--pool``): what was in flight when the iteration was committed."""
    models: list[tuple[str, int, float | None]] = field(default_factory=list)
    """An ensemble's calls so far: (model, calls, cost in USD) of each model, most calls first."""



def screen_out(proposals: list[Proposal], screens: dict) -> None:
    """Cascade evaluation: a proposal screened out falls back to its parent's code, its feedback saying why."""
    for p in proposals:
        if p.candidate in screens and not screens[p.candidate].passed:
            s = screens[p.candidate]
            p.status, p.version_id = "rejected", p.parent_version_id
            if s.forfeit:
                p.note = (f"Your last suggestion was screened out: it did not play the first {s.steps} steps of "
                          f"the evaluation game to their end ({s.forfeit}). The code is unchanged.")
            else:
                p.note = (f"Your last suggestion was screened out: in the first {s.steps} steps of the "
                          f"evaluation game it scored {s.score:g}, where the code it was meant to improve scores "
                          f"{s.bar:g}. The code is unchanged.")


def conclude(store: Store, state: RunState, iteration: int, history: History, proposals: list[Proposal],
             assessments: dict, screens: dict, timing: dict[str, Any]) -> IterationResult:
    """The end of an iteration whose candidates are proposed and assessed: the strategy decides on them against
    ``history`` (the iterations before), the run's best moves, and the iteration is committed (:func:`_commit`)."""
    complexity = {p.version_id: p.version_row["complexity"] for p in proposals if p.version_row is not None}
    complexity.update({c["policy_version_id"]: c["complexity"] for c in history.candidates})
    unknown = [p.version_id for p in proposals if p.version_id not in complexity]
    if unknown:  # the starting policy
        with store.read() as con:
            complexity.update(version_complexity(con, state.run_id, unknown))
    assessed = [assessed_of(p, assessments[p.candidate], complexity.get(p.version_id)) for p in proposals]
    decision = decide_starter(assessed) if iteration == 0 else state.strategy.decide(history, iteration, assessed)
    if decision.new_best is not None:
        best = assessed[decision.new_best]
        state.best_score, state.best_iteration, state.best_version_id = best.score, iteration, best.version_id
    _commit(store, state, iteration, history, proposals, assessments, assessed, decision, screens, timing)
    state.next_iteration = iteration + 1
    models = []
    if state.config.models:  # the progress line shows each model's share and spend
        with store.read() as con:
            models = model_spending(con, state.run_id)
    chosen, notes = assessed[decision.chosen], decision.notes[decision.chosen]
    return IterationResult(state.run_id, iteration, chosen.version_id, chosen.status, chosen.score, state.best_score,
                           state.best_iteration, decision.rolled_back, notes[0] if notes else "",
                           proposals[decision.chosen].prompt_tokens, candidates=len(proposals),
                           standard_score=assessments[decision.chosen].standard_score,
                           forfeit=assessments[decision.chosen].forfeit,
                           forfeit_score=assessments[decision.chosen].forfeit_score, models=models,
                           repairs=proposals[decision.chosen].repairs)


def assessed_of(p: Proposal, a, complexity: int | None) -> Assessed:
    """What a strategy decides on for proposal ``p`` played as ``a`` (an ``Assessment``); ``complexity``: its version's."""
    tampered = a.tampered if p.status == "accepted" else None  # pipeline/play/verify.py: caught, never the best
    notes = [p.note] if p.note else []
    return Assessed(p.candidate, p.parent, p.version_id, "rejected" if tampered else p.status, a.score, tampered,
                    notes, {"complexity": complexity, "eval_length": a.eval_length}, forfeit=a.forfeit)


def pending_row(state: RunState, iteration: int, p: Proposal, played, a: Assessed, screen, assessed_at) -> dict:
    """The history row of a candidate assessed whose iteration is not committed yet (``History.pending``: what the
    proposal pool plans from): its ``candidates`` row as the commit will write it, but for the decision (``rejected``
    when it will be, else ``pending``); its feedback is the committed one, since the population strategies' notes on
    a candidate do not depend on the decision (``with_tampering``)."""
    row = candidate_row(state, iteration, p, played, a, screen, "rejected" if a.status == "rejected" else "pending",
                        with_tampering(a), assessed_at)
    return {k: {**row, **a.behaviour}[k] for k in HISTORY_CANDIDATE_COLUMNS}


def provisional(row: dict) -> dict:
    """A committed candidate's history row as :func:`pending_row` made it before its commit (a basis recorded while
    it was pending, rebuilt after: ``--resume``, ``replay``)."""
    return {**row, "decision": "rejected" if row["decision"] == "rejected" else "pending"}


def candidate_row(state: RunState, iteration: int, p: Proposal, played, a: Assessed, screen, decision: str,
                  notes: list[str], assessed_at=None) -> dict:
    """The ``candidates`` row of proposal ``p``, played as ``played`` (an ``Assessment``), with its feedback text."""
    c = state.config
    notes = notes + ([_protocols_note(c, played)] if played.robust_episode_ids else [])
    text = compose_feedback(c.feedback, state.settings["bands"], a.score, played.train_return, played.train_length,
                            notes, played.forfeit, played.forfeit_score)[2]
    return dict(
        run_id=state.run_id, iteration=iteration, candidate=p.candidate, strategy=c.strategy,
        parent_iteration=p.parent.iteration if p.parent else None,
        parent_candidate=p.parent.candidate if p.parent else None, parent_version_id=p.parent_version_id,
        proposed_version_id=p.proposed_version_id, policy_version_id=a.version_id, llm_call_id=p.call_id,
        repairs=p.repairs, update_status=a.status,
        evaluation="screened" if screen is not None and not screen.passed else played.evaluation,
        train_episode_id=played.train_episode_id, eval_episode_ids=played.eval_episode_ids,
        robust_episode_ids=played.robust_episode_ids or None, train_return=played.train_return, score=a.score,
        deterministic_score=played.deterministic_score, standard_score=played.standard_score,
        forfeit=played.forfeit, forfeit_score=played.forfeit_score, score_low=played.score_low,
        score_high=played.score_high, screen_episode_id=screen.episode_id if screen is not None else None,
        screen_score=screen.score if screen is not None else None,
        screen_bar=screen.bar if screen is not None else None, decision=decision, feedback=text,
        assessed_at=assessed_at)


def _protocols_note(config: OptimizeConfig, a) -> str:
    """Both scores, for the feedback: the model sees how the code fares under sticky actions too."""
    optimized = "the score being optimized" if config.optimize_protocol == "standard" else "not the score optimized"

    def told(score: float | None) -> str:
        return f"{score:g}" if score is not None else "nothing (a game forfeited)"

    return (f"Under the paper's deterministic protocol it scored {told(a.deterministic_score)} (mean of "
            f"{len(a.eval_episode_ids)}); under the standard protocol (sticky actions 0.25, up to 30 no-op starts: "
            f"the game does not always do what the policy asks) {told(a.standard_score)} (mean of "
            f"{len(a.robust_episode_ids)}; {optimized}).")


def _commit(store: Store, state: RunState, iteration: int, history: History, proposals: list[Proposal],
            assessments, assessed, decision, screens, timing: dict[str, Any]) -> None:
    """Write the iteration in one transaction: the proposed versions, the rollback version (greedy), the versions
    caught tampering, every candidate with its feedback, the chosen candidate's feedback and the ``iterations``
    row; then ``state.history`` is ``history`` with the rows written (as ``store.readers`` reads them back)."""
    c = state.config
    chosen = proposals[decision.chosen]
    played = assessments[chosen.candidate]
    notes = decision.notes[chosen.candidate] + ([_protocols_note(c, played)] if played.robust_episode_ids else [])
    stage, stage_score, text = compose_feedback(c.feedback, state.settings["bands"], assessed[decision.chosen].score,
                                                played.train_return, played.train_length, notes, played.forfeit,
                                                played.forfeit_score)
    assessed_at = timing.get("assessed_at")  # the proposal pool's: when it learnt each candidate's assessment
    chosen_play = played
    with store.write() as con:
        for p in proposals:
            if p.version_row is not None:
                insert_policy_version(con, p.version_row)
        if decision.rolled_back:
            best_text = policy_text(con, state.run_id, state.best_version_id)
            insert_policy_version(con, policy_version_row(inspect_policy(best_text, "policy.py"), state.run_id,
                                                          iteration, "rollback", "accepted",
                                                          parent_id=assessed[decision.chosen].version_id))
        written = []
        for p, a in zip(proposals, assessed):
            if a.tampered:
                reject_policy_version(con, state.run_id, iteration, a.version_id, a.tampered)
            written.append(candidate_row(state, iteration, p, assessments[p.candidate], a, screens.get(p.candidate),
                                         decision.decisions[p.candidate], decision.notes[p.candidate],
                                         (assessed_at or {}).get(p.candidate)))
            insert_candidate(con, written[-1])
        insert_feedback(con, dict(run_id=state.run_id, iteration=iteration, mode=c.feedback, stage=stage,
                                  score=stage_score, text=text))
        insert_iteration(con, iteration_row := dict(
            run_id=state.run_id, iteration=iteration, candidate=chosen.candidate,
            policy_version_id=assessed[decision.chosen].version_id, base_version_id=chosen.parent_version_id,
            update_status=assessed[decision.chosen].status, rolled_back=decision.rolled_back,
            llm_call_id=chosen.call_id, train_episode_id=chosen_play.train_episode_id,
            eval_episode_ids=chosen_play.eval_episode_ids, train_return=chosen_play.train_return,
            score=assessed[decision.chosen].score, best_score=state.best_score,
            best_version_id=state.best_version_id, best_iteration=state.best_iteration,
            started_at=timing["started_at"], finished_at=utcnow(), llm_s=timing["llm_s"],
            train_s=timing["train_s"], eval_s=timing["eval_s"], wall_s=time.monotonic() - timing["t0"]))
    known = [{**row, **a.behaviour} for row, a in zip(written, assessed)]  # + complexity, eval_length
    state.history = History(history.iterations + [{k: iteration_row[k] for k in HISTORY_ITERATION_COLUMNS}],
                            history.candidates + [{k: row[k] for k in HISTORY_CANDIDATE_COLUMNS} for row in known])
