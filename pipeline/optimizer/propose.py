"""*propose*: from a strategy's requests to candidates — store slices → prompt → LLM → parsed, validated version.

For each :class:`~pipeline.optimizer.strategies.ProposalRequest` of an iteration:

1. the prompt is built from the store (``pipeline/optimizer/prompt.py``) for the parent candidate, under the token budget;
2. a reply already stored for this prompt, iteration and candidate is reused (a resumed run); the others are
   requested from the model **concurrently** (at most ``max_concurrent_calls`` at a time), after checking that
   all of them together stay within the run's cost and token budgets;
3. each reply is parsed (``pipeline/optimizer/reply.py``) and the calls are written to ``llm_calls`` with what their
   replies parsed into (one transaction, in candidate order, so the store does not depend on which reply came
   first); then each suggestion is validated (``pipeline/play/validate.py``): an
   accepted one becomes a ``policy_versions`` row; a rejected one is stored with its reason, which goes into the
   feedback, and the candidate falls back to its parent's code;
4. **repair turns** (``repairs``, default 1): a reply rejected before it is played (it does not parse, has the
   wrong methods or signatures, raises or returns an invalid action on the recorded observations) goes back to
   the model in the same conversation — its own reply, then the exact error — and the corrected reply is parsed
   and validated exactly as a first one is, up to ``repairs`` times. Each repair is its own call in ``llm_calls``
   (purpose ``repair``, ``repair_of`` the call it repairs), counted by every budget; a resumed iteration and a
   replay find it by its conversation's hash like any prompt. A repair conversation is the prompt plus the
   rejected reply and the error (at most :data:`REPAIR_NOTE_CHARS`): it may go past the prompt's token budget by
   a reply of ``max_tokens`` and the error (:func:`repair_limit`); a longer one (a reply far over ``max_tokens``)
   is not sent. A repair that the budgets forbid, or whose call fails, is not made either: the candidate stays
   rejected, and the run goes on.

LLM errors: fatal ones (authentication, unknown model, ...) stop the run after every call of the iteration is
recorded; an iteration whose every call failed counts towards :data:`MAX_CONSECUTIVE_LLM_FAILURES`.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from typing import Callable

from games import get_game
from pipeline.boundary.untrusted import clean_untrusted_text
from pipeline.llm.client import OUT_OF_TIME, BeforeRetry, LLMClient, LLMError, LLMReply, canonical_messages
from pipeline.llm.providers import price
from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer.context import context_for
from pipeline.optimizer.ensemble import choose_members
from pipeline.optimizer.prompt import Prompt, PromptBudgetError, build_prompt
from pipeline.optimizer.reply import ReplyParseError, clean_text, read_reply
from pipeline.optimizer.state import RunState
from pipeline.optimizer.strategies import History, ProposalRequest, Ref
from pipeline.play.runinfo import new_run_id
from pipeline.play.validate import CandidateRejected, RuntimeCheck, check_fits, spread, validate_candidates
from pipeline.play.versions import policy_version_row
from store import Store
from store.db import Hold
from store.readers import run_spending, stored_replies
from store.writer import insert_llm_calls

MAX_CONSECUTIVE_LLM_FAILURES = 3

REPAIR_NOTE_CHARS = 2_000
"""The longest error sent back in a repair turn (it quotes the candidate's own exception, which the code chose)."""
REPAIR_NOTE_TOKENS = 1_000
"""Room for that error and the request around it in a repair conversation's token limit (:func:`repair_limit`)."""


def repair_limit(config) -> int:
    """The most tokens a repair conversation may have: the prompt's budget, a reply of ``max_tokens`` and the error.
    A reply longer than ``max_tokens`` allows (a server that ignored the limit) is never sent back."""
    return config.token_budget + config.max_tokens + REPAIR_NOTE_TOKENS


class BudgetExhausted(Exception):
    """The next step would exceed one of the run's budgets; the run stops with status ``budget``. ``setting``: the
    budget's (``max_llm_calls``, ...), for the command that goes on with a larger one; None where a larger one
    would not help."""

    def __init__(self, message: str, setting: str | None = None) -> None:
        super().__init__(message)
        self.setting = setting


@dataclass
class Proposal:
    """What one request became: the version to assess for it, and how it got there."""

    candidate: int
    parent: Ref
    parent_version_id: str
    status: str
    """``accepted``, ``unchanged``, ``rejected`` or ``llm_error``."""
    version_id: str
    """The version to assess: the new one if accepted, else the parent's."""
    proposed_version_id: str | None
    """The version the reply proposed, accepted or not (None: no runnable code)."""
    call_id: str | None
    note: str
    prompt_tokens: int
    version_row: dict | None = None
    """The ``policy_versions`` row of the proposed code (accepted or rejected at run time), written with the
    iteration's other rows (``pipeline/optimizer/loop.py``)."""
    text: str | None = None
    """The proposed policy file, when accepted (what its episodes play)."""
    repairs: int = 0
    """Repair turns the reply took (0: the first reply stands)."""
    fixable: str | None = None
    """Why the reply was rejected before it was played, when a repair turn could fix it (what is sent back)."""


@dataclass
class _Pending:
    request: ProposalRequest
    prompt: Prompt
    context_version: str
    observations: list
    info: object
    call_id: str | None = None
    text: str | None = None
    reply: LLMReply | None = None
    error: LLMError | None = None
    suggestion: dict[str, str] | None = None
    parse_error: str | None = None
    reading: str | None = None
    """How the reply was read: structured, parsed, repaired or unusable (``pipeline/optimizer/reply.py``)."""
    repairs: tuple[str, ...] = ()
    turn: int = 0
    """0: the first call for the request; n: its nth repair turn."""
    repair_of: str | None = None
    """The call whose rejected reply this one repairs."""
    basis: int = 0
    """How many iterations its prompt was built from (0 .. basis-1; the proposal pool may start a call before the
    iteration before it is committed: ``pipeline/optimizer/pool.py``)."""
    fresh: tuple = ()
    """The proposal pool's: the candidates assessed and not yet committed that its prompt was built from too
    (``History.pending``: refs), and when that basis was taken (``basis_at``)."""
    basis_at: datetime | None = None
    client: LLMClient | None = None
    """The model that answers it, when the run has several (``pipeline/optimizer/ensemble.py``); else the run's."""
    choice: dict | None = None
    """Why the ensemble chose that model (``llm_calls.model_choice``; a repair turn's is its first call's)."""
    over_budget: BudgetExhausted | None = None
    """Why its call was not retried after a billed attempt: another would not fit a budget (:func:`_retry_budget`)."""

    def parse(self) -> None:
        reply = self.reply
        try:
            read = read_reply(self.text, structured=reply is not None and reply.structured,
                              cut_off=reply is not None and reply.cut_off)
        except ReplyParseError as exc:
            self.suggestion, self.parse_error, self.reading, self.repairs = None, str(exc), "unusable", ()
            return
        self.suggestion, self.parse_error, self.reading, self.repairs = read.suggestion, None, read.how, read.repairs


def propose(store: Store, state: "RunState", history: History, iteration: int, requests: list[ProposalRequest],
            client: LLMClient, counter: TokenCounter, log: Callable[[str], None],
            hold: Hold | None = None, members: dict[int, LLMClient] | None = None,
            budget_ticket: int | None = None) -> list[Proposal]:
    """The candidates of iteration ``iteration`` for ``requests`` (see the module docstring). ``hold`` (the
    caller's hold on the store) is let go while the model is asked and taken again once it has answered (what
    follows is short: store the calls, validate, and the caller's commit). ``budget_ticket``: the proposal pool's
    start order of this candidate, in which the first calls are checked against the budgets
    (:func:`check_budgets`; the caller passes the ticket with :func:`pass_budget_turn` however this ends)."""
    c = state.config
    pending = []
    built: dict[tuple, tuple] = {}  # best-of-n asks N times with the same context: build its prompt once
    with store.read() as con:
        stored = stored_replies(con, state.run_id, iteration)  # a resumed iteration's, for the same prompts
        for request in requests:
            key = (request.parent, tuple(request.memory), request.note)
            if key not in built:
                ctx = context_for(con, state.run_id, history, request.parent, request.memory, request.note,
                                  c.call_time_limit_s, c.collapse_repeats)
                try:
                    built[key] = (ctx, build_prompt(ctx, c.token_budget, counter))
                except PromptBudgetError as exc:
                    raise ValueError(str(exc)) from None
            ctx, prompt = built[key]
            item = _Pending(request, prompt, ctx.info.version_id, [(r["step"], r["obs"]) for r in ctx.train_steps],
                            ctx.info, basis=len(history.iterations), fresh=tuple(history.pending),
                            basis_at=history.as_of)
            if (prompt.hash, request.candidate) in stored:
                item.call_id, item.text = stored[prompt.hash, request.candidate]
                item.parse()
            pending.append(item)
    if members is None:
        choose_members(store, state, history, iteration, client, pending)
    else:  # chosen by the proposal pool as it started them (pipeline/optimizer/pool.py)
        for item in pending:
            item.client = members.get(item.request.candidate)
    for item in pending:  # the reasons the ensemble's rule gave, recorded with each first call
        item.choice = state.model_choices.pop((iteration, item.request.candidate), None)
    reused = [p for p in pending if p.text is not None]
    if reused:
        log(f"iteration {iteration}: reusing {_replies(len(reused))} stored for {'this prompt' if len(pending) == 1 else 'these prompts'}")
    to_call = [p for p in pending if p.text is None]
    if to_call:
        reservation = check_budgets(store, state, client, [p.prompt for p in to_call],
                                    [p.client or client for p in to_call], ticket=budget_ticket)
        name_methods = getattr(client, "hold_reply_to_methods", None)  # the offline model's grammar
        if name_methods is not None:
            name_methods([method.name for method in to_call[0].info.trainable])
        _ask(store, state, iteration, client, to_call, reservation, hold)
        _out_of_time(state, to_call)
        spent = next((p.over_budget for p in to_call if p.over_budget is not None), None)
        if spent is not None:  # recorded, with what its attempts were billed: the run ends as its budget's end
            raise spent
        failed = [p for p in to_call if p.error is not None]
        fatal = next((p.error for p in failed if p.error.fatal), None)
        if len(failed) == len(pending):
            state.llm_failures += 1
        else:
            state.llm_failures = 0
        if fatal is not None:
            raise fatal
        if failed and state.llm_failures >= MAX_CONSECUTIVE_LLM_FAILURES:
            raise failed[-1].error
    else:
        state.llm_failures = 0
    proposals = _validate_all(state, iteration, pending, counter)
    for turn in range(1, c.repairs + 1):
        if not any(p.fixable for p in proposals):
            break
        proposals = _repair_turn(store, state, iteration, turn, pending, proposals, stored, client, counter, log,
                                 hold)
    return proposals


def _out_of_time(state: "RunState", asked: list[_Pending]) -> None:
    """End the run as a spent time budget when a call of ``asked`` was given up on at the run's deadline (its
    row is recorded, with the error; a ``--resume`` with more time asks again)."""
    cut = next((p.error for p in asked if p.error is not None and p.error.error_type == OUT_OF_TIME), None)
    if cut is not None:
        raise BudgetExhausted(f"time budget: --max-wall {state.config.max_wall_minutes:g} min ran out while the "
                              f"model was asked ({cut.message})", "max_wall_minutes")


def repair_messages(item: _Pending, error: str) -> list[dict[str, str]]:
    """The conversation of a repair turn: the rejected reply's, then the reply, then the error and what to do."""
    error = clean_untrusted_text(error)
    if len(error) > REPAIR_NOTE_CHARS:
        error = error[: REPAIR_NOTE_CHARS - 1] + "…"
    return item.prompt.messages + [
        {"role": "assistant", "content": item.text},
        {"role": "user", "content": f"{error}\n\nFix this and reply again in the same JSON format, with the "
                                    "complete corrected definition of every method you change."}]


def _repair_turn(store: Store, state: "RunState", iteration: int, turn: int, pending: list[_Pending],
                 proposals: list[Proposal], stored: dict, client: LLMClient, counter: TokenCounter,
                 log: Callable[[str], None], hold: Hold | None) -> list[Proposal]:
    """One repair turn for every proposal rejected before it was played (``pending[i]`` made ``proposals[i]``):
    ``pending`` is updated in place with the repair's call where one was made, and the proposals are returned
    with each repaired one's outcome in its place."""
    repairs: dict[int, _Pending] = {}
    for i, p in enumerate(proposals):
        if p.fixable is None:
            continue
        item = pending[i]
        limit = repair_limit(state.config)
        # counted only when it may fit: a reply of megabytes is not tokenized to learn that it does not
        fits = len(item.text) + REPAIR_NOTE_CHARS <= 16 * (limit - item.prompt.tokens)
        messages = repair_messages(item, p.fixable) if fits else []
        tokens = counter.messages(messages) if fits else 0
        if not fits or tokens > limit:
            log(f"iteration {iteration}: no repair turn for candidate {item.request.candidate}: its reply is too "
                f"long to send back (the conversation would pass {limit:,} tokens: the prompt's budget, a reply of "
                f"--max-tokens and the error)")
            p.fixable = None
            continue
        prompt = Prompt(messages, tokens, item.prompt.budget, item.prompt.steps_shown, item.prompt.memory_shown,
                        item.prompt.token_method)
        repair = _Pending(item.request, prompt, item.context_version, item.observations, item.info, turn=turn,
                          repair_of=item.call_id, client=item.client, basis=item.basis,
                          fresh=item.fresh, basis_at=item.basis_at)  # the same model fixes it
        if (prompt.hash, item.request.candidate) in stored:  # a resumed iteration: this repair was made before
            repair.call_id, repair.text = stored[prompt.hash, item.request.candidate]
            repair.parse()
        repairs[i] = repair
    to_call = [r for r in repairs.values() if r.text is None]
    if to_call and state.wall_deadline is not None and time.monotonic() >= state.wall_deadline:
        log(f"iteration {iteration}: no repair turn (time budget: --max-wall {state.config.max_wall_minutes:g} min "
            "has run out)")
        return proposals
    if to_call:
        try:
            reservation = check_budgets(store, state, client, [r.prompt for r in to_call],
                                        [r.client or client for r in to_call])
        except BudgetExhausted as exc:
            log(f"iteration {iteration}: no repair turn ({exc})")
            return proposals
        who = ", ".join(str(r.request.candidate) for r in to_call)
        log(f"iteration {iteration}: repair turn {turn} of {state.config.repairs} for the rejected "
            f"{'reply' if len(to_call) == 1 else 'replies'} of candidate{'' if len(to_call) == 1 else 's'} {who}")
        _ask(store, state, iteration, client, to_call, reservation, hold)
        _out_of_time(state, to_call)
    made = {i: r for i, r in repairs.items() if r.error is None}  # a failed repair leaves the rejection standing
    for i, r in repairs.items():
        if r.error is not None:
            log(f"iteration {iteration}: the repair call for candidate {r.request.candidate} failed ({r.error}); "
                "its rejection stands")
            proposals[i].fixable = None
    repaired = _validate_all(state, iteration, list(made.values()), counter)
    result = list(proposals)
    for (i, item), outcome in zip(made.items(), repaired):
        outcome.repairs, outcome.prompt_tokens = turn, proposals[i].prompt_tokens
        pending[i] = item
        result[i] = outcome
    return result


def _ask(store: Store, state: "RunState", iteration: int, client: LLMClient, items: list[_Pending],
         reservation: tuple[int, int, float] | None, hold: Hold | None) -> None:
    """Ask for the replies of ``items`` (their worst case reserved by :func:`check_budgets`), read them and record
    the calls; the reservation is given back once they are recorded (or the asking failed). Other processes may
    read the store while the model thinks: ``hold`` is let go (checkpointing what this process wrote) once the
    requests are on their way, and taken again for the recording."""
    retries = [0, 0, 0.0]  # what the retries of billed attempts reserved on top of ``reservation``
    try:
        _complete_all(state, iteration, client, items, meanwhile=hold.release if hold is not None else None,
                      before_retry=None if reservation is None else
                      lambda item: _retry_budget(store, state, item, item.client or client, retries))
        for item in items:  # before the store is taken back: other processes may read it while a reply is read
            if item.reply is not None:
                item.text = item.reply.text
                item.parse()
        if hold is not None:
            hold.take()
        record_calls(store, state.run_id, iteration, client, items)
    finally:
        release_budget(state, reservation)
        release_budget(state, tuple(retries))


def _retry_budget(store: Store, state: "RunState", item: _Pending, model: LLMClient, retries: list) -> BeforeRetry:
    """The client's question before it retries an attempt of ``item``'s call that was answered, and so billed
    (``LiteLLMClient.complete``): the reservation of :func:`check_budgets` set aside one worst case for the call,
    which that attempt has used part of, and the provider bills every attempt. The retry goes only if the budgets
    still have room for what the attempt was charged (:func:`billed_usage`) on top of everything spent and
    reserved; that much is then reserved too (in ``retries``, given back with the reservation), so the call's
    attempts together never take the run past a budget. Otherwise the call ends there (``BudgetSpent``) and
    ``item.over_budget`` says why; nothing waits for the calls in flight (two calls waiting on each other)."""
    c = state.config

    def before_retry(attempt: LLMReply) -> str | None:
        charge = billed_usage(model.model, attempt, item.prompt.tokens, c.max_tokens)
        tokens = (charge["input_tokens"] or 0) + (charge["output_tokens"] or 0)
        rates = price(model.model) if c.max_cost_usd is not None else None
        cost = charge["cost_usd"] if charge["cost_usd"] is not None else (
            rates.cost(item.prompt.tokens, c.max_tokens) if rates is not None else 0.0)
        worst = item.prompt.tokens + c.max_tokens
        with state.budget_lock:
            with store.read() as con:
                spent = run_spending(con, state.run_id)
            _, flying_tokens, flying_cost = state.in_flight
            why = None
            if c.max_total_tokens is not None and spent["tokens"] + flying_tokens + tokens > c.max_total_tokens:
                why = BudgetExhausted(
                    f"token budget: {spent['tokens']:,} tokens used, {flying_tokens:,} set aside for the calls in "
                    f"flight, and an attempt of this call was billed {tokens:,}: a retry, which may use up to "
                    f"{worst:,} more, would go over --max-total-tokens {c.max_total_tokens:,}", "max_total_tokens")
            elif c.max_cost_usd is not None and spent["cost_usd"] + flying_cost + cost > c.max_cost_usd:
                why = BudgetExhausted(
                    f"cost budget: ${spent['cost_usd']:.4f} spent, ${flying_cost:.4f} set aside for the calls in "
                    f"flight, and an attempt of this call was billed ${cost:.4f}: a retry would go over --max-cost "
                    f"${c.max_cost_usd:g}", "max_cost_usd")
            if why is not None:
                item.over_budget = why
                return str(why)
            state.in_flight = [state.in_flight[0], flying_tokens + tokens, flying_cost + cost]
            retries[1] += tokens
            retries[2] += cost
        return None

    return before_retry


def _replies(n: int) -> str:
    return "the reply" if n == 1 else f"{n} replies"


def _complete_all(state: "RunState", iteration: int, client: LLMClient, items: list[_Pending],
                  meanwhile: Callable[[], None] | None = None,
                  before_retry: Callable[[_Pending], BeforeRetry] | None = None) -> None:
    """Request every reply, at most ``max_concurrent_calls`` at a time; each item gets its reply or error.
    ``meanwhile`` runs in a thread of its own while the model is asked (its error is raised after the replies);
    ``before_retry(item)``: what its call asks before it retries a billed attempt (:func:`_retry_budget`)."""

    def complete(item: _Pending, on_text) -> None:
        try:
            item.reply = (item.client or client).complete(item.prompt.messages, on_text=on_text,
                                                          candidate=item.request.candidate, iteration=iteration,
                                                          deadline=state.wall_deadline,
                                                          before_retry=before_retry(item) if before_retry else None)
        except LLMError as exc:
            item.error = exc

    failed: list[BaseException] = []

    def run_meanwhile() -> None:
        try:
            meanwhile()
        except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread below
            failed.append(exc)

    helper = threading.Thread(target=run_meanwhile, name="meanwhile") if meanwhile is not None else None
    if helper is not None:
        helper.start()
    try:
        with state.waiting(iteration, client.label) as on_text:
            if len(items) == 1:  # in this thread: Ctrl-C stops it at once
                complete(items[0], on_text)
                return
            _in_daemon_threads(lambda item: complete(item, None), items, state.config.max_concurrent_calls)
    finally:
        if helper is not None:
            helper.join()
            if failed:
                raise failed[0]


def _in_daemon_threads(work: Callable[[_Pending], None], items: list[_Pending], at_once: int) -> None:
    """``work(item)`` for every item, at most ``at_once`` at a time, each in a daemon thread this thread waits for
    (the first error any raised is raised here). A Ctrl-C ends the wait at once and leaves the calls in flight to
    end with the process: a thread pool's exit joins its threads, so a Ctrl-C during best-of-n's calls waited for
    each call in flight and its retries (61.6 s for a 60 s reply) before the command could stop."""
    slots = threading.Semaphore(max(1, at_once))
    failed: list[BaseException] = []

    def run(item: _Pending) -> None:
        try:
            work(item)
        except BaseException as exc:  # noqa: BLE001 - raised in the waiting thread below
            failed.append(exc)
        finally:
            slots.release()

    threads = []
    for item in items:
        slots.acquire()  # a lock's wait: a Ctrl-C interrupts it
        threads.append(threading.Thread(target=run, args=(item,), name="llm", daemon=True))
        threads[-1].start()
    for thread in threads:
        thread.join()
    if failed:
        raise failed[0]


def _validate_all(state: "RunState", iteration: int, items: list[_Pending], counter: TokenCounter) -> list[Proposal]:
    """Parse and check every reply (the worker round trips of several at once); a :class:`Proposal` each, with
    the row of its candidate's policy version (accepted or rejected) to write with the iteration."""
    c = state.config
    workers = max(1, c.workers)  # candidates are always checked in confined workers, even with --workers 0

    def outcome(item: _Pending, status: str, note: str, version: str | None = None, proposed: str | None = None,
                row: dict | None = None, text: str | None = None, fixable: str | None = None) -> Proposal:
        base = item.context_version
        return Proposal(item.request.candidate, item.request.parent, base, status, version or base, proposed,
                        item.call_id, note, item.prompt.tokens, row, text, repairs=item.turn, fixable=fixable)

    n_actions = get_game(state.game).n_actions

    def proposed(item: _Pending):
        observations = spread(item.observations)
        return (item.info, item.suggestion,
                lambda text: RuntimeCheck(text, state.game, observations, n_actions=n_actions,
                                           call_time_limit_s=c.call_time_limit_s),
                lambda candidate: check_fits(candidate, c.token_budget, counter))

    checked = [item for item in items if item.error is None and item.parse_error is None]
    results = dict(zip(map(id, checked), validate_candidates([proposed(item) for item in checked], workers)))
    proposals = []
    for item in items:
        if item.error is not None:
            proposals.append(outcome(item, "llm_error", f"The LLM call failed ({item.error}); the code is unchanged."))
            continue
        if item.parse_error is not None:
            proposals.append(outcome(item, "rejected", f"Your last reply was not usable: {item.parse_error}. Reply "
                                                       "with the JSON format asked for.",
                                     fixable=f"Your reply was not usable: {item.parse_error}."))
            continue
        result = results[id(item)]
        if isinstance(result, CandidateRejected):  # nothing runnable to store: the reason is the record
            proposals.append(outcome(item, "rejected", f"Your last suggestion was rejected: {result}",
                                     fixable=f"Your suggestion was rejected: {result}"))
            continue
        candidate, reason = result
        if candidate is None:
            proposals.append(outcome(item, "unchanged", "Your last suggestion did not change the code."))
            continue
        row = policy_version_row(candidate.info, state.run_id, iteration, "llm",
                                 "accepted" if reason is None else "rejected", reason, parent_id=item.context_version,
                                 llm_call_id=item.call_id)
        if reason is not None:
            proposals.append(outcome(item, "rejected", f"Your last suggestion was rejected: {reason}",
                                     proposed=candidate.version_id, row=row,
                                     fixable=f"Your suggestion was rejected: {reason}"))
        else:
            proposals.append(outcome(item, "accepted", "", version=candidate.version_id,
                                     proposed=candidate.version_id, row=row, text=candidate.text))
    return proposals


def billed_usage(model: str, answer: LLMReply, prompt_tokens: int, max_tokens: int | None) -> dict:
    """What a call's answered attempts are charged (``llm_calls``' usage columns): each attempt at the usage it
    reported, one that reported none (a stream that broke midway) or only part at its worst case
    (:func:`_worst_case_usage`, ``usage_estimated``), summed; the provider bills every attempt it answered, not
    only the last. A cost is None when an attempt has none (a model without a price)."""
    attempts = answer.billed or [answer]
    if answer.replayed or all(a.input_tokens is not None and a.output_tokens is not None for a in attempts):
        return {"input_tokens": answer.input_tokens, "output_tokens": answer.output_tokens,
                "cost_usd": answer.cost_usd, "usage_estimated": None if answer.replayed else False}
    each = [_worst_case_usage(model, a, prompt_tokens, max_tokens)
            if a.input_tokens is None or a.output_tokens is None else
            {"input_tokens": a.input_tokens, "output_tokens": a.output_tokens, "cost_usd": a.cost_usd}
            for a in attempts]
    total = {name: None if any(e[name] is None for e in each) else sum(e[name] for e in each)
             for name in ("input_tokens", "output_tokens", "cost_usd")}
    return {**total, "usage_estimated": True}


def _worst_case_usage(model: str, reply: LLMReply, prompt_tokens: int, max_tokens: int | None) -> dict:
    """What a reply whose endpoint reported no usable token count is charged (``usage_estimated``): the budgets
    read the store, and such a call counted as nothing let a run pass ``--max-total-tokens`` and ``--max-cost``
    call after call. The worst case, as the budgets reserve it before a call: our own count of the prompt, a reply
    of the request's ``max_tokens`` (hidden reasoning included), at litellm's price (none without one); a count the
    endpoint did report stays as it is."""
    inputs = reply.input_tokens if reply.input_tokens is not None else prompt_tokens
    outputs = reply.output_tokens if reply.output_tokens is not None else max_tokens
    rates = price(model) if outputs is not None else None
    return {"input_tokens": inputs, "output_tokens": outputs, "usage_estimated": True,
            "cost_usd": rates.cost(inputs, outputs) if rates is not None else None}


def record_calls(store: Store, run_id: str, iteration: int, client: LLMClient, items: list[_Pending]) -> None:
    """Write the ``llm_calls`` rows of an iteration's calls (failed ones too) with what each reply parsed into,
    in one transaction and in candidate order (the store does not depend on which reply came first); each item
    gets its call id."""
    calls = []
    canonical: dict[int, str] = {}  # best-of-n: N calls share one prompt
    for item in items:
        if item.error is not None and item.error.error_type == OUT_OF_TIME and not item.error.attempts:
            continue  # never made: the run's time had run out before it (not a call, nor counted as one)
        item.call_id = new_run_id()
        reply, error = item.reply, item.error
        model = item.client or client
        params = model.request_params()
        row = {
            "call_id": item.call_id, "run_id": run_id, "iteration": iteration,
            "candidate": item.request.candidate, "purpose": "repair" if item.turn else "update",
            "repair_of": item.repair_of, "repair_turn": item.turn, "history_iterations": item.basis,
            "basis_candidates": [{"iteration": r.iteration, "candidate": r.candidate} for r in item.fresh]
            if item.basis_at is not None else None, "basis_at": item.basis_at,
            "model_choice": json.dumps(item.choice, sort_keys=True) if item.choice is not None else None,
            "operation_name": "chat",
            "provider_name": model.provider, "request_model": model.model,
            "request_temperature": params.get("temperature"),
            "request_max_tokens": params.get("max_tokens", params.get("max_completion_tokens")),
            "request_seed": params.get("seed"), "request_params": json.dumps(params, sort_keys=True),
            "prompt_tokens_counted": item.prompt.tokens,
            "latency_s": reply.latency_s if reply else (error.latency_s if error else None),
            "attempts": reply.attempts if reply else (error.attempts if error else 1),
            "replayed": bool(reply.replayed) if reply else False,
        }
        # every attempt that was answered was billed, an error's (one without text, a broken stream) too: the
        # usage of them all is counted
        billed = reply if reply is not None else getattr(error, "answer", None)
        if billed is not None:
            row.update(response_model=billed.response_model, response_id=billed.response_id,
                       finish_reasons=billed.finish_reasons, cached_input_tokens=billed.cached_input_tokens,
                       cache_creation_input_tokens=billed.cache_creation_input_tokens,
                       **billed_usage(model.model, billed, item.prompt.tokens, row["request_max_tokens"]))
        if error is not None:
            row.update(error_type=error.error_type, error_message=clean_untrusted_text(error.message))
        if reply is not None:
            row.update(parse_error=item.parse_error, reply_reading=item.reading, reply_repairs=list(item.repairs))
        if id(item.prompt) not in canonical:
            canonical[id(item.prompt)] = canonical_messages(item.prompt.messages)
        calls.append((row, canonical[id(item.prompt)], clean_text(reply.text) if reply is not None else None,
                      json.dumps(item.suggestion, sort_keys=True) if item.suggestion is not None else None))
    with store.write() as con:
        insert_llm_calls(con, calls)


def check_budgets(store: Store, state: "RunState", client: LLMClient, prompts: list[Prompt],
                  models: list[LLMClient] | None = None, ticket: int | None = None) -> tuple[int, int, float] | None:
    """Raise :class:`BudgetExhausted` if the calls about to be made could take the run past a budget: their
    number, and each counted at its prompt plus a reply of the longest length asked for, priced at litellm's
    rates for the model that makes it (``models``, one per prompt; default: ``client`` for all). The run's
    spending so far is every call's, whichever model made it, and the worst case of the calls other threads have
    in flight (the proposal pool); these calls' worst case is reserved until :func:`release_budget` (after their
    rows are recorded): the reservation, or None without budgets. When only the reservations of calls in flight
    stand in the way, it waits for them to be recorded (they seldom use their worst case) and looks again.
    ``ticket`` (the proposal pool): it first waits for the candidates started before it to have checked theirs,
    so the budget's last calls go to the earliest candidates, whose iterations are committed first."""
    try:
        if ticket is not None:
            with state.budget_lock:
                state.budget_lock.wait_for(lambda: state.budget_turn >= ticket)
        return _check_budgets(store, state, client, prompts, models)
    finally:
        if ticket is not None:
            pass_budget_turn(state, ticket)


def pass_budget_turn(state: "RunState", ticket: int) -> None:
    """The pool's candidate ``ticket`` has checked the budgets, or will make no first call (a stored reply, an
    error before asking): the candidates after it may check theirs. Passing a ticket twice is harmless."""
    with state.budget_lock:
        state.budget_turns_passed.add(ticket)
        while state.budget_turn in state.budget_turns_passed:
            state.budget_turns_passed.discard(state.budget_turn)
            state.budget_turn += 1
        state.budget_lock.notify_all()


def _check_budgets(store: Store, state: "RunState", client: LLMClient, prompts: list[Prompt],
                   models: list[LLMClient] | None) -> tuple[int, int, float] | None:
    c = state.config
    if c.max_cost_usd is None and c.max_total_tokens is None and c.max_llm_calls is None:
        return None
    prompt_tokens = sum(p.tokens for p in prompts)
    worst_tokens = prompt_tokens + c.max_tokens * len(prompts)
    worst = 0.0
    if c.max_cost_usd is not None:
        for p, model in zip(prompts, models or [client] * len(prompts)):
            rates = price(model.model)
            if rates is None:
                raise BudgetExhausted(f"--max-cost needs a price for {model.label}, and litellm has none: use "
                                      "--max-total-tokens instead")
            worst += rates.cost(p.tokens, c.max_tokens)
    calls = "the next call" if len(prompts) == 1 else f"the next {len(prompts)} calls"

    def refusal(spent: dict, flying_calls: int, flying_tokens: int, flying_cost: float) -> BudgetExhausted | None:
        flying = f" ({flying_calls} more call{'s' * (flying_calls != 1)} in flight)" if flying_calls else ""
        if c.max_llm_calls is not None and spent["calls"] + flying_calls + len(prompts) > c.max_llm_calls:
            return BudgetExhausted(f"call budget: {spent['calls']} LLM calls made{flying}, {calls} would go over "
                                   f"--max-llm-calls {c.max_llm_calls}", "max_llm_calls")
        if c.max_total_tokens is not None and spent["tokens"] + flying_tokens + worst_tokens > c.max_total_tokens:
            return BudgetExhausted(f"token budget: {spent['tokens']:,} tokens used{flying}, {calls} may use up to "
                                   f"{worst_tokens:,} (prompt {prompt_tokens:,} + reply up to "
                                   f"{c.max_tokens * len(prompts):,}), over --max-total-tokens "
                                   f"{c.max_total_tokens:,}", "max_total_tokens")
        if c.max_cost_usd is not None and spent["cost_usd"] + flying_cost + worst > c.max_cost_usd:
            return BudgetExhausted(f"cost budget: ${spent['cost_usd']:.4f} spent{flying}, {calls} may cost up to "
                                   f"${worst:.4f}, over --max-cost ${c.max_cost_usd:g}", "max_cost_usd")
        return None

    with state.budget_lock:
        while True:
            with store.read() as con:
                spent = run_spending(con, state.run_id)
            why = refusal(spent, *state.in_flight)
            if why is None:
                break
            if state.in_flight[0] and refusal(spent, 0, 0, 0.0) is None:
                # only the worst cases of the calls in flight are in the way, and they mostly use far less: wait
                # for one to be recorded and look again
                state.budget_lock.wait()
                continue
            raise why
        reservation = (len(prompts), worst_tokens, worst)
        state.in_flight = [a + b for a, b in zip(state.in_flight, reservation)]
        return reservation


def release_budget(state: "RunState", reservation: tuple[int, int, float] | None) -> None:
    """Give back what :func:`check_budgets` reserved (the calls are recorded, or were never made)."""
    if reservation is not None:
        with state.budget_lock:
            state.in_flight = [a - b for a, b in zip(state.in_flight, reservation)]
            state.budget_lock.notify_all()


def check_wall(store: Store, state: "RunState", *, ahead: bool = False, uncommitted_s: float = 0.0) -> None:
    """Raise :class:`BudgetExhausted` if the run's time has passed ``max_wall_minutes`` — or, ``ahead``, if one
    more iteration as long as the last would pass it (the barrier loop, whose iterations come one after another).
    The run's time is the sum of its committed iterations' (time between a kill and its resume does not count) and
    ``uncommitted_s``, the time since the last commit (the proposal pool, whose calls run ahead of its commits)."""
    limit = state.config.max_wall_minutes
    if limit is None:
        return
    with store.read() as con:
        spent = run_spending(con, state.run_id)
    taken = spent["wall_s"] + uncommitted_s
    state.wall_deadline = time.monotonic() + limit * 60 - taken  # a call in flight then is given up on
    if ahead and taken + spent["last_wall_s"] > limit * 60:
        raise BudgetExhausted(
            f"time budget: the run has taken {taken / 60:.1f} min and its last iteration "
            f"{spent['last_wall_s'] / 60:.1f} min, over --max-wall {limit:g} min", "max_wall_minutes")
    if taken > limit * 60:
        raise BudgetExhausted(f"time budget: the run has taken {taken / 60:.1f} min, over --max-wall {limit:g} min",
                              "max_wall_minutes")
