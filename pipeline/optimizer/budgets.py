"""The run's budgets: LLM calls, tokens and cost (``--max-llm-calls``, ``--max-total-tokens``, ``--max-cost``), and
time (``--max-wall``). A budget that the next step could pass raises :class:`BudgetExhausted`, and the run stops
with status ``budget``.

Before calls are made, their worst case (each prompt and a reply of ``max_tokens``, at litellm's price for the model
that makes it) is held against what the run has spent (its ``llm_calls``, every model's) and what the calls in flight
have set aside, and is set aside itself until the calls are recorded (:func:`check_budgets`,
:func:`release_budget`); the proposal pool's candidates check theirs in the order they started
(:func:`pass_budget_turn`). A retry of an attempt that was answered, and so billed, must fit as well
(:func:`retry_budget`). What a call's answered attempts are charged, their worst case where the endpoint reported no
usable count, is :func:`billed_usage`; :func:`check_wall` holds the run to its time. *propose*
(``pipeline/optimizer/propose.py``) asks the model; this module only counts.
"""

from __future__ import annotations

import time
from typing import Callable, Sequence

from pipeline.llm.answers import LLMReply
from pipeline.llm.client import BeforeRetry, LLMClient
from pipeline.llm.providers import price
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.prompt import Prompt
from pipeline.optimizer.state import RunState
from store import Store
from store.readers import run_spending


class BudgetExhausted(Exception):
    """The next step would exceed one of the run's budgets; the run stops with status ``budget``. ``setting``: the
    budget's (``max_llm_calls``, ...), for the command that goes on with a larger one; None where a larger one
    would not help."""

    def __init__(self, message: str, setting: str | None = None) -> None:
        super().__init__(message)
        self.setting = setting


def check_budgets(store: Store, state: RunState, client: LLMClient, prompts: list[Prompt],
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


def pass_budget_turn(state: RunState, ticket: int) -> None:
    """The pool's candidate ``ticket`` has checked the budgets, or will make no first call (a stored reply, an
    error before asking): the candidates after it may check theirs. Passing a ticket twice is harmless."""
    with state.budget_lock:
        state.budget_turns_passed.add(ticket)
        while state.budget_turn in state.budget_turns_passed:
            state.budget_turns_passed.discard(state.budget_turn)
            state.budget_turn += 1
        state.budget_lock.notify_all()


def _check_budgets(store: Store, state: RunState, client: LLMClient, prompts: list[Prompt],
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
    reservation = (len(prompts), worst_tokens, worst)

    def refusal(spent: dict, flying_calls: int, flying_tokens: int, flying_cost: float) -> BudgetExhausted | None:
        passed = _passed(c, spent, (flying_calls, flying_tokens, flying_cost), reservation)
        flying = f" ({flying_calls} more call{'s' * (flying_calls != 1)} in flight)" if flying_calls else ""
        if passed == "max_llm_calls":
            return BudgetExhausted(f"call budget: {spent['calls']} LLM calls made{flying}, {calls} would go over "
                                   f"--max-llm-calls {c.max_llm_calls}", passed)
        if passed == "max_total_tokens":
            return BudgetExhausted(f"token budget: {spent['tokens']:,} tokens used{flying}, {calls} may use up to "
                                   f"{worst_tokens:,} (prompt {prompt_tokens:,} + reply up to "
                                   f"{c.max_tokens * len(prompts):,}), over --max-total-tokens "
                                   f"{c.max_total_tokens:,}", passed)
        if passed == "max_cost_usd":
            return BudgetExhausted(f"cost budget: ${spent['cost_usd']:.4f} spent{flying}, {calls} may cost up to "
                                   f"${worst:.4f}, over --max-cost ${c.max_cost_usd:g}", passed)
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
        _reserve(state, reservation)
        return reservation


def release_budget(state: RunState, reservation: tuple[int, int, float] | None) -> None:
    """Give back what :func:`check_budgets` reserved (the calls are recorded, or were never made)."""
    if reservation is not None:
        with state.budget_lock:
            state.in_flight = [a - b for a, b in zip(state.in_flight, reservation)]
            state.budget_lock.notify_all()


def check_wall(store: Store, state: RunState, *, ahead: bool = False, uncommitted_s: float = 0.0) -> None:
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


def retry_budget(store: Store, state: RunState, model: LLMClient, prompt_tokens: int, retries: list,
                 refused: Callable[[BudgetExhausted], None]) -> BeforeRetry:
    """The client's question before it retries an attempt of a call (its prompt: ``prompt_tokens``) that was
    answered, and so billed (``LiteLLMClient.complete``): the reservation of :func:`check_budgets` set aside one
    worst case for the call, which that attempt has used part of, and the provider bills every attempt. The retry
    goes only if the budgets still have room for what the attempt was charged (:func:`billed_usage`) on top of
    everything spent and reserved; that much is then reserved too (in ``retries``, given back with the
    reservation), so the call's attempts together never take the run past a budget. Otherwise the call ends there
    (``BudgetSpent``) and ``refused`` is told why; nothing waits for the calls in flight (two calls waiting on each
    other)."""
    c = state.config

    def before_retry(attempt: LLMReply) -> str | None:
        charge = billed_usage(model.model, attempt, prompt_tokens, c.max_tokens)
        tokens = (charge["input_tokens"] or 0) + (charge["output_tokens"] or 0)
        rates = price(model.model) if c.max_cost_usd is not None else None
        cost = charge["cost_usd"] if charge["cost_usd"] is not None else (
            rates.cost(prompt_tokens, c.max_tokens) if rates is not None else 0.0)
        worst = prompt_tokens + c.max_tokens
        with state.budget_lock:
            with store.read() as con:
                spent = run_spending(con, state.run_id)
            passed = _passed(c, spent, state.in_flight, (None, tokens, cost))
            _, flying_tokens, flying_cost = state.in_flight
            why = None
            if passed == "max_total_tokens":
                why = BudgetExhausted(
                    f"token budget: {spent['tokens']:,} tokens used, {flying_tokens:,} set aside for the calls in "
                    f"flight, and an attempt of this call was billed {tokens:,}: a retry, which may use up to "
                    f"{worst:,} more, would go over --max-total-tokens {c.max_total_tokens:,}", passed)
            elif passed == "max_cost_usd":
                why = BudgetExhausted(
                    f"cost budget: ${spent['cost_usd']:.4f} spent, ${flying_cost:.4f} set aside for the calls in "
                    f"flight, and an attempt of this call was billed ${cost:.4f}: a retry would go over --max-cost "
                    f"${c.max_cost_usd:g}", passed)
            if why is not None:
                refused(why)
                return str(why)
            _reserve(state, (0, tokens, cost))
            retries[1] += tokens
            retries[2] += cost
        return None

    return before_retry


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


def _passed(c: OptimizeConfig, spent: dict, flying: Sequence[float],
            wanted: tuple[int | None, int, float]) -> str | None:
    """The setting of the first budget (calls, tokens, cost) that the run's spending (``spent``: the store's), the
    reservations of the calls in flight (``flying``) and ``wanted`` would pass together; None when they fit.
    ``wanted`` of None calls is not held to the call budget (a retry is no new call)."""
    calls, tokens, cost = wanted
    if calls is not None and c.max_llm_calls is not None and spent["calls"] + flying[0] + calls > c.max_llm_calls:
        return "max_llm_calls"
    if c.max_total_tokens is not None and spent["tokens"] + flying[1] + tokens > c.max_total_tokens:
        return "max_total_tokens"
    if c.max_cost_usd is not None and spent["cost_usd"] + flying[2] + cost > c.max_cost_usd:
        return "max_cost_usd"
    return None


def _reserve(state: RunState, amounts: Sequence[float]) -> None:
    """Set ``amounts`` (calls, tokens, cost) aside for calls in flight (under ``budget_lock``), until
    :func:`release_budget` gives them back."""
    state.in_flight = [a + b for a, b in zip(state.in_flight, amounts)]
