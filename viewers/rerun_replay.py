"""Rebuild an episode's Rerun recording from the store, regenerating its frames by replaying its actions.

The store holds every step's objects, action, reward and score, and (for traced episodes) every bundled
call, but no pixels. Episodes are deterministic given the game, seed, sticky-action probability and
``noop_max`` (they seed the environment's RNG at reset), so replaying the stored actions in a fresh
``make_env`` reproduces the screens (an episode that continues a game, under the authors' one-life protocol,
after the actions of the episodes before it: ``store.showing.lead_in_actions``). The replay is checked: the objects it observes at each step are
compared with the stored ones, and :class:`ReplayCheck` says how many steps differed (0 when the frames are
faithful). Frames are optional (``frames_every=0``: no replay at all) and taken every K-th step.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import duckdb
import pyarrow as pa
import rerun as rr

from games import get_game, list_widths
from games.base import ONE_LIFE_CONTINUE, OBSERVATION_VERSION, recorded_observation
from games.envs import make_env
from games.wrappers import may_predate_serve_again
from store import Store
from store.readers import get_run, policy_text
from store.recorded import read_recorded, unreadable_settings
from store.showing import episode_tables, lead_in_actions
from tracing.steps import objects_to_obs
from viewers.frames import FrameEncoder
from viewers.rerun_episode import EpisodeLogger
from viewers.rerun_recording import new_recording, resolve_recording
from viewers.rerun_steps import StepColumns

CHUNK_STEPS = 2000
"""Steps per ``send_columns`` chunk when logging a stored episode."""


@dataclass
class ReplayCheck:
    """How faithfully replaying the stored actions reproduced the stored observations."""

    steps_compared: int = 0
    mismatched_steps: int = 0
    first_mismatch: int | None = None

    @property
    def faithful(self) -> bool:
        return self.mismatched_steps == 0

    def describe(self) -> str:
        if self.steps_compared == 0:
            return "no frames replayed"
        if self.faithful:
            steps = "the one step" if self.steps_compared == 1 else f"all {self.steps_compared} steps"
            return f"replayed frames match the stored objects on {steps}"
        return (f"replayed objects differ from the stored ones on {self.mismatched_steps} of {self.steps_compared} "
                f"steps (first at step {self.first_mismatch}): the frames after it may not show what was played")


@dataclass
class StoredEpisode:
    episode: dict[str, Any]
    steps: pa.Table
    nodes: pa.Table
    policy_text: str | None
    observation: int = OBSERVATION_VERSION
    """The version of the observation conventions its run played (``games.base.OBSERVATION_VERSION``)."""
    lead_in: list[list[int]] = field(default_factory=list)
    """The actions of the episodes it continues, in order (``store.showing.lead_in_actions``)."""


def read_episode(con: duckdb.DuckDBPyConnection, episode_id: str) -> StoredEpisode:
    """The episode row, its steps and nodes (Arrow) and the policy file it played."""
    episode, steps, nodes = episode_tables(con, episode_id)
    try:
        text = policy_text(con, episode["run_id"], episode["policy_version_id"])
    except KeyError:
        text = None
    run = get_run(con, episode["run_id"])
    # a store is anyone's file: settings that do not read are one line naming the run
    config = read_recorded(run["config"], run["run_id"]) if run else {}
    try:
        observation = recorded_observation(config)
    except ValueError as exc:
        raise unreadable_settings(run["run_id"], str(exc)) from None
    return StoredEpisode(episode, steps, nodes, text, observation, lead_in_actions(con, episode_id))


def replay_frames(episode: dict[str, Any], steps: pa.Table, every: int, observation: int = OBSERVATION_VERSION,
                  lead_in: list[list[int]] = ()) -> tuple[list[int], list[bytes], ReplayCheck]:
    """Replay the stored actions; PNG frames of every ``every``-th step, and the check against stored objects
    (both built with the run's ``observation`` version). An episode that ``continues`` a game is replayed after
    ``lead_in``, the actions of the episodes before it, each followed by the reset that goes on with the game."""
    if every <= 0 or steps.num_rows == 0:
        return [], [], ReplayCheck()
    game = get_game(episode["game"]).observing(observation)
    replayed = _replay(game, episode, steps, every, lead_in, serve_again=True)
    if not replayed[2].faithful and may_predate_serve_again(game, float(episode.get("sticky") or 0.0)):
        before = _replay(game, episode, steps, every, lead_in, serve_again=False)
        if before[2].faithful:
            return before
    return replayed


def _replay(game: Any, episode: dict[str, Any], steps: pa.Table, every: int, lead_in: list[list[int]],
            serve_again: bool) -> tuple[list[int], list[bytes], ReplayCheck]:
    check = ReplayCheck()
    frame_steps: list[int] = []
    pngs: list[bytes] = []
    widths = list_widths(game)
    env = make_env(game, sticky=float(episode.get("sticky") or 0.0), noop_max=int(episode.get("noop_max") or 0),
                   one_life=ONE_LIFE_CONTINUE if episode.get("continues") else False, serve_again=serve_again)
    try:
        obs, _ = env.reset(seed=int(episode["seed"]))
        for actions in lead_in if episode.get("continues") else ():
            for action in actions:
                env.step(action)
            obs, _ = env.reset()
        encoder = FrameEncoder(env.unwrapped.ale)
        for step, action, lives, objects in zip(steps.column("step").to_pylist(), steps.column("action").to_pylist(),
                                                steps.column("lives").to_pylist(), steps.column("objects").to_pylist()):
            check.steps_compared += 1
            stored = objects_to_obs(objects, widths)
            if game.derive is not None:  # the environment's observation has the game's derived fields
                game.derive(stored, lives)
            if obs != stored:
                check.mismatched_steps += 1
                if check.first_mismatch is None:
                    check.first_mismatch = step
            if step % every == 0:
                frame_steps.append(step)
                pngs.append(encoder.screen_png())
            if action is None:
                break
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                obs = None  # no further stored step should exist; if one does, it mismatches
    finally:
        env.close()
    return frame_steps, pngs, check


def log_stored_episode(data: StoredEpisode, recording: rr.RecordingStream | None = None,
                       frames_every: int = 0) -> ReplayCheck:
    """Log a stored episode into ``recording`` (or the ambient one), frames regenerated every K-th step."""
    frame_steps, pngs, check = replay_frames(data.episode, data.steps, frames_every, data.observation, data.lead_in)
    logger = EpisodeLogger(resolve_recording(recording), traced=bool(data.episode.get("traced")),
                           frames_every=frames_every if frame_steps else 0)
    if data.policy_text is not None:
        logger.code(data.policy_text)
    for start in range(0, data.steps.num_rows, CHUNK_STEPS):
        logger.steps(StepColumns.from_table(data.steps.slice(start, CHUNK_STEPS)))
    logger.frames(frame_steps, pngs)
    logger.nodes(data.nodes)
    logger.properties(data.episode, frames_every if frame_steps else 0)
    logger.send_blueprint()
    return check


def episode_recording(store: Store, episode_id: str, frames_every: int = 0,
                      recording: rr.RecordingStream | None = None) -> tuple[rr.RecordingStream, ReplayCheck]:
    """Rebuild an episode's recording from ``store``; a new stream (recording id = the episode id) unless given.

    The caller attaches a sink first or afterwards (``save``, ``connect_grpc``, ``spawn``): a new stream
    buffers what is logged until then.
    """
    with store.read() as con:
        data = read_episode(con, episode_id)
    rec = recording if recording is not None else new_recording(episode_id)
    return rec, log_stored_episode(data, rec, frames_every)
