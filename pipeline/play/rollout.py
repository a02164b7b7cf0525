"""One episode, played by the game host: the environment here, the policy behind a channel.

This is the trusted side of an episode (DESIGN.md, "the game host and the policy process"). The emulator,
OCAtari's objects, the game's observation builder, rewards, lives, the protocols, the step log and live Rerun
recordings all live in the process that runs :func:`play_episode`, where no policy code ever runs; the policy
answers each observation through a :class:`~pipeline.play.channels.PolicyChannel` (``pipeline/play/channels.py``:
a confined policy process, the normal case, or the policy in this very process with ``--workers 0``).

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

import random
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable

import numpy as np
import pyarrow as pa

from games import Game, get_game, list_widths
from pipeline.boundary.nodes import MalformedTrace, read_nodes
from pipeline.play.channels import LocalPolicy, PolicyChannel, PolicyFailed
from pipeline.play.spec import EpisodeSpec
from tracing.steps import StepLog

PROGRESS_EVERY = 250
"""Steps between progress callbacks."""


@dataclass
class EpisodeOutcome:
    """An episode's row for the ``episodes`` table, with its step and node rows."""

    episode: dict[str, Any]
    steps: pa.Table
    nodes: pa.Table | None = None
    printed: str | None = None
    """What the policy printed, when the spec asked (``EpisodeSpec.keep_printed``) and its process said."""
    recording: str | None = None
    """Why the episode's live Rerun recording (``EpisodeSpec.rerun``) was not made whole, in one line; None when
    it was, or none was asked for. The episode is stored either way; the command says this (a game host's own
    stderr goes nowhere)."""

    @property
    def end_reason(self) -> str:
        return self.episode["end_reason"]


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
    from games.envs import RESET_WITHOUT_SCREEN, discard_env, shared_env

    game = get_game(spec.game).observing(spec.observation)
    t0 = time.perf_counter()
    policy = policy if policy is not None else LocalPolicy(spec, game.n_actions)
    env = shared_env(game, sticky=spec.sticky, noop_max=spec.noop_max, one_life=spec.one_life)
    policy.begin_loading()  # a policy process loads it while the environment resets here
    try:  # an episode that logs no frames reads no screen: its reset may restore the state ALE's reset leads to
        obs, info = env.reset(seed=spec.seed, options=None if spec.logs_frames else RESET_WITHOUT_SCREEN)
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
    (``games.wrappers.EpisodicLife``: one NOOP, Breakout a FIRE, their rewards dropped), and the same policy, still
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
    recording = None  # why it could not start
    env_s = policy_s = 0.0

    if prepared.end_reason is None:
        env, obs, info = prepared.env, prepared.obs, prepared.info
        try:
            if spec.rerun:
                live, recording = _live_recorder(spec, env, steps)
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
    outcome = EpisodeOutcome(episode, step_table, nodes, policy.printed, recording)
    if live is not None:
        from viewers.rerun_live import finish_recorder

        outcome.recording = finish_recorder(live, episode, live_nodes if isinstance(live_nodes, pa.Table) else None)
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


def _live_recorder(spec: EpisodeSpec, env: Any, steps: StepLog) -> tuple[Any, str | None]:
    """The live Rerun recorder of ``spec.rerun`` (``viewers/rerun_live.py``), or None and why it cannot start.

    Rerun is imported here, in the process that plays the episode. The policy's RNG state is kept as it
    was, so an episode plays the same with and without a recording.
    """
    state, np_state = random.getstate(), np.random.get_state()
    try:
        from viewers.rerun_live import open_recorder

        return open_recorder(spec, env, steps)
    except Exception as exc:  # noqa: BLE001 - a viewer problem must never cost the episode (Rerun not importable)
        return None, f"{type(exc).__name__}: {exc}"
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

