"""One episode, played by the game host: the environment here, the policy behind a channel.

This is the trusted side of an episode (DESIGN.md, "the game host and the policy process"). The emulator,
OCAtari's objects, the game's observation builder, rewards, lives, the protocols, the step log and live Rerun
recordings all live in the process that runs :func:`play_episode`, where no policy code ever runs; the policy
answers each observation through a :class:`PolicyChannel`:

- :class:`RemotePolicy`: a confined policy process (``pipeline/boundary/policy.py``), one round trip per step
  over a socket; the normal case (``pipeline/play/episodes.py`` starts the host and the policy process as a pair);
- :class:`LocalPolicy`: the policy loaded in this very process (``--workers 0``: debugging, no isolation at all).

Every reward, score, life and step is therefore computed where the policy cannot reach: scores are right by
construction, and nothing is replayed to trust them. :func:`run_episode` is a pure function of an
:class:`EpisodeSpec` (primitives only, sent to the host as JSON: the policy travels as text), returning an
:class:`EpisodeOutcome` that holds the episode row and its steps and nodes as Arrow tables (a remote policy's node
rows stay the bytes it sent, checked by the parent: ``pipeline/play/episodes.py``); only the caller writes to the store.

Whatever the policy does, the episode ends with a recorded ``end_reason``:
``terminated`` (the game ended), ``truncated`` (``max_steps`` reached, or ALE's own limit),
``policy_error`` (the policy raised, returned an illegal action, or could not be loaded), ``timeout`` (a
policy call or the whole episode exceeded its time limit), or ``crashed`` (the policy process died or broke the
protocol; the steps before it are kept). When the policy failed on a step, that step is stored with ``action``
NULL: its observation is what the policy failed on, and its nodes show where.
"""

from __future__ import annotations

import json
import marshal
import math
import random
import socket
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable

import numpy as np
import pyarrow as pa

from games import Game, get_game, list_widths
from games.base import OBSERVATION_VERSION
from pipeline.boundary.nodes import MAX_NODE_FRAME, MalformedTrace, node_budget, read_nodes
from pipeline.boundary.policy import (ACTION, MAX_ANSWER, Channel, capped_error, coerce_action,
                                     describe_exception, printed_text)
from pipeline.play.runinfo import policy_rng_seed
from pipeline.settings import EpisodeLimits
from tracing.capture import NodeRecorder
from tracing.policy_file import PolicyLoadError, load_policy
from tracing.sandbox import CallTimer, PolicyTimeout
from tracing.steps import StepLog

PROGRESS_EVERY = 250
"""Steps between progress callbacks."""
ANSWER_GRACE_S = 1.0
"""How long past its call limit the host waits for the policy process's answer (its own timer reports a slow
call at the limit; this catches one that defeated the timer or hangs in C)."""
LOAD_TIMEOUT_S = 60.0
"""How long the policy process may take to load the policy."""
FINISH_TIMEOUT_S = 30.0
"""How long the policy process may take to send its node rows at the end."""


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
    max_steps: int = EpisodeLimits.max_steps
    sticky: float = 0.0
    noop_max: int = 0
    one_life: bool | str = False
    """End the episode at a lost life: ``True``, the first life of the game reset from ``seed``
    (``games.envs.OneLife``); ``"continue"``, the authors' protocol exactly (``games.envs.EpisodicLife``)."""
    continues: str | None = None
    """The episode whose game this one goes on with (``one_life="continue"``): it is played right after that one,
    by the same game host and policy process, from where it ended (one NOOP, Breakout a FIRE); None: it starts
    from ``reset(seed)``. ``seed`` is then the seed of the game."""
    observation: int = OBSERVATION_VERSION
    """The version of the observation conventions the run plays (``games.base.OBSERVATION_VERSION``)."""
    trace: bool = False
    """Record a node for every call of a bundled method (slower; steps are always recorded)."""
    trace_lines: bool = True
    """With ``trace``: record in each node the lines of the method that ran (``nodes.lines_run``)."""
    call_time_limit_s: float = EpisodeLimits.call_time_limit_s
    """Limit for one policy call, ``policy(obs)``, including every bundled method it calls."""
    episode_time_limit_s: float = EpisodeLimits.episode_time_limit_s
    """Wall-clock limit for the whole episode."""
    memory_limit_mb: int | None = EpisodeLimits.memory_limit_mb
    """Extra address space a worker process may take beyond what it had at start (None: unlimited)."""
    rerun: str | None = None
    """Live Rerun recording: a directory (``DIR/<episode_id>.rrd``) or a ``rerun+http://…/proxy`` URL; None: off.
    Rerun is imported only inside the process that plays the episode (``viewers/rerun_live.py``)."""
    rerun_frames_every: int = 4
    """With ``rerun``: log the screen every this many steps (0: no frames)."""
    keep_printed: bool = False
    """Keep what the policy prints to its stdout (its first ``policy.MAX_PRINTED_BYTES`` bytes) and return it with
    the outcome (:attr:`EpisodeOutcome.printed`, never stored with the episode); off: it goes to ``/dev/null``."""
    rng_key: str | None = None
    """The key of the run's random stream for policies (``runinfo.policy_rng_seed``): the policy process's
    generators are seeded from it and the game's seed, never with the game's seed itself. None: a run recorded
    before the key existed, whose policies' generators were seeded with the game's seed (kept, so it replays)."""

    @property
    def policy_seed(self) -> int:
        """The seed of the policy's ``random`` and NumPy generators in this episode."""
        return policy_rng_seed(self.rng_key, self.seed) if self.rng_key else self.seed


@dataclass
class EpisodeOutcome:
    """An episode's row for the ``episodes`` table, with its step and node rows."""

    episode: dict[str, Any]
    steps: pa.Table
    nodes: pa.Table | None = None
    printed: str | None = None
    """What the policy printed, when the spec asked (``EpisodeSpec.keep_printed``) and its process said."""

    @property
    def end_reason(self) -> str:
        return self.episode["end_reason"]


class PolicyFailed(Exception):
    """The policy could not give an action: ``end_reason`` (``policy_error``, ``timeout``, ``crashed``) and why."""

    def __init__(self, end_reason: str, error: str):
        super().__init__(error)
        self.end_reason, self.error = end_reason, error


class PolicyChannel:
    """How the host asks the policy for actions (see the module docstring)."""

    printed: str | None = None
    """What the policy printed in the episode :meth:`finish` ended (``EpisodeSpec.keep_printed``), or None."""

    def begin_loading(self) -> None:
        """Have the policy start loading, so that it loads while the host resets its environment (a policy process
        is another process); :meth:`start` then waits for it."""

    def start(self) -> None:
        """Load the policy, or wait until it is loaded (raises :class:`PolicyFailed`, e.g. for a policy file that
        does not load)."""

    def go(self, cpu: int | None, deadline: float = math.inf) -> None:
        """The episode begins (on ``cpu``, where the host now runs); its time is up at ``deadline``
        (``time.perf_counter()``)."""

    def act(self, obs: dict[str, Any]) -> int:
        """The policy's legal action for ``obs``; raises :class:`PolicyFailed`."""
        raise NotImplementedError

    def finish(self, more: bool = False, steps: int | None = None) -> Any:
        """The episode is over: the node rows (an Arrow table, the raw Arrow bytes of a remote policy, or None).
        ``more``: the next episode of the same game follows, played by the same policy (loaded, its state kept);
        ``steps``: the policy calls of the episode (its node rows' byte budget: ``nodes.node_budget``)."""
        return None


class LocalPolicy(PolicyChannel):
    """The policy in this process (``--workers 0``: for debugging; no isolation at all)."""

    def __init__(self, spec: "EpisodeSpec", n_actions: int) -> None:
        self.spec, self.n_actions = spec, n_actions
        self.recorder = NodeRecorder(lines=spec.trace_lines) if spec.trace else None
        self.timer = CallTimer()
        self.policy: Any = None

    def start(self) -> None:
        random.seed(self.spec.policy_seed)
        np.random.seed(self.spec.policy_seed % 2**32)
        try:
            self.policy = load_policy(self.spec.policy_text, self.spec.policy_name).policy
        except PolicyLoadError as exc:
            raise PolicyFailed("policy_error", str(exc)) from None
        self.timer.__enter__()
        if self.recorder is not None:
            self.recorder.__enter__()
        self.step = -1

    def act(self, obs: dict[str, Any]) -> int:
        self.step += 1
        if self.recorder is not None:
            self.recorder.begin_step(self.step, obs)
        try:
            return coerce_action(self.timer.call(self.spec.call_time_limit_s or math.inf, self.policy, obs),
                                 self.n_actions)
        except PolicyTimeout as exc:
            raise PolicyFailed("timeout", describe_exception(exc)) from None
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # noqa: BLE001 - untrusted code: anything, SystemExit too
            raise PolicyFailed("policy_error", describe_exception(exc)) from None

    def finish(self, more: bool = False, steps: int | None = None) -> Any:
        if self.policy is not None:
            self.timer.__exit__(None, None, None)
            if self.recorder is not None:
                self.recorder.__exit__(None, None, None)
        nodes = self.recorder.table() if self.recorder is not None else None
        if more and self.policy is not None:  # the next episode: a new node log, the same policy object
            self.timer.__enter__()
            if self.recorder is not None:
                self.recorder = NodeRecorder(lines=self.spec.trace_lines).__enter__()
            self.step = -1
        return nodes


class RemotePolicy(PolicyChannel):
    """The host's end of a confined policy process (``pipeline/boundary/policy.py``): one frame out and one back
    per step. Every answer is checked here: an action is a legal int, an error is capped text; a process that
    does not answer within its call limit (plus :data:`ANSWER_GRACE_S`), that sends anything else, or that dies,
    ends the episode (``timeout`` / ``crashed``) with the steps played so far."""

    def __init__(self, sock: socket.socket, spec: "EpisodeSpec", n_actions: int) -> None:
        self.channel = Channel(sock)
        self.spec, self.n_actions = spec, n_actions
        self.limit = (spec.call_time_limit_s or math.inf) + ANSWER_GRACE_S
        self.loading = False
        """The start message is sent (:meth:`begin_loading`)."""
        self.deadline = math.inf
        """When the episode's time is up (``time.perf_counter()``; :meth:`go`): no answer is awaited past it (plus
        :data:`ANSWER_GRACE_S`), so the host ends the episode itself, its steps kept, before the parent's kill."""
        self.broken = False
        """The stream is past use (no whole answer in time, a frame over its limit, the process gone): nothing more
        is read from it, not even the node rows at the end (what is left of a frame trickled a byte at a time would
        be read as the next)."""

    def _receive(self, timeout: float, what: str) -> tuple[bytes, bytes]:
        """The next answer, whole within ``timeout`` seconds (the frame's deadline, not each read's)."""
        timeout = None if math.isinf(timeout) else timeout
        try:
            return self.channel.receive(MAX_ANSWER, within=timeout)
        except TimeoutError:
            self.broken = True
            raise PolicyFailed("timeout", f"the policy process did not answer {what} within {timeout:.3g} s") from None
        except EOFError:
            self.broken = True
            raise PolicyFailed("crashed", f"the policy process ended {what}") from None
        except (OSError, ValueError) as exc:
            self.broken = True
            raise PolicyFailed("crashed", f"the policy process broke the protocol {what}: {exc}") from None

    def _failure(self, payload: bytes, what: str) -> PolicyFailed:
        try:
            message = json.loads(payload)
            reason, error = message["end_reason"], message["error"]
        except (ValueError, KeyError, TypeError, RecursionError):
            return PolicyFailed("crashed", f"the policy process sent a malformed message {what}")
        if message.get("kind") != "failed" or reason not in ("policy_error", "timeout") or not isinstance(error, str):
            return PolicyFailed("crashed", f"the policy process sent a malformed message {what}")
        return PolicyFailed(reason, capped_error(error))

    def begin_loading(self) -> None:
        spec = self.spec
        self.channel.send_json({
            "op": "start", "policy_text": spec.policy_text, "policy_name": spec.policy_name, "seed": spec.policy_seed,
            "trace": spec.trace, "trace_lines": spec.trace_lines, "call_time_limit_s": spec.call_time_limit_s,
            "n_actions": self.n_actions, "keep_printed": spec.keep_printed})
        self.loading = True

    def start(self) -> None:
        if not self.loading:
            self.begin_loading()
        kind, payload = self._receive(LOAD_TIMEOUT_S, "while loading the policy")
        if kind == b"J" and payload == b'{"kind":"ready"}':
            return
        raise self._failure(payload, "while loading the policy") if kind == b"J" else \
            PolicyFailed("crashed", "the policy process sent a malformed message while loading the policy")

    def go(self, cpu: int | None, deadline: float = math.inf) -> None:
        self.deadline = deadline
        self.channel.send_json({"op": "go", "cpu": cpu})

    def act(self, obs: dict[str, Any]) -> int:
        try:
            self.channel.send(b"O", marshal.dumps(obs))
        except OSError:
            raise PolicyFailed("crashed", "the policy process ended before the step") from None
        limit, what = self.limit, "at this step"
        left = self.deadline - time.perf_counter()
        if left + ANSWER_GRACE_S < limit:  # the episode's time is up first
            limit, what = max(left, 0.0) + ANSWER_GRACE_S, "at this step (the episode's time limit came first)"
        kind, payload = self._receive(limit, what)
        if kind == b"a" and len(payload) == ACTION.size:
            (action,) = ACTION.unpack(payload)
            if 0 <= action < self.n_actions:
                return action
            raise PolicyFailed("crashed", f"the policy process sent an illegal action {action}")
        raise self._failure(payload, "at this step") if kind == b"J" else \
            PolicyFailed("crashed", "the policy process sent a frame of an unknown kind")

    def close(self) -> None:
        """Let the policy process go (a game host that plays another episode next must not keep its socket)."""
        self.channel.sock.close()

    def finish(self, more: bool = False, steps: int | None = None) -> bytes | None:
        """The node rows as the policy process sent them (an Arrow stream of at most the episode's byte budget,
        :func:`~pipeline.boundary.nodes.node_budget` of ``steps``, read and checked by the parent), or None.
        :class:`PolicyFailed` (``policy_error``, a malformed trace) for node rows the episode did not ask for
        (refused unread) or a node frame over the limit (refused at its header). None at once when the stream is
        :attr:`broken` (the host timed the process out: waiting for its node rows would only let it hold the
        host longer)."""
        self.printed = None
        if self.broken:
            return None
        try:
            self.channel.send_json({"op": "end", "more": more})
            kind, payload = self._receive(FINISH_TIMEOUT_S, "at the end")
            message = json.loads(payload) if kind == b"J" else None
            if self.spec.keep_printed and isinstance(message, dict) and message.get("kind") == "done":
                self.printed = printed_text(message)
            if not isinstance(message, dict) or message.get("kind") != "done" or message.get("nodes") is not True:
                return None
        except (PolicyFailed, OSError, ValueError, RecursionError):
            return None  # the steps are the host's: an episode without its node rows is still an episode
        if not self.spec.trace:
            raise PolicyFailed("policy_error", "malformed trace: node rows for an episode that is not traced")
        try:
            budget = MAX_NODE_FRAME if steps is None else node_budget(steps)
            kind, payload = self.channel.receive(budget, within=FINISH_TIMEOUT_S)
        except ValueError as exc:  # over the episode's byte budget, refused at the header
            raise PolicyFailed("policy_error", f"malformed trace: a node frame over the episode's budget ({exc})") \
                from None
        except (OSError, EOFError):
            return None
        return payload if kind == b"A" else None


def _report(steps: StepLog, reported: int, length: int, progress: Callable[[int], None] | None) -> int:
    """Tell the caller how far the episode is; the new mark."""
    if progress is not None and length > reported:
        progress(length)
    return length


@dataclass
class PreparedEpisode:
    """An episode ready for its first step (:func:`prepare_episode`): environment reset, policy loaded (or the
    reason it did not load)."""

    spec: EpisodeSpec
    game: Game
    policy: PolicyChannel
    env: Any | None
    obs: Any
    info: dict[str, Any]
    end_reason: str | None
    error: str | None
    prepare_s: float
    """Seconds the preparation took; they count in the episode's duration and against its time limit."""


def prepare_episode(spec: EpisodeSpec, policy: PolicyChannel | None = None) -> PreparedEpisode:
    """Everything before the first step: reset the environment (a few ms; with sticky actions ALE's seeded reset
    reloads the ROM, ~0.15 s, as long as 150 steps) and have the policy loaded. A staged host
    (``pipeline/boundary/zygote.py``) does this while the previous episode still plays; it then waits for its
    go-ahead. ``policy`` defaults to a :class:`LocalPolicy`."""
    # imported here, not with this module: the parent of an eval imports it and needs no emulator (gymnasium, ALE and
    # OCAtari are ~0.6 s of imports); the game zygote imports them when it prepares the environments, before any
    # host forks
    from games.envs import discard_env, shared_env

    game = get_game(spec.game).observing(spec.observation)
    t0 = time.perf_counter()
    policy = policy if policy is not None else LocalPolicy(spec, game.n_actions)
    env = shared_env(game, sticky=spec.sticky, noop_max=spec.noop_max, one_life=spec.one_life)
    policy.begin_loading()  # a policy process loads it while the environment resets here
    try:
        obs, info = env.reset(seed=spec.seed)
    except BaseException:
        discard_env(env)  # a failed reset leaves the environment in an unknown state
        raise
    try:
        policy.start()
    except PolicyFailed as exc:
        return PreparedEpisode(spec, game, policy, None, None, {}, exc.end_reason, exc.error,
                               time.perf_counter() - t0)
    return PreparedEpisode(spec, game, policy, env, obs, info, None, None, time.perf_counter() - t0)


def continue_episode(spec: EpisodeSpec, previous: PreparedEpisode) -> PreparedEpisode:
    """The next episode of a continued game (``spec.continues``, after ``previous`` was played to its end by the
    game or the step cap): the same environment, reset without a seed, which goes on with the game
    (``games.envs.EpisodicLife``: one NOOP, Breakout a FIRE, their rewards dropped), and the same policy, still
    loaded with whatever state it kept."""
    from games.envs import discard_env

    t0 = time.perf_counter()
    env = previous.env
    try:
        obs, info = env.reset()
    except BaseException:
        discard_env(env)
        raise
    return PreparedEpisode(spec, previous.game, previous.policy, env, obs, info, None, None, time.perf_counter() - t0)


def run_episode(spec: EpisodeSpec, progress: Callable[[int], None] | None = None) -> EpisodeOutcome:
    """Play one episode as ``spec`` says, the policy in this process (``--workers 0``), and return what happened
    (never raises for policy misbehaviour). ``progress(steps)`` is called every :data:`PROGRESS_EVERY` steps and
    at the end."""
    return play_episode(prepare_episode(spec), progress)


def play_episode(prepared: PreparedEpisode, progress: Callable[[int], None] | None = None,
                 cpu: int | None = None, more: bool = False) -> EpisodeOutcome:
    """Play a :func:`prepare_episode`'d episode to its end (see :func:`run_episode`); ``cpu``: where this host
    runs, passed on to the policy process; ``more``: the next episode of the same game follows with the same
    policy (unless this one ends by the policy's failure)."""
    spec, game, policy = prepared.spec, prepared.game, prepared.policy
    started_at = time.time() - prepared.prepare_s
    t0 = time.perf_counter() - prepared.prepare_s  # the preparation counts, a staged host's wait does not
    steps = StepLog(list_widths(game), *game.hot_keys)
    end_reason, error = prepared.end_reason or "truncated", prepared.error
    score, lives_lost, length = 0.0, 0, 0
    reported = 0
    live = None  # live Rerun recorder (spec.rerun)
    env_s = policy_s = 0.0

    if prepared.end_reason is None:
        env, obs, info = prepared.env, prepared.obs, prepared.info
        try:
            if spec.rerun:
                live = _live_recorder(spec, env, steps)
            deadline = t0 + spec.episode_time_limit_s
            policy.go(cpu, deadline)
            lives = info.get("lives", 0)
            for step in range(spec.max_steps):
                now = time.perf_counter()
                if now >= deadline:
                    end_reason = "timeout"
                    error = f"episode exceeded its time limit of {spec.episode_time_limit_s:g} s"
                    break
                steps.observe(obs, getattr(env, "object_rows", None))
                if live is not None:
                    live.observe(step)
                try:
                    action = policy.act(obs)
                except PolicyFailed as exc:
                    policy_s += time.perf_counter() - now
                    end_reason, error = exc.end_reason, exc.error
                    steps.outcome(step, None, 0.0, score, False, False, lives)
                    break
                after_policy = time.perf_counter()
                policy_s += after_policy - now
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
                    reported = _report(steps, reported, length, progress)
                if terminated or truncated:
                    end_reason = "terminated" if terminated else "truncated"
                    break
            else:
                end_reason = "truncated"
        except BaseException:
            from games.envs import discard_env

            discard_env(env)  # an error inside the loop leaves the environment in an unknown state
            raise
    try:
        nodes = policy.finish(more=more and end_reason in GAME_END_REASONS, steps=len(steps))
    except PolicyFailed as exc:  # node rows the episode did not ask for, or too many bytes of them
        nodes = None
        if end_reason in GAME_END_REASONS:
            end_reason, error = exc.end_reason, exc.error
    _report(steps, reported, length, progress)
    step_table = steps.table()
    duration_s = time.perf_counter() - t0
    live_nodes = nodes
    if live is not None and isinstance(nodes, bytes):
        # the recording shows the node rows: read as the parent reads them, within bounds, every field checked
        try:
            live_nodes = read_nodes(nodes, spec, step_table.num_rows, duration_s)
        except MalformedTrace as exc:
            live_nodes = nodes = None
            if end_reason in GAME_END_REASONS:
                end_reason, error = "policy_error", str(exc)

    episode = _episode_row(
        spec, game=game.name, started_at=_utc(started_at), duration_s=duration_s, env_s=env_s,
        policy_s=policy_s, length=length, lives_lost=lives_lost, end_reason=end_reason, error=error, score=score,
    )
    outcome = EpisodeOutcome(episode, step_table, nodes, policy.printed)
    if live is not None:
        from viewers.rerun_live import finish_recorder

        finish_recorder(live, episode, live_nodes if isinstance(live_nodes, pa.Table) else None)
    return outcome


GAME_END_REASONS = ("terminated", "truncated")
"""End reasons after which a continued game goes on (the others are the policy's failures)."""


def run_game(specs: list[EpisodeSpec], progress: Callable[[int], None] | None = None) -> list[EpisodeOutcome]:
    """Play the episodes of one continued game, the policy in this process (``--workers 0``); see
    :func:`play_game`."""
    return play_game(specs, prepare_episode(specs[0]), progress)


def play_game(specs: list[EpisodeSpec], first: PreparedEpisode, progress: Callable[[int], None] | None = None,
              cpu: int | None = None) -> list[EpisodeOutcome]:
    """Play ``specs``, the episodes of one game in order (each after the first ``continues`` the one before it),
    from the :func:`prepare_episode`'d first, with one environment and one policy that keeps its state from one
    episode to the next (the authors' evaluation calls one policy object throughout). ``progress(steps)``: the
    steps of the whole game so far. An episode that ends by the policy's failure ends the game: the episodes
    after it are not played (length 0, the same end reason, an error that says so)."""
    outcomes: list[EpisodeOutcome] = []
    played = 0
    prepared = first
    for k, spec in enumerate(specs):
        if k:
            prepared = continue_episode(spec, prepared)
        outcome = play_episode(prepared, (lambda n, base=played: progress(base + n)) if progress else None, cpu,
                               more=k + 1 < len(specs))
        outcome.episode["start_step"] = played
        outcomes.append(outcome)
        played += outcome.episode["length"]
        if outcome.end_reason not in GAME_END_REASONS:
            for rest in specs[k + 1:]:
                outcomes.append(not_played(rest, spec, outcome.end_reason, played))
            break
    return outcomes


def not_played(spec: EpisodeSpec, failed: EpisodeSpec, end_reason: str, start_step: int) -> EpisodeOutcome:
    """The outcome of an episode of a continued game that was not played because ``failed``, an earlier episode
    of it, ended by the policy's failure (``end_reason``)."""
    episode = _episode_row(spec, game=spec.game, started_at=None, duration_s=0.0, env_s=None, policy_s=None,
                           length=0, lives_lost=0, end_reason=end_reason, score=0.0, start_step=start_step,
                           error=f"not played: episode {failed.index} of this game ended with {end_reason}")
    return EpisodeOutcome(episode, StepLog().table(), None)


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
        max_steps=spec.max_steps, traced=spec.trace, sticky=spec.sticky, noop_max=spec.noop_max,
        continues=spec.continues, start_step=0,
    )
    row.update(measured)
    row["return"] = score  # a Python keyword, hence not a keyword argument
    return row


def crashed_outcome(spec: EpisodeSpec, error: str, duration_s: float = 0.0) -> EpisodeOutcome:
    """The outcome recorded for an episode whose worker died or was killed before reporting."""
    episode = _episode_row(spec, game=spec.game, started_at=None, duration_s=duration_s, env_s=None, policy_s=None,
                           length=0, lives_lost=0, end_reason="crashed", error=error, score=0.0)
    return EpisodeOutcome(episode, StepLog().table(), None)


def _utc(epoch: float) -> datetime:
    return datetime.fromtimestamp(epoch, timezone.utc).replace(tzinfo=None)

