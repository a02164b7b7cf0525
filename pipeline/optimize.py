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
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from pipeline.executor import run_episodes
from pipeline.feedback import FEEDBACK_MODES, compose_feedback
from pipeline.games import get_game
from pipeline.llm import LLMClient, LLMError, LLMReply
from pipeline.prompt import Prompt, PromptBudgetError, build_prompt, canonical_messages, read_context
from pipeline.reply import ReplyParseError, clean_text, parse_reply
from pipeline.rollout import EpisodeOutcome, EpisodeSpec
from pipeline.runinfo import episode_id, new_run_id, package_versions
from pipeline.task import example_path, task_settings
from pipeline.tokens import TokenCounter
from pipeline.untrusted import clean_untrusted_text
from pipeline.validate import (CandidateRejected, RuntimeCheck, build_candidate, check_at_runtime, check_fits,
                               spread)
from pipeline.verify import tampering, verify_outcome
from pipeline.versions import policy_version_row
from store import Store
from store.db import utcnow
from store.locks import run_lock
from store.readers import get_run, policy_text
from store.writer import finish_run, insert_policy_version, insert_run, put_blob, write_episode
from tracing.policy_file import PolicyInfo, inspect_policy, read_policy_file

MAX_CONSECUTIVE_LLM_FAILURES = 3
RESUME_LIMITS = ("token_budget", "max_tokens", "call_time_limit_s", "workers")
"""Limits a resumed run takes from the config it is resumed with (the command line), not from its record."""


@dataclass
class OptimizeConfig:
    """Options of an optimization run (the CLI flags of ``codearcade optimize``)."""

    game: str | None = None
    """Game; None takes the policy file's ``GAME``."""
    policy: str | None = None
    """Starting policy file; None starts from the game's scaffold in ``examples/``."""
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


def resolve_start(config: OptimizeConfig) -> tuple[PolicyInfo, str]:
    """The starting policy and the game, with one-line errors for bad input."""
    from pipeline.evaluate import resolve_game

    if config.policy is None:
        if config.game is None:
            raise ValueError("give a policy file or --game (pong, breakout, space_invaders)")
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
    record = {**asdict(config), "game": game, "model": model_name,
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


def _stored_reply(store: Store, run_id: str, iteration: int, digest: str) -> tuple[str, str] | None:
    rows = store.query(
        "SELECT c.call_id, b.text FROM llm_calls c JOIN blobs b ON b.hash = c.reply_hash "
        "WHERE c.run_id = ? AND c.iteration = ? AND c.prompt_hash = ? AND c.error_type IS NULL "
        "ORDER BY c.created_at LIMIT 1", [run_id, iteration, digest])
    return (rows[0][0], rows[0][1]) if rows else None


def _record_call(store: Store, state: _State, iteration: int, client: LLMClient, prompt: Prompt,
                 reply: LLMReply | None, error: LLMError | None) -> str:
    call_id = new_run_id()
    with store.write() as con:
        prompt_digest = put_blob(con, "prompt", canonical_messages(prompt.messages))
        reply_digest = put_blob(con, "reply", clean_text(reply.text)) if reply is not None else None
        params = client.request_params()
        con.execute(
            """INSERT INTO llm_calls (call_id, run_id, iteration, purpose, created_at, operation_name,
                   provider_name, request_model, response_model, request_temperature, request_max_tokens,
                   request_seed, request_params, prompt_hash, reply_hash, response_id, finish_reasons,
                   input_tokens, output_tokens, prompt_tokens_counted, cost_usd, latency_s, attempts,
                   error_type, error_message, replayed)
               VALUES (?, ?, ?, 'update', ?, 'chat', ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)""",
            [call_id, state.run_id, iteration, utcnow(), client.provider, client.model,
             reply.response_model if reply else None, params.get("temperature"), params.get("max_tokens"),
             params.get("seed"), json.dumps(params, sort_keys=True), prompt_digest, reply_digest,
             reply.response_id if reply else None, reply.finish_reasons if reply else None,
             reply.input_tokens if reply else None, reply.output_tokens if reply else None, prompt.tokens,
             reply.cost_usd if reply else None, reply.latency_s if reply else (error.latency_s if error else None),
             reply.attempts if reply else (error.attempts if error else 1),
             error.error_type if error else None, clean_untrusted_text(error.message) if error else None,
             bool(reply.replayed) if reply else False],
        )
    return call_id


def _set_call_outcome(store: Store, call_id: str, suggestion: dict[str, str] | None, parse_error: str | None) -> None:
    with store.write() as con:
        digest = put_blob(con, "suggestion", json.dumps(suggestion, sort_keys=True)) if suggestion is not None else None
        con.execute("UPDATE llm_calls SET suggestion_hash = ?, parse_error = ? WHERE call_id = ?",
                    [digest, parse_error, call_id])


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

    stored = _stored_reply(store, state.run_id, iteration, prompt.hash)
    if stored is not None:
        call_id, text = stored
        log(f"iteration {iteration}: reusing the reply stored for this prompt")
    else:
        try:
            reply = client.complete(prompt.messages)
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
    for i, outcome in run_episodes(specs, workers=max(1, state.config.workers), progress=progress):
        outcome = verify_outcome(specs[i], outcome)
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
            item = run_iteration(store, state, iteration, client, counter, log, progress)
            result.iterations.append(item)
            if on_iteration is not None:
                on_iteration(item)
        status = "finished"
    except KeyboardInterrupt:
        status, error = "interrupted", "interrupted by the user; continue with --resume"
        raise
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


def optimize(config: OptimizeConfig, store: Store, client: LLMClient, resume: str | None = None,
             log: Callable[[str], None] = lambda s: None,
             on_iteration: Callable[[IterationResult], None] | None = None,
             progress: Callable[[int, int], None] | None = None,
             tags: dict[str, Any] | None = None, rerun: str | None = None) -> OptimizeResult:
    """Start (or, with ``resume``, continue) an optimization run with ``client``; ``tags`` go into its config;
    ``rerun``: live Rerun recordings of the episodes (a directory or a gRPC url, see ``EpisodeSpec.rerun``)."""
    _validate_config(config)
    run_id = resume or start_run(config, store, client.model, extra=tags)
    state = load_state(store, run_id)
    state.rerun = rerun
    if resume:  # resuming may extend a run, never shrink it; the limits given now apply (and are recorded)
        patch = {k: getattr(config, k) for k in RESUME_LIMITS if getattr(config, k) != getattr(state.config, k)}
        if config.iterations > state.config.iterations:
            patch["iterations"] = config.iterations
        if patch:
            for name, value in patch.items():
                setattr(state.config, name, value)
            with store.write() as con:
                con.execute("UPDATE runs SET config = json_merge_patch(config, ?) WHERE run_id = ?",
                            [json.dumps(patch), run_id])
    return run_loop(store, state, client, log, on_iteration, progress)
