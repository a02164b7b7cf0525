"""One episode of a policy in an environment, captured step by step (and call by call when traced).

:func:`run_episode` is a pure function of an :class:`EpisodeSpec` (primitives only, sent to a worker as JSON: the
policy travels as text), returning an :class:`EpisodeOutcome` that holds the episode row and its steps and nodes
as Arrow tables. It runs in a confined worker process (``pipeline/boundary/workers.py``, which sends the outcome back as
JSON and Arrow IPC) or, for debugging, in-process; only the caller writes to the store.

Whatever the policy does, the episode ends with a recorded ``end_reason``:
``terminated`` (the game ended), ``truncated`` (``max_steps`` reached, or ALE's own limit),
``policy_error`` (the policy raised, returned an illegal action, or could not be loaded), ``timeout`` (a
policy call or the whole episode exceeded its time limit), or ``crashed`` (set by the executor when the worker
process died or sent a malformed answer). When the policy failed on a step, that step is stored with ``action`` NULL: its observation
is what the policy failed on, and its nodes show where.
"""

from __future__ import annotations

import math
import operator
import random
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable

import numpy as np
import pyarrow as pa

from games import Game, get_game, list_widths
from games.base import OBSERVATION_VERSION
from games.envs import discard_env, shared_env
from tracing.capture import NodeRecorder, failing_policy_line
from tracing.policy_file import PolicyLoadError, load_policy
from tracing.sandbox import CallTimer, PolicyTimeout
from tracing.steps import StepLog

PROGRESS_EVERY = 250
"""Steps between progress callbacks."""


@dataclass
class EpisodeSpec:
    """Everything needed to play one episode; every field a primitive, so that it crosses to a worker as JSON."""

    episode_id: str
    run_id: str
    game: str
    policy_text: str
    policy_version_id: str
    policy_name: str = "policy.py"
    iteration: int = 0
    kind: str = "eval"
    """``eval`` (evaluation episode) or ``train`` (traced training rollout of the optimizer)."""
    index: int = 0
    seed: int = 0
    max_steps: int = 4000
    sticky: float = 0.0
    noop_max: int = 0
    one_life: bool = False
    """End the episode at the first lost life (the authors' follow-up evaluation: ``games.envs.OneLife``)."""
    observation: int = OBSERVATION_VERSION
    """The version of the observation conventions the run plays (``games.base.OBSERVATION_VERSION``)."""
    trace: bool = False
    """Record a node for every call of a bundled method (slower; steps are always recorded)."""
    trace_lines: bool = True
    """With ``trace``: record in each node the lines of the method that ran (``nodes.lines_run``)."""
    call_time_limit_s: float = 1.0
    """Limit for one policy call, ``policy(obs)``, including every bundled method it calls."""
    episode_time_limit_s: float = 900.0
    """Wall-clock limit for the whole episode."""
    memory_limit_mb: int | None = 4096
    """Extra address space a worker process may take beyond what it had at start (None: unlimited)."""
    rerun: str | None = None
    """Live Rerun recording: a directory (``DIR/<episode_id>.rrd``) or a ``rerun+http://…/proxy`` URL; None: off.
    Rerun is imported only inside the process that plays the episode (``viewers/rerun_live.py``)."""
    rerun_frames_every: int = 4
    """With ``rerun``: log the screen every this many steps (0: no frames)."""


@dataclass
class EpisodeOutcome:
    """An episode's row for the ``episodes`` table, with its step and node rows."""

    episode: dict[str, Any]
    steps: pa.Table
    nodes: pa.Table | None = None

    @property
    def end_reason(self) -> str:
        return self.episode["end_reason"]


def coerce_action(action: Any, n_actions: int) -> int:
    """The policy's return value as a legal action index, or ValueError saying why it is not one."""
    if isinstance(action, (bool, np.bool_)):
        raise ValueError(f"illegal action {action!r}: expected an int in 0..{n_actions - 1}, got a bool")
    try:
        index = operator.index(action)
    except TypeError:
        raise ValueError(
            f"illegal action {action!r}: expected an int in 0..{n_actions - 1}, got {type(action).__name__}"
        ) from None
    if not 0 <= index < n_actions:
        raise ValueError(f"illegal action {index}: legal actions are 0..{n_actions - 1}")
    return index


def describe_exception(exc: BaseException) -> str:
    """One line: the exception, and the innermost line of policy code it came from."""
    line, text = failing_policy_line(exc)
    where = f" at line {line}: `{text}`" if line and text else (f" at line {line}" if line else "")
    return f"{type(exc).__name__}: {exc}{where}"


def _report(steps: StepLog, reported: int, length: int, progress: Callable[[int], None] | None,
            on_actions: Callable[[list[int]], None] | None) -> int:
    """Tell the caller how far the episode is (and which actions it played since last time); the new mark."""
    if on_actions is not None and length > reported:
        on_actions([a for a in steps.scalars["action"][reported:length] if a is not None])
    if progress is not None:
        progress(length)
    return length


@dataclass
class PreparedEpisode:
    """An episode ready for its first step (:func:`prepare_episode`): RNGs seeded, policy loaded (or the reason it
    did not load), environment reset."""

    spec: EpisodeSpec
    game: Game
    policy: Any | None
    env: Any | None
    obs: Any
    info: dict[str, Any]
    end_reason: str | None
    error: str | None
    prepare_s: float
    """Seconds the preparation took; they count in the episode's duration and against its time limit."""


def prepare_episode(spec: EpisodeSpec) -> PreparedEpisode:
    """Everything before the first step: seed the RNGs, load the policy, reset the environment (ALE's seeded
    reset reloads the ROM: ~0.1 s, as long as a few hundred steps). A staged worker (``pipeline/boundary/zygote.py``) does
    this, confined, while the previous episode still plays; it then waits for its go-ahead."""
    game = get_game(spec.game).observing(spec.observation)
    t0 = time.perf_counter()
    random.seed(spec.seed)
    np.random.seed(spec.seed % 2**32)
    try:
        policy = load_policy(spec.policy_text, spec.policy_name).policy
    except PolicyLoadError as exc:
        return PreparedEpisode(spec, game, None, None, None, {}, "policy_error", str(exc), time.perf_counter() - t0)
    env = shared_env(game, sticky=spec.sticky, noop_max=spec.noop_max, one_life=spec.one_life)
    try:
        obs, info = env.reset(seed=spec.seed)
    except BaseException:
        discard_env(env)  # a failed reset leaves the environment in an unknown state
        raise
    return PreparedEpisode(spec, game, policy, env, obs, info, None, None, time.perf_counter() - t0)


def run_episode(spec: EpisodeSpec, progress: Callable[[int], None] | None = None,
                on_actions: Callable[[list[int]], None] | None = None) -> EpisodeOutcome:
    """Play one episode as ``spec`` says and return what happened (never raises for policy misbehaviour).

    ``progress(steps)`` is called every :data:`PROGRESS_EVERY` steps and at the end; ``on_actions(actions)``
    just before it with the actions played since its last call (the parent verifies the score while the
    episode plays: ``pipeline/play/verify.py``)."""
    return play_episode(prepare_episode(spec), progress, on_actions)


def play_episode(prepared: PreparedEpisode, progress: Callable[[int], None] | None = None,
                 on_actions: Callable[[list[int]], None] | None = None) -> EpisodeOutcome:
    """Play a :func:`prepare_episode`'d episode to its end (see :func:`run_episode`)."""
    spec, game = prepared.spec, prepared.game
    started_at = time.time() - prepared.prepare_s
    t0 = time.perf_counter() - prepared.prepare_s  # the preparation counts, a staged worker's wait does not
    steps = StepLog(list_widths(game), *game.hot_keys)
    recorder = NodeRecorder(lines=spec.trace_lines) if spec.trace else None
    end_reason, error = prepared.end_reason or "truncated", prepared.error
    score, lives_lost, length = 0.0, 0, 0
    reported = 0  # steps whose actions went to on_actions
    live = None  # live Rerun recorder (spec.rerun)
    env_s = policy_s = 0.0

    if prepared.policy is not None:
        policy, env, obs, info = prepared.policy, prepared.env, prepared.obs, prepared.info
        try:
            if spec.rerun:
                live = _live_recorder(spec, env, steps)
            lives = info.get("lives", 0)
            deadline = t0 + spec.episode_time_limit_s
            with CallTimer() as timer, (recorder if recorder is not None else nullcontext()):
                for step in range(spec.max_steps):
                    now = time.perf_counter()
                    if now >= deadline:
                        end_reason = "timeout"
                        error = f"episode exceeded its time limit of {spec.episode_time_limit_s:g} s"
                        break
                    # before the policy: a policy that mutates obs cannot alter the record
                    steps.observe(obs, getattr(env, "object_rows", None))
                    if live is not None:
                        live.observe(step)
                    if recorder is not None:
                        recorder.begin_step(step, obs)
                    end_reason = None
                    try:
                        timer.arm(min(spec.call_time_limit_s or math.inf, deadline - now))
                        try:
                            raw_action = policy(obs)
                        finally:
                            timer.disarm()
                        action = coerce_action(raw_action, game.n_actions)
                    except PolicyTimeout as exc:
                        end_reason, error = "timeout", describe_exception(exc)
                    except KeyboardInterrupt:
                        raise
                    except BaseException as exc:  # noqa: BLE001 - untrusted code: anything, SystemExit too
                        end_reason, error = "policy_error", describe_exception(exc)
                    after_policy = time.perf_counter()
                    policy_s += after_policy - now
                    if end_reason is not None:
                        steps.outcome(step, None, 0.0, score, False, False, lives)
                        break
                    obs, reward, terminated, truncated, info = env.step(action)
                    env_s += time.perf_counter() - after_policy
                    score += float(reward)
                    steps.outcome(step, action, float(reward), score, bool(terminated), bool(truncated), lives)
                    new_lives = info.get("lives", lives)
                    if game.lives:
                        lives_lost += max(0, lives - new_lives)
                    elif reward < 0:
                        lives_lost += 1  # points conceded, for games without lives
                    lives = new_lives
                    length = step + 1
                    if length % PROGRESS_EVERY == 0:
                        reported = _report(steps, reported, length, progress, on_actions)
                    if terminated or truncated:
                        end_reason = "terminated" if terminated else "truncated"
                        break
                else:
                    end_reason = "truncated"
        except BaseException:
            discard_env(env)  # an error inside the loop leaves the environment in an unknown state
            raise
    _report(steps, reported, length, progress, on_actions)

    episode = _episode_row(
        spec, game=game.name, started_at=_utc(started_at), duration_s=time.perf_counter() - t0, env_s=env_s,
        policy_s=policy_s, length=length, lives_lost=lives_lost, end_reason=end_reason, error=error, score=score,
    )
    outcome = EpisodeOutcome(episode, steps.table(), recorder.table() if recorder is not None else None)
    if live is not None:
        from viewers.rerun_live import finish_recorder

        finish_recorder(live, episode, outcome.nodes)
    return outcome


def _live_recorder(spec: EpisodeSpec, env: Any, steps: StepLog) -> Any:
    """The live Rerun recorder of ``spec.rerun`` (``viewers/rerun_live.py``), or None if it cannot start.

    Rerun is imported here, in the process that plays the episode. The policy's RNG state is kept as it
    was, so an episode plays the same with and without a recording.
    """
    state, np_state = random.getstate(), np.random.get_state()
    try:
        from viewers.rerun_live import open_recorder

        return open_recorder(spec, env, steps)
    except Exception as exc:  # noqa: BLE001 - a viewer problem must never cost the episode
        print(f"codearcade: no Rerun recording for {spec.episode_id}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return None
    finally:
        random.setstate(state)
        np.random.set_state(np_state)


def _episode_row(spec: EpisodeSpec, score: float, **measured: Any) -> dict[str, Any]:
    """The ``episodes`` row: what the spec says, plus what was measured."""
    row = dict(
        episode_id=spec.episode_id, run_id=spec.run_id, iteration=spec.iteration, kind=spec.kind,
        episode_index=spec.index, seed=spec.seed, policy_version_id=spec.policy_version_id,
        max_steps=spec.max_steps, traced=spec.trace, sticky=spec.sticky, noop_max=spec.noop_max, **measured,
    )
    row["return"] = score  # a Python keyword, hence not a keyword argument
    return row


def crashed_outcome(spec: EpisodeSpec, error: str, duration_s: float = 0.0) -> EpisodeOutcome:
    """The outcome recorded for an episode whose worker died or was killed before reporting."""
    episode = _episode_row(spec, game=spec.game, started_at=None, duration_s=duration_s, env_s=None, policy_s=None,
                           length=0, lives_lost=0, end_reason="crashed", error=error, score=0.0)
    return EpisodeOutcome(episode, StepLog().table(), None)


def _utc(epoch: float) -> datetime:
    return datetime.fromtimestamp(epoch, timezone.utc).replace(tzinfo=None)
