"""``codearcade optimize``: the optimization loop — a strategy, proposals and assessments, all in the store.

The loop is three parts with one job each, driven from here:

- *strategy* (``pipeline/optimizer/strategies.py``): from the run's history in the store, which candidates to improve this
  iteration and with what memory; afterwards, which candidate stands for the iteration, whether it is the new
  best, and a decision on each. ``greedy`` is the paper's loop (improve the last version, roll back to the best
  after a regression); ``best-of-n`` and ``beam`` search wider.
- *propose* (``pipeline/optimizer/propose.py``): prompt from the store → LLM (concurrent calls) → parsed, validated version.
- *assess* (``pipeline/optimizer/assess.py``): the traced training rollout and the evaluation episodes of every candidate,
  played concurrently in confined workers, each score verified by replay; versions already assessed in the run
  reuse their episodes (the evaluation cache).

The run's settings are an :class:`~pipeline.optimizer.config.OptimizeConfig` (``config.py``); what the loop
carries from one iteration to the next is a :class:`~pipeline.optimizer.state.RunState` (``state.py``); its
budgets of calls, tokens, cost and time are held in ``budgets.py``.

Iteration 0 assesses the starting policy. Each iteration then writes its candidates (parents, LLM call, score,
decision, feedback), the feedback of the chosen one and the ``iterations`` row in one transaction. An iteration
exists once that transaction commits. ``--resume RUN`` continues a killed run from the store alone: it redoes
the first iteration without a row, reusing each candidate's reply already stored for the same prompt (prompts
are deterministic), replacing any episodes the killed attempt left, and never duplicating an iteration or a
candidate. ``codearcade replay RUN`` re-runs a run with the stored replies instead of the model.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, ContextManager, Iterator

from games import get_game
from pipeline.llm.client import LLMClient, LLMError
from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer.assess import assess, screen
from pipeline.optimizer.conclude import IterationResult, conclude, screen_out
from pipeline.optimizer.pool import run_pool
from pipeline.optimizer.config import RESUME_OVERRIDES, OptimizeConfig, validate_config
from pipeline.settings import flag_of
from pipeline.stopping import uninterrupted
from pipeline.optimizer.feedback import FeedbackBands
from pipeline.optimizer.budgets import BudgetExhausted, check_wall
from pipeline.optimizer.propose import Proposal, propose
from pipeline.optimizer.prompt import check_prompt_fits
from pipeline.optimizer.state import RunState
from pipeline.optimizer.strategies import History
from pipeline.optimizer.task import recorded_task_problem, resolve_start, task_settings
from pipeline.play.runinfo import new_run_id, package_versions
from pipeline.play.versions import policy_version_row
from store import Store
from store.db import Hold, is_ctrl_c, utcnow
from store.locks import lock_folder, run_lock
from store.readers import (
    candidates,
    get_run,
    iteration_count,
    iterations,
    last_iteration,
    starter_version_id,
    update_failures,
)
from store.recorded import read_recorded, unreadable_settings
from store.runs import kind_phrase
from store.writer import (
    end_run_left_running,
    finish_run,
    insert_policy_version,
    insert_run,
    mark_run_running,
    merge_run_config,
)
from tracing.policy_file import PolicyInfo

__all__ = ["BudgetExhausted", "NewRun", "new_run", "optimize", "plan_resume", "run_loop", "start_run", "load_state"]


@dataclass
class OptimizeResult:
    run_id: str
    status: str
    iterations: list[IterationResult] = field(default_factory=list)
    error: str | None = None
    audit: Any = None
    """The held-out audit played when the run ended (``pipeline/optimizer/audit.py``: an ``AuditResult``)."""
    budget: str | None = None
    """The setting of the budget that stopped the run (status ``budget``: ``max_llm_calls``, ...; None where a
    larger one would not help)."""


def start_run(config: OptimizeConfig, store: Store, model_name: str, kind: str = "optimize",
              extra: dict[str, Any] | None = None, starter: PolicyInfo | None = None,
              start: tuple[PolicyInfo, str] | None = None) -> str:
    """Create the run and its iteration-0 policy version; return the run id.

    The starting policy is ``starter`` if given (a replay), else the file of ``config.policy`` or the scaffold
    (``start``: it and its game, as :func:`resolve_start` gave them already).
    """
    validate_config(config)
    if starter is None:
        info, game = start or resolve_start(config)
    else:
        info, game = starter, get_game(config.game or starter.game).name
    settings = task_settings(info, game)
    run_id = new_run_id()
    record = {**asdict(config), "game": game, "rng_key": config.rng_key or run_id,
              "rollout_steps": config.rollout_steps or settings.rollout_steps,
              "eval_max_steps": config.eval_max_steps or settings.eval_max_steps,
              "instruction": settings.instruction, "feedback_bands": asdict(settings.feedback), **(extra or {})}
    if config.models:  # an ensemble's prices, as litellm has them now: its choices do not move with a later one
        record["models"] = _priced(config.models)
    with store.write() as con:
        insert_run(con, run_id, kind, game, record, info.text, info.version_id, package_versions(),
                   model=model_name, seed=config.seed)
        insert_policy_version(con, policy_version_row(info, run_id, 0, produced_by="initial", validation="accepted"))
    return run_id


def _end_if_cut_short(store: Store, run_id: str, exc: BaseException, client: LLMClient | None = None) -> None:
    """End the new run ``run_id`` that ``exc`` stopped before its loop took it over, as the loop would have: a
    Ctrl-C or SIGTERM as interrupted (resumable), anything else as failed. A run the loop ended is left as it is.
    Never raises: a store that cannot be written is ``exc``'s story to tell."""
    if isinstance(exc, KeyboardInterrupt) or is_ctrl_c(exc):
        status, error = "interrupted", f"interrupted by the user; {_go_on(client)}"
    else:
        status, error = "failed", f"{type(exc).__name__}: {exc}"
    try:
        with uninterrupted(), store.write() as con:
            end_run_left_running(con, run_id, status, error)
    except Exception:  # noqa: BLE001 - the store's own failure; the caller re-raises exc, which says what happened
        pass


class NewRun:
    """The run a command makes inside :func:`new_run` (:meth:`start`); ``run_id`` is None until it is made."""

    def __init__(self, store: Store, client: LLMClient | None = None) -> None:
        self.store, self.client = store, client
        self.run_id: str | None = None

    def start(self, config: OptimizeConfig, model_name: str, **kwargs: Any) -> str:
        """:func:`start_run` (same arguments after the store): a press as the run is made is raised once its id
        is known here, so that :func:`new_run` ends it. A budget no prompt fits is refused first
        (``prompt.check_prompt_fits``), whichever command makes the run."""
        if self.client is not None and config.iterations and kwargs.get("starter") is None:
            # the check ran only in optimize(): `codearcade optimize --token-budget 600` (and a batch's run) made
            # its run, played iteration 0 and failed at iteration 1's prompt
            info, game = kwargs["start"] = kwargs.get("start") or resolve_start(config)
            check_prompt_fits(config.token_budget, game, task_settings(info, game).instruction, info,
                              self.client.model, config.call_time_limit_s)
        lock_folder(self.store.path)  # a run that could not be locked is not made (it was, then failed)
        with uninterrupted():
            self.run_id = start_run(config, self.store, model_name, **kwargs)
        return self.run_id


@contextmanager
def new_run(store: Store, client: LLMClient | None = None) -> Iterator[NewRun]:
    """Make a run with the yielded :meth:`NewRun.start` and hand it to the loop; if anything stops the block
    before the loop has ended the run, end it as the loop would (:func:`_end_if_cut_short`).

    :func:`start_run` writes a new run as 'running'; what a command does next (its start line, its name, its Rerun
    recordings, loading the state, taking the run's lock) is outside the loop, and a stop there left the row
    'running' for good (shown interrupted only while no process holds it). Only a run made in the block is ended:
    a resumed one may be another live process's. The command line, a batch's run, :func:`optimize` and a replay
    all make their runs this way."""
    made = NewRun(store, client)
    try:
        yield made
    except BaseException as exc:
        if made.run_id is not None:
            _end_if_cut_short(store, made.run_id, exc, client)
        raise


def _priced(models: list[dict[str, Any]]) -> list[dict[str, Any]]:
    from pipeline.llm.providers import price
    from pipeline.optimizer.ensemble import priced

    return priced(models, price)


def load_state(store: Store, run_id: str) -> RunState:
    """The loop's state for ``run_id``, read back from the store (the whole of ``--resume``)."""
    with store.read() as con:
        run = get_run(con, run_id)
        if run is None:
            raise ValueError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
        last = last_iteration(con, run_id)
    recorded = read_recorded(run["config"], run_id)
    config = OptimizeConfig.from_record(recorded, run_id)
    problem = recorded_task_problem(recorded)  # the task's, as the run started with them
    if problem is not None:
        raise unreadable_settings(run_id, problem)
    settings = {k: recorded.get(k) for k in ("rollout_steps", "eval_max_steps", "instruction", "feedback_bands")}
    settings["bands"] = FeedbackBands.from_record(recorded.get("feedback_bands"), run_id)
    state = RunState(run_id, run["game"], config, settings, rng_key=recorded.get("rng_key"))
    if last is not None:
        state.next_iteration = last["iteration"] + 1
        state.best_score, state.best_iteration = last["best_score"], last["best_iteration"]
        state.best_version_id = last["best_version_id"]
    return state


def run_iteration(store: Store, state: RunState, iteration: int, client: LLMClient | None,
                  counter: TokenCounter | None, log: Callable[[str], None],
                  progress: Callable[[int, int], None] | None = None, hold: Hold | None = None) -> IterationResult:
    """One whole iteration (see the module docstring): plan, propose, assess, decide; commits its rows last.

    ``hold``: the loop's hold on the store, kept from this iteration's commit to the next one's LLM calls (the
    file is let go and checkpointed once per iteration, before the model is asked); without one, the iteration
    holds the store itself and lets go when it is done."""
    started_at, t0 = utcnow(), time.monotonic()
    own = hold is None
    hold = store.hold() if own else hold  # all but the LLM calls and the episodes: short reads and writes
    try:
        return _run_iteration(store, state, iteration, client, counter, log, progress, hold, started_at, t0)
    finally:
        if own:
            hold.release()


def _run_iteration(store, state, iteration, client, counter, log, progress, hold, started_at, t0) -> IterationResult:
    hold.take()  # propose lets go while the model is asked
    history = state.history
    if history is None or len(history.iterations) != iteration:
        with store.read() as con:
            history = History(iterations(con, state.run_id, iteration), candidates(con, state.run_id, iteration))
    if iteration == 0:
        with store.read() as con:
            starter = starter_version_id(con, state.run_id)
    strategy = state.strategy
    if iteration == 0:
        proposals = [Proposal(0, None, None, "initial", starter, starter, None, "", None)]
    else:
        requests = strategy.plan(history, iteration)
        proposals = propose(store, state, history, iteration, requests, client, counter, log, hold)
    llm_s = time.monotonic() - t0

    screens = {}
    if iteration > 0 and state.config.screen_steps:
        screens = screen(store, state, iteration, history, [p for p in proposals if p.status == "accepted"], progress,
                         before_play=hold.release)
        screen_out(proposals, screens)
    assessments, times = assess(store, state, iteration, {p.candidate: p.version_id for p in proposals}, progress,
                                texts={p.version_id: p.text for p in proposals if p.text is not None},
                                before_play=hold.release, after_play=hold.take)
    hold.take()  # (taken already if episodes were played)
    return conclude(store, state, iteration, history, proposals, assessments, screens,
                    timing=dict(started_at=started_at, llm_s=llm_s, train_s=times.train_s, eval_s=times.eval_s, t0=t0))


def run_loop(store: Store, state: RunState, client: LLMClient | None, log: Callable[[str], None] = lambda s: None,
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
    hold = store.hold()
    try:
        with store.write() as con:
            mark_run_running(con, state.run_id)
        for iteration in range(state.next_iteration, state.config.iterations + 1):
            if state.config.pool and iteration > 0:  # the proposal pool takes the updates from here
                hold.release()  # its threads use the store in turns, and other processes may read it between
                run_pool(store, state, client, counter, log, lambda item: _report(result, item, on_iteration), progress)
                break
            if iteration > 0:
                check_wall(store, state, ahead=True)
            _report(result, run_iteration(store, state, iteration, client, counter, log, progress, hold), on_iteration)
        status, error = "finished", _all_updates_failed(store, state.run_id)
        if error is not None:
            status = "failed"
        else:
            result.audit = _audit(store, state, log, progress, hold)
    except KeyboardInterrupt:
        status, error = "interrupted", f"interrupted by the user; {_go_on(client)}"
        raise
    except BudgetExhausted as exc:
        status, error = "budget", f"{exc}; continue with a larger budget and --resume"
        result.budget = exc.setting
        result.audit = _audit(store, state, log, progress, hold)
    except LLMError as exc:
        status, error = "failed", f"the LLM call failed: {exc}"
    except Exception as exc:
        if is_ctrl_c(exc):  # DuckDB's own word for a Ctrl-C that reached it past the store's conversion
            status, error = "interrupted", f"interrupted by the user; {_go_on(client)}"
            raise KeyboardInterrupt from None
        status, error = "failed", f"{type(exc).__name__}: {exc}"
        raise
    finally:
        result.status, result.error = status, error
        try:
            with uninterrupted(), store.write() as con:  # a press here had left a finished run 'running'
                finish_run(con, state.run_id, status, error)
        finally:
            hold.release()
    return result


def _report(result: OptimizeResult, item: IterationResult, on_iteration) -> None:
    result.iterations.append(item)
    if on_iteration is not None:
        on_iteration(item)


def _go_on(client: LLMClient | None) -> str:
    """How an interrupted run goes on: ``--resume``, or, for a replay (whose client answers from the record), the
    original replayed again (a replay run cannot be resumed)."""
    replaying = getattr(client, "provider", None) == "replay"
    return "replay the original run again" if replaying else "continue with --resume"


def _audit(store: Store, state: RunState, log: Callable[[str], None], progress, hold: Hold):
    """The held-out audit of the run's best version and starter (``audit_episodes`` games each; none: 0). It only
    measures: a failure is logged and leaves the run as it is (``codearcade audit RUN`` plays it again)."""
    from pipeline.optimizer.audit import audit_run

    if not state.config.audit_episodes:
        return None
    hold.release()  # playing takes a while: let readers in
    try:
        return audit_run(store, state.run_id, progress=progress)
    except Exception as exc:  # noqa: BLE001 - the run's iterations are stored; the audit can be played again
        log(f"codearcade: the held-out audit failed ({type(exc).__name__}: {exc}); play it with "
            f"`codearcade audit {state.run_id}`")
        return None


def _all_updates_failed(store: Store, run_id: str) -> str | None:
    """Why a run whose every update ended in an LLM error is not a success, or None."""
    with store.read() as con:
        updates, failed, last_error = update_failures(con, run_id)
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
    from pipeline.llm.client import OFFLINE_MODEL_LABEL
    from pipeline.llm.local import MODEL_ALIAS
    from store.views import resolve_run_id

    with store.read() as con:
        run_id = resolve_run_id(con, run, store)
        row = get_run(con, run_id)
        done = iteration_count(con, run_id)
    if row["kind"] != "optimize":
        raise ValueError(f"run {run_id} is {kind_phrase(row['kind'])}: only optimization runs can be resumed "
                         f"({'evaluate the policy again with codearcade eval' if row['kind'] == 'eval' else 'replay the original run again'})")
    config = OptimizeConfig.from_record(read_recorded(row["config"], run_id), run_id)

    def same(key: str) -> bool:  # the run's own value, given again (its command line repeated with --resume)
        mine, theirs = getattr(config, key, None), given[key]
        if key == "policy" and mine is not None and theirs is not None:
            return Path(mine).resolve() == Path(theirs).resolve()
        return mine == theirs

    fixed = sorted(k for k in given if k not in RESUME_OVERRIDES and not same(k))
    if fixed:
        flags = ", ".join(flag_of(OptimizeConfig, k) for k in fixed)
        raise ValueError(f"{flags} cannot change when resuming run {run_id}: they are part of its settings "
                         "(start a new run instead)")
    given = {k: v for k, v in given.items() if k in RESUME_OVERRIDES}
    if config.model == f"openai/{MODEL_ALIAS}" and not config.api_base or row["model"] == OFFLINE_MODEL_LABEL:
        config.model = None  # the offline model (runs made before its name was recorded as asked for)
    if given.get("iterations") is not None and given["iterations"] < config.iterations:
        raise ValueError(f"run {run_id} has {config.iterations} iterations planned; --iterations can only extend "
                         f"it, not shrink it")
    if "model" in given and "models" not in given:
        config.models = None  # one --model resumes an ensemble's run with that model alone
    for key, value in given.items():
        setattr(config, key, value)
    validate_config(config)
    if row["status"] == "finished" and done >= config.iterations + 1:
        return ResumePlan(run_id, config, row["status"], nothing_to_do=(
            f"run {run_id} is finished ({done - 1} of {config.iterations} iterations); nothing to do. "
            f"Give --iterations N (more than {config.iterations}) to extend it"))
    if done >= config.iterations + 1 and row["status"] == "failed" and _all_updates_failed(store, run_id):
        # every update's LLM call failed, and all its iterations are played: a resume plays the iterations still
        # to play, and there are none, so it would only fail again (a killed or budget-stopped run that played
        # them all is resumed to its end: its audit, its status)
        raise ValueError(f"run {run_id} failed after playing all {config.iterations} of its iterations"
                         f"{': ' + row['error'] if row['error'] else ''}; give --iterations N (more than "
                         f"{config.iterations}) to play more")
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
    validate_config(config)
    start = None
    if not resume:
        start = resolve_start(config)
    if resume:
        return _continue(config, store, client, resume, log, on_iteration, progress, rerun, waiting, resumed=True)
    with new_run(store, client) as made:
        run_id = made.start(config, client.label, extra=tags, start=start)
        return _continue(config, store, client, run_id, log, on_iteration, progress, rerun, waiting)


def _continue(config, store, client, run_id, log, on_iteration, progress, rerun, waiting,
              resumed: bool = False) -> OptimizeResult:
    """Run the loop on the run ``run_id``; a resumed one's settings that ``config`` changes are recorded first."""
    state = load_state(store, run_id)
    state.rerun = rerun
    if waiting is not None:
        state.waiting = waiting
    changed = {k: getattr(config, k) for k in RESUME_OVERRIDES
               if resumed and getattr(config, k) != getattr(state.config, k)}
    if changed.get("models"):
        changed["models"] = _priced(changed["models"])
    if changed:
        for key, value in changed.items():
            setattr(state.config, key, value)
        with store.write() as con:
            merge_run_config(con, run_id, changed)
    return run_loop(store, state, client, log, on_iteration, progress)
