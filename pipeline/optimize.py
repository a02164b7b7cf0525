"""``codearcade optimize``: the paper's optimization loop, with every step of it in the store.

Iteration 0 evaluates the starting policy. Each iteration k >= 1 then:

1. builds the prompt from the store (``pipeline/prompt.py``): the version to improve (the previous one, or the
   best one after a rollback), its traced training rollout, its evaluation, its feedback, and memory;
2. gets a reply: one stored for this very prompt (a resumed run) or one LLM call through litellm;
3. parses and validates the suggestion (``pipeline/reply.py``, ``pipeline/validate.py``): an accepted one
   becomes a new policy version, a rejected one is stored with its reason, which goes into the feedback;
4. plays a traced training rollout (the game's horizon: 400/300/15 steps) and the evaluation episodes in
   parallel worker processes; the score is the mean evaluation return, as verified by replaying each episode's
   actions in this process (``pipeline/verify.py``): a candidate caught tampering with its score is rejected;
5. writes the feedback (staged from the evaluation score, or rollout-only for the paper's ablation) and the
   ``iterations`` row in one transaction, and decides on a rollback: a score below
   ``best - (1 - rollback_fraction) * max(|best|, 1)`` (for a positive best: below ``rollback_fraction * best``)
   sends the next update back to the best version.

An iteration exists once its ``iterations`` row is committed. ``--resume RUN`` continues a killed run from
the store alone: it redoes the first iteration without a row, reusing a reply already stored for the same
prompt (prompts are deterministic), replacing any episodes the killed attempt left, and never duplicating an
iteration. ``codearcade replay RUN`` re-runs a finished run with the stored replies instead of the model.
"""

from __future__ import annotations

import json
import statistics
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, ContextManager

from games import get_game
from pipeline.executor import run_episodes
from pipeline.feedback import FEEDBACK_MODES, compose_feedback
from pipeline.llm import LLMClient, LLMError, LLMReply
from pipeline.prompt import Prompt, PromptBudgetError, build_prompt, canonical_messages, read_context
from pipeline.providers import price
from pipeline.reply import ReplyParseError, clean_text, parse_reply
from pipeline.rollout import EpisodeOutcome, EpisodeSpec
from pipeline.runinfo import episode_id, new_run_id, package_versions
from pipeline.task import example_path, task_settings
from pipeline.tokens import TokenCounter
from pipeline.untrusted import clean_untrusted_text
from pipeline.validate import CandidateRejected, RuntimeCheck, build_candidate, check_at_runtime, check_fits, spread
from pipeline.verify import StreamingVerification, tampering
from pipeline.versions import policy_version_row
from store import Store
from store.db import utcnow
from store.locks import run_lock
from store.readers import get_run, policy_text, run_spending, stored_reply
from store.writer import (
    finish_run,
    insert_llm_call,
    insert_policy_version,
    insert_run,
    set_llm_call_outcome,
    write_episode,
)
from tracing.policy_file import PolicyInfo, inspect_policy, read_policy_file

MAX_CONSECUTIVE_LLM_FAILURES = 3


@dataclass
class OptimizeConfig:
    """Options of an optimization run (the CLI flags of ``codearcade optimize``)."""

    game: str | None = None
    """Game; None takes the policy file's ``GAME``."""
    policy: str | None = None
    """Starting policy file; None starts from the game's scaffold in ``games/scaffolds/``."""
    model: str | None = None
    """litellm model string (``anthropic/...``, ``openai/...``); None: the offline SmolLM2 server."""
    api_base: str | None = None
    """Base URL of an OpenAI-compatible server (use with ``--model openai/NAME``)."""
    iterations: int = 20
    """Optimization iterations (LLM updates) after the evaluation of the starting policy (paper: 20)."""
    memory: int = 5
    """Earlier iterations shown in the prompt (paper: 5)."""
    token_budget: int = 16_000
    """Hard limit on the prompt's tokens; the trace slice is chosen to fit."""
    eval_episodes: int = 1
    """Evaluation episodes per iteration, played in parallel; the score is their mean return."""
    feedback: str = "staged"
    """``staged`` (from the evaluation score; the paper's method) or ``rollout`` (rollout reward only: the ablation)."""
    rollback: bool = True
    """Send the next update back to the best version after a regression."""
    rollback_fraction: float = 0.5
    """Regression threshold: below ``best - (1 - f) * max(|best|, 1)``."""
    seed: int = 0
    """Seed of the training rollout; evaluation episode i uses ``seed + i``."""
    temperature: float = 0.0
    """Sampling temperature of the LLM."""
    max_tokens: int = 4096
    """Longest reply asked for."""
    rollout_steps: int | None = None
    """Training rollout horizon; None: the task's (400 Pong, 300 Breakout, 15 Space Invaders)."""
    eval_max_steps: int | None = None
    """Evaluation cap; None: the task's (4000)."""
    workers: int = 2
    """Worker processes for the episodes of an iteration."""
    call_time_limit_s: float = 1.0
    """Time limit of one policy call."""
    episode_time_limit_s: float = 900.0
    """Wall-clock limit of one episode."""
    max_cost_usd: float | None = None
    """Stop (status ``budget``) before an LLM call that could take the run's cost past this many USD, counting
    the prompt and a reply of ``max_tokens`` at litellm's price; None: no limit. Needs a model litellm prices."""
    max_total_tokens: int | None = None
    """Stop (status ``budget``) before an LLM call that could take the run's input + output tokens past this."""
    max_wall_minutes: float | None = None
    """Stop (status ``budget``) before an iteration that, lasting as long as the last one, would take the run's
    wall time (the sum of its iterations) past this many minutes."""


BUDGET_FIELDS = ("max_cost_usd", "max_total_tokens", "max_wall_minutes")
"""Limits of how far a run goes, not of what it does: ``--resume`` may change them, batch keys ignore them."""

RESUME_OVERRIDES = BUDGET_FIELDS + ("model", "api_base", "iterations", "token_budget", "max_tokens", "workers",
                                    "call_time_limit_s", "episode_time_limit_s")
"""Settings that ``--resume`` takes from the command line; every other setting is the run's own."""


class BudgetExhausted(Exception):
    """The next step would exceed one of the run's budgets; the run stops with status ``budget``."""


@dataclass
class IterationResult:
    run_id: str
    iteration: int
    policy_version_id: str
    update_status: str
    score: float
    best_score: float
    best_iteration: int
    rolled_back: bool
    detail: str = ""
    prompt_tokens: int | None = None


@dataclass
class OptimizeResult:
    run_id: str
    status: str
    iterations: list[IterationResult] = field(default_factory=list)
    error: str | None = None


@dataclass
class _State:
    """What the loop carries from one iteration to the next (all of it derivable from the store)."""

    run_id: str
    game: str
    config: OptimizeConfig
    settings: dict[str, Any]
    next_iteration: int = 0
    best_score: float | None = None
    best_iteration: int = 0
    best_version_id: str | None = None
    llm_failures: int = 0
    rerun: str | None = None
    """Live Rerun recordings of this invocation's episodes (``EpisodeSpec.rerun``); an output option, not recorded."""
    waiting: Callable[[int, str], ContextManager[Callable[[str], None] | None]] = lambda it, model: nullcontext()
    """Wrapped around each LLM call (iteration, model label); what it yields gets the streamed text, if any. The
    CLI shows how long it has been waiting and how much text has arrived."""


def resolve_start(config: OptimizeConfig) -> tuple[PolicyInfo, str]:
    """The starting policy and the game, with one-line errors for bad input."""
    from pipeline.evaluate import resolve_game

    if config.policy is None:
        if config.game is None:
            raise ValueError("give a policy file or --game (`codearcade games` lists them)")
        path = example_path(config.game)
    else:
        path = Path(config.policy)
    info = inspect_policy(read_policy_file(path), path.name)
    game = resolve_game(info.game, config.game, path.name)
    if not info.trainable:
        raise ValueError(f"{path.name}: Policy has no trainable methods; mark some with @trace.bundle(trainable=True)")
    return info, game


def _validate_config(config: OptimizeConfig) -> None:
    if config.iterations < 0:
        raise ValueError("--iterations must be 0 or more")
    if config.memory < 0:
        raise ValueError("--memory must be 0 or more")
    if config.token_budget < 500:
        raise ValueError("--token-budget must be at least 500 tokens")
    if config.eval_episodes < 1:
        raise ValueError("--eval-episodes must be at least 1")
    if config.feedback not in FEEDBACK_MODES:
        raise ValueError(f"--feedback must be one of {', '.join(FEEDBACK_MODES)}")
    if not 0.0 <= config.rollback_fraction <= 1.0:
        raise ValueError("--rollback-fraction must be within [0, 1]")
    for name, flag in (("max_cost_usd", "--max-cost"), ("max_total_tokens", "--max-total-tokens"),
                       ("max_wall_minutes", "--max-wall")):
        value = getattr(config, name)
        if value is not None and value <= 0:
            raise ValueError(f"{flag} must be above 0, got {value:g}")


def start_run(config: OptimizeConfig, store: Store, model_name: str, kind: str = "optimize",
              extra: dict[str, Any] | None = None, starter: PolicyInfo | None = None) -> str:
    """Create the run and its iteration-0 policy version; return the run id.

    The starting policy is ``starter`` if given (a replay), else the file of ``config.policy`` or the scaffold.
    """
    _validate_config(config)
    if starter is None:
        info, game = resolve_start(config)
    else:
        info, game = starter, get_game(config.game or starter.game).name
    settings = task_settings(info, game)
    run_id = new_run_id()
    record = {**asdict(config), "game": game,
              "rollout_steps": config.rollout_steps or settings.rollout_steps,
              "eval_max_steps": config.eval_max_steps or settings.eval_max_steps,
              "instruction": settings.instruction, "feedback_bands": asdict(settings.feedback), **(extra or {})}
    with store.write() as con:
        insert_run(con, run_id, kind, game, record, info.text, info.version_id, package_versions(),
                   model=model_name, seed=config.seed)
        insert_policy_version(con, policy_version_row(info, run_id, 0, produced_by="initial", validation="accepted"))
    return run_id


def load_state(store: Store, run_id: str) -> _State:
    """The loop's state for ``run_id``, read back from the store (the whole of ``--resume``)."""
    from pipeline.feedback import FeedbackBands

    with store.read() as con:
        run = get_run(con, run_id)
        if run is None:
            raise ValueError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
        last = con.execute(
            "SELECT iteration, best_score, best_iteration, best_version_id FROM iterations WHERE run_id = ? "
            "ORDER BY iteration DESC LIMIT 1", [run_id]).fetchone()
    recorded = json.loads(run["config"])
    fields = {k: recorded[k] for k in OptimizeConfig.__dataclass_fields__ if k in recorded}
    config = OptimizeConfig(**fields)
    settings = {k: recorded[k] for k in ("rollout_steps", "eval_max_steps", "instruction", "feedback_bands")}
    settings["bands"] = FeedbackBands(**recorded["feedback_bands"])
    state = _State(run_id, run["game"], config, settings)
    if last is not None:
        state.next_iteration = last[0] + 1
        state.best_score, state.best_iteration, state.best_version_id = last[1], last[2], last[3]
    return state


def _episode_specs(state: _State, iteration: int, text: str, version_id: str) -> list[EpisodeSpec]:
    c = state.config
    common = dict(run_id=state.run_id, game=state.game, policy_text=text, policy_version_id=version_id,
                  policy_name="policy.py", iteration=iteration, call_time_limit_s=c.call_time_limit_s,
                  episode_time_limit_s=c.episode_time_limit_s, rerun=state.rerun)
    train = EpisodeSpec(episode_id=episode_id(state.run_id, iteration, "train", 0), kind="train", index=0,
                        seed=c.seed, max_steps=state.settings["rollout_steps"], trace=True, **common)
    evals = [EpisodeSpec(episode_id=episode_id(state.run_id, iteration, "eval", i), kind="eval", index=i,
                         seed=c.seed + i, max_steps=state.settings["eval_max_steps"], **common)
             for i in range(c.eval_episodes)]
    return [train] + evals


def _version_text(store: Store, run_id: str, version_id: str) -> str:
    with store.read() as con:
        return policy_text(con, run_id, version_id)


def _record_call(store: Store, state: _State, iteration: int, client: LLMClient, prompt: Prompt,
                 reply: LLMReply | None, error: LLMError | None) -> str:
    """Write the ``llm_calls`` row of one call (or failed call); return its id."""
    call_id = new_run_id()
    params = client.request_params()
    row = {
        "call_id": call_id, "run_id": state.run_id, "iteration": iteration, "purpose": "update",
        "operation_name": "chat", "provider_name": client.provider, "request_model": client.model,
        "request_temperature": params.get("temperature"),
        "request_max_tokens": params.get("max_tokens", params.get("max_completion_tokens")),
        "request_seed": params.get("seed"), "request_params": json.dumps(params, sort_keys=True),
        "prompt_tokens_counted": prompt.tokens,
        "latency_s": reply.latency_s if reply else (error.latency_s if error else None),
        "attempts": reply.attempts if reply else (error.attempts if error else 1),
        "replayed": bool(reply.replayed) if reply else False,
    }
    if reply is not None:
        row.update(response_model=reply.response_model, response_id=reply.response_id,
                   finish_reasons=reply.finish_reasons, input_tokens=reply.input_tokens,
                   output_tokens=reply.output_tokens, cached_input_tokens=reply.cached_input_tokens,
                   cache_creation_input_tokens=reply.cache_creation_input_tokens, cost_usd=reply.cost_usd)
    if error is not None:
        row.update(error_type=error.error_type, error_message=clean_untrusted_text(error.message))
    with store.write() as con:
        insert_llm_call(con, row, canonical_messages(prompt.messages),
                        clean_text(reply.text) if reply is not None else None)
    return call_id


def _set_call_outcome(store: Store, call_id: str, suggestion: dict[str, str] | None, parse_error: str | None) -> None:
    with store.write() as con:
        set_llm_call_outcome(con, call_id, json.dumps(suggestion, sort_keys=True) if suggestion is not None else None,
                             parse_error)


def _check_budgets(store: Store, state: _State, client: LLMClient, prompt: Prompt) -> None:
    """Raise :class:`BudgetExhausted` if the call about to be made could take the run past a budget: its
    prompt plus a reply of the longest length asked for, priced at litellm's rates."""
    c = state.config
    if c.max_cost_usd is None and c.max_total_tokens is None:
        return
    with store.read() as con:
        spent = run_spending(con, state.run_id)
    worst_tokens = prompt.tokens + c.max_tokens
    if c.max_total_tokens is not None and spent["tokens"] + worst_tokens > c.max_total_tokens:
        raise BudgetExhausted(
            f"token budget: {spent['tokens']:,} tokens used, the next call may use up to {worst_tokens:,} "
            f"(prompt {prompt.tokens:,} + reply up to {c.max_tokens:,}), over --max-total-tokens "
            f"{c.max_total_tokens:,}")
    if c.max_cost_usd is not None:
        rates = price(client.model)
        if rates is None:
            raise BudgetExhausted(f"--max-cost needs a price for {client.label}, and litellm has none: use "
                                  "--max-total-tokens instead")
        worst = rates.cost(prompt.tokens, c.max_tokens)
        if spent["cost_usd"] + worst > c.max_cost_usd:
            raise BudgetExhausted(
                f"cost budget: ${spent['cost_usd']:.4f} spent, the next call may cost up to ${worst:.4f}, over "
                f"--max-cost ${c.max_cost_usd:g}")


def _check_wall(store: Store, state: _State) -> None:
    """Raise :class:`BudgetExhausted` if another iteration as long as the last would pass ``max_wall_minutes``."""
    limit = state.config.max_wall_minutes
    if limit is None:
        return
    with store.read() as con:
        spent = run_spending(con, state.run_id)
    if spent["wall_s"] + spent["last_wall_s"] > limit * 60:
        raise BudgetExhausted(
            f"time budget: the run has taken {spent['wall_s'] / 60:.1f} min and its last iteration "
            f"{spent['last_wall_s'] / 60:.1f} min, over --max-wall {limit:g} min")


def _update(store: Store, state: _State, iteration: int, client: LLMClient, counter: TokenCounter,
            log: Callable[[str], None]) -> tuple[str, str, str | None, str, int | None]:
    """Step 1-3 of an iteration: (version to evaluate, update status, llm call id, note for feedback, tokens)."""
    c = state.config
    with store.read() as con:
        ctx = read_context(con, state.run_id, iteration, c.memory, c.call_time_limit_s)
    observations = [(r["step"], r["obs"]) for r in ctx.train_steps]
    base_version = ctx.info.version_id
    try:
        prompt = build_prompt(ctx, c.token_budget, counter)
    except PromptBudgetError as exc:
        raise ValueError(str(exc)) from None

    with store.read() as con:
        stored = stored_reply(con, state.run_id, iteration, prompt.hash)
    if stored is not None:
        call_id, text = stored
        log(f"iteration {iteration}: reusing the reply stored for this prompt")
    else:
        _check_budgets(store, state, client, prompt)
        try:
            with state.waiting(iteration, client.label) as on_text:
                reply = client.complete(prompt.messages, on_text=on_text)
        except LLMError as exc:
            call_id = _record_call(store, state, iteration, client, prompt, None, exc)
            state.llm_failures += 1
            if exc.fatal or state.llm_failures >= MAX_CONSECUTIVE_LLM_FAILURES:
                raise
            return base_version, "llm_error", call_id, f"The LLM call failed ({exc}); the code is unchanged.", prompt.tokens
        call_id = _record_call(store, state, iteration, client, prompt, reply, None)
        text = reply.text
    state.llm_failures = 0

    try:
        suggestion = parse_reply(text)
    except ReplyParseError as exc:
        _set_call_outcome(store, call_id, None, str(exc))
        return base_version, "rejected", call_id, (f"Your last reply was not usable: {exc}. Reply with the JSON "
                                                  "format asked for."), prompt.tokens
    _set_call_outcome(store, call_id, suggestion, None)

    try:
        candidate = build_candidate(ctx.info, suggestion)
        if candidate is not None:
            check_fits(candidate, c.token_budget, counter)
    except CandidateRejected as exc:  # nothing runnable to store: the reason is the record
        return base_version, "rejected", call_id, f"Your last suggestion was rejected: {exc}", prompt.tokens
    if candidate is None:
        return base_version, "unchanged", call_id, "Your last suggestion did not change the code.", prompt.tokens
    try:
        check_at_runtime(RuntimeCheck(candidate.text, state.game, spread(observations),
                                      call_time_limit_s=c.call_time_limit_s))
        verdict, reason = "accepted", None
    except CandidateRejected as exc:
        verdict, reason = "rejected", str(exc)
    with store.write() as con:
        insert_policy_version(con, policy_version_row(candidate.info, state.run_id, iteration, "llm", verdict,
                                                      reason, parent_id=base_version))
    if reason is not None:
        return base_version, "rejected", call_id, f"Your last suggestion was rejected: {reason}", prompt.tokens
    return candidate.version_id, "accepted", call_id, "", prompt.tokens


def _play(store: Store, state: _State, iteration: int, version_id: str,
          progress: Callable[[int, int], None] | None) -> tuple[EpisodeOutcome, list[EpisodeOutcome], float, float]:
    """Step 4: the traced training rollout and the evaluation episodes, written as they finish."""
    text = _version_text(store, state.run_id, version_id)
    specs = _episode_specs(state, iteration, text, version_id)
    outcomes: list[EpisodeOutcome | None] = [None] * len(specs)
    started = time.monotonic()
    train_done = None
    verification = StreamingVerification(specs)
    for i, outcome in run_episodes(specs, workers=max(1, state.config.workers), progress=progress,
                                   on_actions=verification.feed):
        outcome = verification.verify(i, outcome)
        with store.write() as con:
            write_episode(con, outcome.episode, outcome.steps, outcome.nodes, replace=True)
        outcomes[i] = outcome
        if i == 0:
            train_done = time.monotonic()
    eval_s = time.monotonic() - started
    train_s = (train_done or time.monotonic()) - started
    return outcomes[0], outcomes[1:], train_s, eval_s


def run_iteration(store: Store, state: _State, iteration: int, client: LLMClient | None,
                  counter: TokenCounter | None, log: Callable[[str], None],
                  progress: Callable[[int, int], None] | None = None) -> IterationResult:
    """One whole iteration (see the module docstring); commits its ``iterations`` row last."""
    started_at, t0 = utcnow(), time.monotonic()
    c = state.config
    notes: list[str] = []
    if iteration == 0:
        with store.read() as con:
            version_id = con.execute("SELECT starter_version_id FROM runs WHERE run_id = ?", [state.run_id]).fetchone()[0]
        base_version, status, call_id, tokens = None, "initial", None, None
    else:
        with store.read() as con:
            base_version = con.execute(
                "SELECT CASE WHEN rolled_back THEN best_version_id ELSE policy_version_id END FROM iterations "
                "WHERE run_id = ? AND iteration = ?", [state.run_id, iteration - 1]).fetchone()[0]
        version_id, status, call_id, note, tokens = _update(store, state, iteration, client, counter, log)
        if note:
            notes.append(note)
    llm_s = time.monotonic() - t0

    train, evals, train_s, eval_s = _play(store, state, iteration, version_id, progress)
    score = statistics.fmean(o.episode["return"] for o in evals)
    previous_best = state.best_score
    rolled_back = False
    tampered = tampering([train] + evals) if status == "accepted" else None
    if tampered:  # pipeline/verify.py: the candidate is rejected, never the best; the next update starts from the best
        status = "rejected"
        notes.insert(0, f"Your last suggestion was rejected: {tampered}")
        rolled_back = state.best_version_id is not None and version_id != state.best_version_id
        with store.write() as con:
            con.execute("UPDATE policy_versions SET validation = 'rejected', validation_error = ? WHERE run_id = ? "
                        "AND iteration = ? AND policy_version_id = ?", [tampered, state.run_id, iteration, version_id])
    elif previous_best is None or score > previous_best:
        state.best_score, state.best_iteration, state.best_version_id = score, iteration, version_id
    elif c.rollback and iteration > 0:
        threshold = previous_best - (1 - c.rollback_fraction) * max(abs(previous_best), 1.0)
        if score < threshold and version_id != state.best_version_id:
            rolled_back = True
            notes.append(f"This version scored {score:g}, below the best {previous_best:g} (iteration "
                         f"{state.best_iteration}): its change is rolled back, and the next update starts again from "
                         f"iteration {state.best_iteration}'s code.")
    stage, stage_score, text = compose_feedback(c.feedback, state.settings["bands"], score,
                                                train.episode["return"], train.episode["length"], notes)
    with store.write() as con:
        if rolled_back:
            best_text = policy_text(con, state.run_id, state.best_version_id)
            info = inspect_policy(best_text, "policy.py")
            insert_policy_version(con, policy_version_row(info, state.run_id, iteration, "rollback", "accepted",
                                                          parent_id=version_id))
        con.execute("INSERT INTO feedback VALUES (?, ?, ?, ?, ?, ?)",
                    [state.run_id, iteration, c.feedback, stage, stage_score, text])
        con.execute(
            """INSERT INTO iterations VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
            [state.run_id, iteration, version_id, base_version, status, rolled_back, call_id,
             train.episode["episode_id"], [o.episode["episode_id"] for o in evals], train.episode["return"], score,
             state.best_score, state.best_version_id, state.best_iteration, started_at, utcnow(), llm_s, train_s,
             eval_s, time.monotonic() - t0],
        )
    state.next_iteration = iteration + 1
    return IterationResult(state.run_id, iteration, version_id, status, score, state.best_score, state.best_iteration,
                           rolled_back, notes[0] if notes else "", tokens)


def run_loop(store: Store, state: _State, client: LLMClient | None, log: Callable[[str], None] = lambda s: None,
             on_iteration: Callable[[IterationResult], None] | None = None,
             progress: Callable[[int, int], None] | None = None) -> OptimizeResult:
    """Iterations ``state.next_iteration .. config.iterations``; marks the run finished, failed or interrupted.

    Holds the run's lock throughout (``store/locks.py``): a run another live process works on raises
    :class:`~store.locks.RunBusyError` before anything is written.
    """
    with run_lock(store.path, state.run_id):
        return _iterate(store, state, client, log, on_iteration, progress)


def _iterate(store, state, client, log, on_iteration, progress) -> OptimizeResult:
    counter = TokenCounter(client.model) if client is not None and state.config.iterations else None
    result = OptimizeResult(state.run_id, "running")
    status, error = "failed", None
    try:
        with store.write() as con:
            con.execute("UPDATE runs SET status = 'running', finished_at = NULL, error = NULL WHERE run_id = ?",
                        [state.run_id])
        for iteration in range(state.next_iteration, state.config.iterations + 1):
            if iteration > 0:
                _check_wall(store, state)
            item = run_iteration(store, state, iteration, client, counter, log, progress)
            result.iterations.append(item)
            if on_iteration is not None:
                on_iteration(item)
        status, error = "finished", _all_updates_failed(store, state.run_id)
        if error is not None:
            status = "failed"
    except KeyboardInterrupt:
        status, error = "interrupted", "interrupted by the user; continue with --resume"
        raise
    except BudgetExhausted as exc:
        status, error = "budget", f"{exc}; continue with a larger budget and --resume"
    except LLMError as exc:
        status, error = "failed", f"the LLM call failed: {exc}"
    except Exception as exc:
        status, error = "failed", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        result.status, result.error = status, error
        with store.write() as con:
            finish_run(con, state.run_id, status, error)
    return result


def _all_updates_failed(store: Store, run_id: str) -> str | None:
    """Why a run whose every update ended in an LLM error is not a success, or None."""
    with store.read() as con:
        updates, failed, last_error = con.execute(
            "SELECT count(*), count(*) FILTER (WHERE i.update_status = 'llm_error'), "
            "(SELECT arg_max(error_type || ': ' || error_message, created_at) FROM llm_calls "
            " WHERE run_id = ? AND error_type IS NOT NULL) "
            "FROM iterations i WHERE i.run_id = ? AND i.iteration > 0", [run_id, run_id]).fetchone()
    if updates and failed == updates:
        return f"every LLM call failed ({failed} of {updates} updates; last: {last_error})"
    return None


@dataclass
class ResumePlan:
    """What ``--resume`` will do: continue ``config`` (the run's own settings, with the command line's
    budgets, limits and endpoint), or nothing, with a message saying why."""

    run_id: str
    config: OptimizeConfig
    status: str
    nothing_to_do: str | None = None


def plan_resume(store: Store, run: str, given: dict[str, Any]) -> ResumePlan:
    """How to resume ``run`` (an id or a unique prefix of one) with the options ``given`` on the command line.

    Only :data:`RESUME_OVERRIDES` may be given; ``iterations`` may extend a run, never shrink it. A finished run
    is left as it is unless more iterations are asked for; an eval or replay run cannot be resumed.
    """
    from pipeline.llm import OFFLINE_MODEL_LABEL
    from pipeline.local_llm import MODEL_ALIAS
    from store.views import resolve_run_id

    with store.read() as con:
        run_id = resolve_run_id(con, run, store)
        row = get_run(con, run_id)
        done = con.execute("SELECT count(*) FROM iterations WHERE run_id = ?", [run_id]).fetchone()[0]
    if row["kind"] != "optimize":
        raise ValueError(f"run {run_id} is an {row['kind']} run: only optimization runs can be resumed "
                         f"({'evaluate the policy again with codearcade eval' if row['kind'] == 'eval' else 'replay the original run again'})")
    fixed = sorted(k for k in given if k not in RESUME_OVERRIDES)
    if fixed:
        flags = ", ".join("--" + k.replace("_s", "").replace("_", "-") for k in fixed)
        raise ValueError(f"{flags} cannot change when resuming run {run_id}: they are part of its settings "
                         "(start a new run instead)")
    recorded = json.loads(row["config"])
    config = OptimizeConfig(**{k: recorded[k] for k in OptimizeConfig.__dataclass_fields__ if k in recorded})
    if config.model == f"openai/{MODEL_ALIAS}" and not config.api_base or row["model"] == OFFLINE_MODEL_LABEL:
        config.model = None  # the offline model (runs made before its name was recorded as asked for)
    if given.get("iterations") is not None and given["iterations"] < config.iterations:
        raise ValueError(f"run {run_id} has {config.iterations} iterations planned; --iterations can only extend "
                         f"it, not shrink it")
    for key, value in given.items():
        setattr(config, key, value)
    _validate_config(config)
    if row["status"] == "finished" and done >= config.iterations + 1:
        return ResumePlan(run_id, config, row["status"], nothing_to_do=(
            f"run {run_id} is finished ({done - 1} of {config.iterations} iterations); nothing to do. "
            f"Give --iterations N (more than {config.iterations}) to extend it"))
    return ResumePlan(run_id, config, row["status"])


def optimize(config: OptimizeConfig, store: Store, client: LLMClient, resume: str | None = None,
             log: Callable[[str], None] = lambda s: None,
             on_iteration: Callable[[IterationResult], None] | None = None,
             progress: Callable[[int, int], None] | None = None,
             tags: dict[str, Any] | None = None, rerun: str | None = None,
             waiting: Callable[[int, str], ContextManager[Callable[[str], None] | None]] | None = None,
             ) -> OptimizeResult:
    """Start (or, with ``resume``, continue) an optimization run with ``client``; ``tags`` go into its config;
    ``rerun``: live Rerun recordings of the episodes (a directory or a gRPC url, see ``EpisodeSpec.rerun``).

    With ``resume``, ``config`` is the one :func:`plan_resume` made: its budgets, limits and endpoint replace
    the stored ones (and are recorded), the rest is the run's own.
    """
    _validate_config(config)
    run_id = resume or start_run(config, store, client.label, extra=tags)
    state = load_state(store, run_id)
    state.rerun = rerun
    if waiting is not None:
        state.waiting = waiting
    if resume:
        changed = {k: getattr(config, k) for k in RESUME_OVERRIDES if getattr(config, k) != getattr(state.config, k)}
        if changed:
            for key, value in changed.items():
                setattr(state.config, key, value)
            with store.write() as con:
                con.execute("UPDATE runs SET config = json_merge_patch(config, ?) WHERE run_id = ?",
                            [json.dumps(changed), run_id])
    return run_loop(store, state, client, log, on_iteration, progress)
