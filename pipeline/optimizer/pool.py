"""*pool*: the asynchronous proposal pool of the population strategies (``--pool``; best-of-n, beam, map-elites).

The barrier loop (``loop.py``) asks for all of an iteration's proposals, waits for the slowest reply, plays them
all, then commits: the cores idle while the model thinks, and every call waits for the slowest one. The pool keeps
``max_concurrent_calls`` calls in flight instead:

- **Start.** Candidates start in order (iteration i's candidates 0 .. N-1, N the strategy's ``max_proposals``, then
  iteration i+1's), each as soon as a call slot frees, at most :data:`LOOKAHEAD` iterations past the last one
  committed. A candidate's request is the strategy's plan for its iteration made from the freshest state when it
  starts, its *basis*: the iterations committed then (``llm_calls.history_iterations``) and every candidate already
  assessed in the iterations not committed yet (``llm_calls.basis_candidates``, ``History.pending``: a new best among
  them is the parent, and memory and beams see them). A slow call holds its iteration's commit, not the prompts of
  the candidates after it. Candidate c takes the plan's request c (modulo the plan's length: a beam narrower than
  its width plans fewer).
- **Propose.** In its slot's thread the prompt is built from the basis, the model asked, the reply read and
  validated, with repair turns (``propose.py``), exactly as in the barrier loop.
- **Play.** One player thread plays whatever candidates are ready, together (cascade screens first), while the
  calls go on; each candidate is played as soon as the player is free after its reply is in. The evaluation cache
  reuses the assessments of iterations not committed yet too: a version is played once in the run.
- **Commit.** Iterations are committed in order, each once all its candidates are assessed: the strategy decides
  on them against the iterations before (``conclude.py``), exactly as in the barrier loop.

Reproducible: a candidate's prompt depends only on its basis, and the basis is recorded with its first call (and
when it was taken, ``basis_at``, beside each candidate's ``candidates.assessed_at``: no call leaves out a candidate
assessed before it started), so ``--resume`` and ``codearcade replay`` start every recorded candidate from the same
basis (waiting until its iterations are committed and its pending candidates assessed; an ensemble's resumed
candidate keeps its recorded model) and build the same prompt, which the stored reply answers. A candidate that had
no call recorded when a run was killed starts afresh, from the freshest state of the resumed run: which candidates
are assessed when it starts depends on how long calls and games take, so from there a resumed run may differ from
an uninterrupted one, as two uninterrupted runs of the same settings may. Budgets are checked before each call;
once one is reached no candidate starts, the calls in flight finish, the iterations they complete are committed,
and the run stops (status ``budget``) — an iteration left incomplete is not committed, and a resume with a larger
budget completes it from its stored calls.

Greedy keeps its strict order (each prompt needs the outcome of the update before it): it never uses the pool.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import defaultdict
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import Callable

from pipeline.llm.client import LLMClient
from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer.assess import Assessment, Screen, assess, screen
from pipeline.optimizer.budgets import BudgetExhausted, check_wall, pass_budget_turn
from pipeline.optimizer.conclude import IterationResult, assessed_of, conclude, pending_row, provisional, screen_out
from pipeline.optimizer.ensemble import member_picks
from pipeline.optimizer.propose import Proposal, propose
from pipeline.optimizer.state import RunState
from pipeline.optimizer.strategies import History, Ref
from store import Store
from store.db import utcnow
from store.readers import candidates, first_call_models, iterations, pool_bases, version_complexity
from store.writer import insert_policy_version
from tracing.ast_threads import serialize_ast_parse

LOOKAHEAD = 4
"""How many iterations past the last committed one may have candidates started: enough that one slow call (a long
tail of latency) does not idle the other slots while its iteration waits to commit, little enough that prompts are
built from recent iterations and a hung call does not leave a pile of candidates waiting behind it."""


@dataclass
class _Candidate:
    iteration: int
    candidate: int
    basis: int
    """Its prompt is built from iterations 0 .. basis-1 (and the candidates assessed then: ``History.pending``)."""
    started_at: datetime = field(default_factory=utcnow)
    started: float = field(default_factory=time.monotonic)
    llm_s: float = 0.0
    proposal: Proposal | None = None
    assessment: Assessment | None = None
    screen: Screen | None = None
    train_s: float = 0.0
    eval_s: float = 0.0


@dataclass
class PoolProgress:
    """What the pool is doing, for the running line: calls in flight, candidates playing and waiting to play."""

    calls: int = 0
    playing: int = 0
    episodes: int = 0
    waiting: int = 0

    def line(self) -> str:
        return (f"pool: {self.calls} call{'s' * (self.calls != 1)} in flight, {self.playing} candidate"
                f"{'s' * (self.playing != 1)} playing ({self.episodes} episodes), {self.waiting} waiting to play")


def run_pool(store: Store, state: RunState, client: LLMClient, counter: TokenCounter | None,
             log: Callable[[str], None], on_iteration: Callable[[IterationResult], None] | None = None,
             progress: Callable[[int, int], None] | None = None) -> None:
    """Iterations ``state.next_iteration .. config.iterations`` through the pool (module docstring), each given to
    ``on_iteration`` once committed; iteration 0 must be committed. Raises what stopped it
    (:class:`BudgetExhausted`, an ``LLMError``, ...) once the calls and games in flight are done and the iterations
    they completed are committed."""
    serialize_ast_parse()  # its threads parse candidates at once (tracing/ast_threads.py)
    c = state.config
    per_iteration = state.strategy.max_proposals
    episodes_each = 1 + c.eval_episodes + c.robust_episodes  # a training rollout and the evaluation games
    with store.read() as con:
        recorded = state.pool_bases if state.pool_bases is not None else pool_bases(con, state.run_id)
        # an ensemble's model of each candidate started, in start order: a resumed run's committed ones first
        picks = first_call_models(con, state.run_id, state.next_iteration) if c.models else {}
        # and the model each recorded candidate's first call had: a resumed candidate keeps it (its reply is reused)
        asked = first_call_models(con, state.run_id, 2**31 - 1) if c.models and state.pool_bases is None else {}
        if state.history is None or len(state.history.iterations) != state.next_iteration:
            state.history = History(iterations(con, state.run_id, state.next_iteration),
                                    candidates(con, state.run_id, state.next_iteration))
    events: queue.Queue = queue.Queue()
    order = iter([(i, j) for i in range(state.next_iteration, c.iterations + 1) for j in range(per_iteration)])
    next_up = next(order, None)
    calling: dict[tuple[int, int], _Candidate] = {}
    ready: list[_Candidate] = []
    playing: list[_Candidate] = []
    assessed: dict[int, dict[int, _Candidate]] = defaultdict(dict)
    rows: dict[Ref, dict] = {}  # the history rows of the candidates assessed whose iterations are not committed
    assessed_at: dict[Ref, datetime] = {}
    stop: BaseException | None = None
    failed_at: int | None = None  # the first iteration with a call that failed
    player_failed = False
    last_commit = time.monotonic()
    # calls overlap: no "waiting for the model" line per call (each iteration's line says what is in flight)
    waiting, state.waiting = state.waiting, lambda iteration, model: nullcontext()
    with state.budget_lock:  # the candidates' tickets, in start order (budgets.check_budgets)
        state.budget_turn, state.budget_turns_passed = 0, set()
    tickets = 0

    def propose_one(item: _Candidate, history: History, member: LLMClient | None, ticket: int) -> None:
        try:
            plan = state.strategy.plan(history, item.iteration)
            request = replace(plan[item.candidate % len(plan)], candidate=item.candidate)
            (item.proposal,) = propose(store, state, history, item.iteration, [request], client, counter, log,
                                       members={item.candidate: member} if member is not None else None,
                                       budget_ticket=ticket)
            item.llm_s = time.monotonic() - item.started
            events.put(("proposed", item, None))
        except BaseException as exc:  # noqa: BLE001 - raised by the coordinator, after the work in flight
            events.put(("proposed", item, exc))
        finally:
            pass_budget_turn(state, ticket)

    def play(batch: list[_Candidate], known: History, pending: list[Assessment]) -> None:
        """Play ``batch`` (its iterations in order); ``pending``: the assessments of the iterations not committed
        yet, which the evaluation cache reuses as it does committed ones (and this batch's own, as they come)."""
        try:
            by_iteration: dict[int, list[_Candidate]] = defaultdict(list)
            for item in batch:
                by_iteration[item.iteration].append(item)
            for iteration, items in sorted(by_iteration.items()):
                proposals = [item.proposal for item in items]
                screens = {}
                if c.screen_steps:
                    screens = screen(store, state, iteration, known,
                                     [p for p in proposals if p.status == "accepted"], progress, pending=pending)
                    screen_out(proposals, screens)
                found, times = assess(store, state, iteration, {p.candidate: p.version_id for p in proposals},
                                      progress, texts={p.version_id: p.text for p in proposals if p.text is not None},
                                      pending=pending)
                for item in items:
                    item.assessment, item.screen = found[item.candidate], screens.get(item.candidate)
                    item.train_s, item.eval_s = times.train_s, times.eval_s
                pending = pending + [item.assessment for item in items]
            events.put(("played", batch, None))
        except BaseException as exc:  # noqa: BLE001
            events.put(("played", batch, exc))

    def row_of(ref: Ref) -> dict:
        """A candidate of a basis as it was when pending: still pending, or committed since (resume, replay)."""
        return rows[ref] if ref in rows else provisional(state.history.candidate(ref))

    def start_what_can_start() -> None:
        nonlocal next_up, stop, tickets
        while stop is None and next_up is not None and len(calling) < c.max_concurrent_calls:
            iteration, candidate = next_up
            committed = state.next_iteration
            if iteration >= committed + LOOKAHEAD:
                return
            if (iteration, candidate) in recorded:  # it waits for the iterations and candidates its original saw
                basis, fresh = recorded[iteration, candidate]
                fresh = [Ref(*ref) for ref in fresh]
                if basis > committed or any(ref not in rows and ref.iteration >= committed for ref in fresh):
                    return
            else:  # the freshest state: every candidate assessed so far, committed or not
                basis, fresh = committed, sorted(rows)
            try:
                check_wall(store, state, uncommitted_s=time.monotonic() - last_commit)
            except BudgetExhausted as exc:
                stop = exc
                return
            item = _Candidate(iteration, candidate, basis)
            with store.read() as con:
                history = History(iterations(con, state.run_id, basis), candidates(con, state.run_id, basis))
            member = None
            if c.models and (iteration, candidate) in asked:  # --resume: the model its recorded call had
                picks[iteration, candidate] = asked[iteration, candidate]
                member = client.member(asked[iteration, candidate])
            elif c.models:  # chosen here, in start order, counting the candidates in flight that its history lacks
                in_flight = [model for (i, _), model in picks.items() if i >= basis]
                (model,) = member_picks(store, state, history, iteration, [candidate], in_flight)
                picks[iteration, candidate], member = model, client.member(model)
            basis_history = History(history.iterations, history.candidates + [row_of(ref) for ref in fresh],
                                    pending=fresh, as_of=item.started_at)
            calling[iteration, candidate] = item
            threading.Thread(target=propose_one, args=(item, basis_history, member, tickets),
                             name=f"propose-{iteration}.{candidate}", daemon=True).start()
            tickets += 1
            next_up = next(order, None)

    def complexity_of(item: _Candidate) -> int | None:
        p = item.proposal
        if p.version_row is not None:
            return p.version_row["complexity"]
        known = [r["complexity"] for r in [*rows.values(), *state.history.candidates]
                 if r["policy_version_id"] == p.version_id]
        if known:
            return known[0]
        with store.read() as con:
            return version_complexity(con, state.run_id, [p.version_id]).get(p.version_id)

    def now_assessed(batch: list[_Candidate]) -> None:
        """Its new versions stored (later prompts show their code) and its rows kept for the next bases."""
        with store.write() as con:
            for item in batch:
                if item.proposal.version_row is not None:
                    insert_policy_version(con, item.proposal.version_row)
        at = utcnow()
        for item in batch:
            ref = Ref(item.iteration, item.candidate)
            assessed[item.iteration][item.candidate] = item
            assessed_at[ref] = at
            a = assessed_of(item.proposal, item.assessment, complexity_of(item))
            rows[ref] = pending_row(state, item.iteration, item.proposal, item.assessment, a, item.screen, at)

    def commit_what_is_complete() -> None:
        nonlocal last_commit
        while len(assessed.get(state.next_iteration, {})) == per_iteration:
            iteration = state.next_iteration
            done = assessed.pop(iteration)
            items = [done[j] for j in range(per_iteration)]
            timing = dict(started_at=min(item.started_at for item in items),
                          llm_s=max(item.llm_s for item in items), train_s=max(item.train_s for item in items),
                          eval_s=max(item.eval_s for item in items), t0=last_commit,
                          assessed_at={j: assessed_at.pop(Ref(iteration, j)) for j in range(per_iteration)})
            result = conclude(store, state, iteration, state.history, [item.proposal for item in items],
                              {item.candidate: item.assessment for item in items},
                              {item.candidate: item.screen for item in items if item.screen is not None}, timing)
            for j in range(per_iteration):  # committed: from here on state.history has them
                rows.pop(Ref(iteration, j), None)
            last_commit = time.monotonic()
            # what was in flight when it was committed (the event that completed it handled)
            result.pool = PoolProgress(len(calling), len(playing), len(playing) * episodes_each, len(ready)).line()
            if on_iteration is not None:
                on_iteration(result)

    def handle(kind: str, payload, error: BaseException | None) -> None:
        nonlocal stop, failed_at, player_failed
        if kind == "proposed":
            calling.pop((payload.iteration, payload.candidate))
            if error is not None:
                stop = stop or error
                # the iterations before it still finish, as the barrier loop had committed them before this
                # call (a replay that misses at iteration 3 still compares 1 and 2); those from it on cannot
                failed_at = payload.iteration if failed_at is None else min(failed_at, payload.iteration)
            else:
                ready.append(payload)
        else:
            playing.clear()
            if error is not None:
                stop = stop or error
                player_failed = True
            else:
                now_assessed(payload)
        if failed_at is not None:
            ready[:] = [item for item in ready if item.iteration < failed_at]
        if player_failed:
            ready.clear()  # no more play, only what is in flight ends
        else:  # a budget or a failed call lets what is in flight before it finish
            commit_what_is_complete()

    try:
        while True:
            start_what_can_start()
            if ready and not playing:
                playing[:], ready[:] = ready, []
                known = History(state.history.iterations,  # the parents to screen against, pending ones too
                                state.history.candidates + [rows[ref] for ref in sorted(rows)])
                pending = [item.assessment for done in assessed.values() for item in done.values()]
                threading.Thread(target=play, args=(list(playing), known, pending), name="play",
                                 daemon=True).start()
            if not calling and not playing and not ready and (next_up is None or stop is not None):
                break
            handle(*events.get())
            while True:  # everything that happened meanwhile, before the next call's basis is taken
                try:
                    handle(*events.get_nowait())
                except queue.Empty:
                    break
    finally:
        state.waiting = waiting
    if stop is not None:
        raise stop
