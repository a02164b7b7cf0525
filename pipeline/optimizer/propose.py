"""*propose*: from a strategy's requests to candidates — store slices → prompt → LLM → parsed, validated version.

For each :class:`~pipeline.optimizer.strategies.ProposalRequest` of an iteration:

1. the prompt is built from the store (``pipeline/optimizer/prompt.py``) for the parent candidate, under the token budget;
2. a reply already stored for this prompt, iteration and candidate is reused (a resumed run); the others are
   requested from the model **concurrently** (at most ``max_concurrent_calls`` at a time), after checking that
   all of them together stay within the run's cost and token budgets (``pipeline/optimizer/budgets.py``);
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
from pipeline.llm.answers import EMPTY_REPLY, LLMReply
from pipeline.llm.client import OUT_OF_TIME, BeforeRetry, LLMClient, LLMError, canonical_messages
from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer.budgets import BudgetExhausted, billed_usage, check_budgets, release_budget, retry_budget
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
from store.readers import stored_replies
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
    """Why the reply is unusable, as stored and logged (with advice for the person who runs it)."""
    unusable: ReplyParseError | None = None
    """The same as an error, which :func:`unusable_reply_note` words for the model."""
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
    """Why its call was not retried after a billed attempt: another would not fit a budget
    (``budgets.retry_budget``)."""

    def parse(self) -> None:
        reply = self.reply
        try:
            read = read_reply(self.text, structured=reply is not None and reply.structured,
                              cut_off=reply is not None and reply.cut_off)
        except ReplyParseError as exc:
            self.suggestion, self.parse_error, self.reading, self.repairs = None, str(exc), "unusable", ()
            self.unusable = exc
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
    (``budgets.check_budgets``; the caller passes the ticket with ``budgets.pass_budget_turn`` however this ends)."""
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


def unusable_reply_note(exc: ReplyParseError, max_tokens: int) -> str:
    """Why a reply is unusable, as the model is told it (in its repair turn and the next prompt's feedback): a
    reply cut off at the token limit is not told to raise ``--max-tokens``, the person's remedy, but to fit."""
    if not exc.cut_off:
        return exc.reason
    return (f"{exc.reason}. A reply may be at most {max_tokens:,} tokens long: send only the methods you change, "
            "each complete, and keep the reasoning short")


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
    """Ask for the replies of ``items`` (their worst case reserved by ``budgets.check_budgets``), read them and record
    the calls; the reservation is given back once they are recorded (or the asking failed). Other processes may
    read the store while the model thinks: ``hold`` is let go (checkpointing what this process wrote) once the
    requests are on their way, and taken again for the recording."""
    retries = [0, 0, 0.0]  # what the retries of billed attempts reserved on top of ``reservation``

    def before_retry(item: _Pending) -> BeforeRetry:
        return retry_budget(store, state, item.client or client, item.prompt.tokens, retries,
                            refused=lambda why: setattr(item, "over_budget", why))

    try:
        _complete_all(state, iteration, client, items, meanwhile=hold.release if hold is not None else None,
                      before_retry=None if reservation is None else before_retry)
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


def _replies(n: int) -> str:
    return "the reply" if n == 1 else f"{n} replies"


def _complete_all(state: "RunState", iteration: int, client: LLMClient, items: list[_Pending],
                  meanwhile: Callable[[], None] | None = None,
                  before_retry: Callable[[_Pending], BeforeRetry] | None = None) -> None:
    """Request every reply, at most ``max_concurrent_calls`` at a time; each item gets its reply or error.
    ``meanwhile`` runs in a thread of its own while the model is asked (its error is raised after the replies);
    ``before_retry(item)``: what its call asks before it retries a billed attempt (``budgets.retry_budget``)."""

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
    if helper is not None:  # first: a client's first use below waits seconds for litellm's import
        helper.start()
    try:
        for model in {id(m): m for m in (item.client or client for item in items)}.values():
            model.request_params()  # what the client asks litellm on first use (and says) is said before the wait
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
            answer = item.error.answer
            if item.error.error_type == EMPTY_REPLY and answer is not None and answer.cut_off:  # the model's to mend
                note = (f"Your last reply stopped at the token limit before any text: a reply may be at most "
                        f"{c.max_tokens:,} tokens long, so keep it short (only the methods you change); the code is "
                        "unchanged.")
            else:
                note = f"The LLM call failed ({item.error}); the code is unchanged."
            proposals.append(outcome(item, "llm_error", note))
            continue
        if item.parse_error is not None:
            why = unusable_reply_note(item.unusable, c.max_tokens) if item.unusable else item.parse_error
            proposals.append(outcome(item, "rejected", f"Your last reply was not usable: {why}. Reply with the JSON "
                                                       "format asked for.",
                                     fixable=f"Your reply was not usable: {why}."))
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
