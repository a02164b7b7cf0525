"""Live Rerun recording of an episode, from inside the worker process that plays it.

``run_episode`` (``pipeline/play/rollout.py``) creates a :class:`LiveEpisodeRecorder` when ``EpisodeSpec.rerun`` is
set: a directory (the recording goes to ``DIR/<episode_id>.rrd``) or a ``rerun+http://…/proxy`` URL (a
viewer started by ``--rerun spawn``, or any Rerun gRPC server). Rerun is imported here, in the game host that
plays the episode (``pipeline/play/episodes.py``; no policy code runs there, and it keeps the machine's network),
never in the game zygote that forks the hosts: the SDK starts Rust threads, which a fork does not carry over.

Cost: per step only a frame every ``rerun_frames_every`` steps (an indexed PNG, ``viewers/frames.py``); the
steps themselves are read from the episode's :class:`~tracing.steps.StepLog` (which records them anyway)
every :data:`FLUSH_EVERY` steps and sent as columns. Node outputs go out at the end of the episode.
``bench/rerun_logging.py`` measures it against the environment's own time.
"""

from __future__ import annotations

import os
import time
from typing import Any, Mapping

import numpy as np
import pyarrow as pa

IMPORT_S = time.perf_counter()
import rerun as rr  # noqa: E402, F401  (loaded here on purpose, and timed: the SDK import is part of the cost in a fresh worker)

IMPORT_S = time.perf_counter() - IMPORT_S

from tracing.steps import StepLog  # noqa: E402
from viewers.frames import FrameEncoder  # noqa: E402
from viewers.rerun_episode import EpisodeLogger  # noqa: E402
from viewers.rerun_layout import episode_blueprint  # noqa: E402
from viewers.rerun_recording import close, new_recording, save_whole, within  # noqa: E402
from viewers.rerun_steps import StepColumns  # noqa: E402

FLUSH_EVERY = 250
"""Steps between two sends of the buffered step columns (a viewer sees the episode advance in these chunks)."""
FLUSH_TIMEOUT_S = 10.0
"""How long the end of an episode may wait for a viewer to take the data."""
SINK_TIMEOUT_S = 5.0
"""How long opening or closing an episode's recording may take (:func:`~viewers.rerun_recording.within`): past it
the recording is given up (the episode goes on), and the host plays no more episodes after this one."""

last_stats: dict[str, float] = {}
"""Timings of the last finished recorder in this process (for bench/rerun_logging.py)."""


def is_url(target: str) -> bool:
    return target.startswith(("rerun://", "rerun+http://", "rerun+https://"))


def steplog_columns(log: StepLog, start: int, stop: int) -> StepColumns:
    """Rows ``start <= row < stop`` of a StepLog (completed steps only) as :class:`StepColumns`."""
    s, offsets = log.scalars, log.offsets
    o = log.object_columns(start, stop)
    counts = np.diff(np.asarray(offsets[start:stop + 1], dtype=np.int64))
    return StepColumns.from_arrays(
        s["step"][start:stop],
        pa.array(s["action"][start:stop], type=pa.float64()),
        s["reward"][start:stop], s["score"][start:stop],
        pa.array(s["lives"][start:stop], type=pa.float64()),
        np.repeat(np.arange(stop - start, dtype=np.int64), counts),
        pa.array(o["key"], type=pa.utf8()), pa.array(o["category"], type=pa.utf8()),
        o["x"], o["y"], o["w"], o["h"],
    )


class LiveEpisodeRecorder:
    """Streams one episode to a file or viewer while it is played (see the module docstring)."""

    def __init__(self, spec: Any, ale: Any, steps: StepLog):
        t0 = time.perf_counter()
        self.spec = spec
        self.steps = steps
        self.frames_every = max(0, int(getattr(spec, "rerun_frames_every", 4) or 0))
        self.encoder = FrameEncoder(ale) if self.frames_every and ale is not None else None
        self.rec = new_recording(spec.episode_id)
        blueprint = episode_blueprint(traced=spec.trace)
        target = spec.rerun
        self.path: str | None = None
        self.partial: str | None = None  # written there, renamed to self.path once whole (save_whole)
        if is_url(target):
            self.rec.connect_grpc(target, default_blueprint=blueprint)
        else:
            self.path = os.path.join(target, f"{spec.episode_id}.rrd")
            self.partial = save_whole(self.rec, self.path, SINK_TIMEOUT_S, default_blueprint=blueprint)
        self.logger = EpisodeLogger(self.rec, traced=spec.trace,
                                    frames_every=self.frames_every if self.encoder is not None else 0)
        self.logger.code(spec.policy_text)
        self._flushed = 0
        self._frame_steps: list[int] = []
        self._pngs: list[bytes] = []
        self._frames = 0
        self.setup_s = time.perf_counter() - t0
        self.cost_s = 0.0

    def observe(self, step: int) -> None:
        """Called once the observation of ``step`` is in the StepLog, before the policy sees it."""
        t0 = time.perf_counter()
        if self.encoder is not None and step % self.frames_every == 0:
            self._frame_steps.append(step)
            self._pngs.append(self.encoder.screen_png())
        if step - self._flushed >= FLUSH_EVERY:
            self._flush(step)
        self.cost_s += time.perf_counter() - t0

    def _flush(self, stop: int) -> None:
        if stop > self._flushed:
            self.logger.steps(steplog_columns(self.steps, self._flushed, stop))
            self._flushed = stop
        if self._pngs:
            self.logger.frames(self._frame_steps, self._pngs)
            self._frames += len(self._pngs)
            self._frame_steps, self._pngs = [], []

    def finish(self, episode: Mapping[str, Any], nodes: pa.Table | None) -> None:
        """Send the rest (remaining steps, node outputs, the episode's properties) and close the sink: a file is
        renamed from its ``.partial`` name once whole, and removed if it is not (a disk that filled under it left
        a recording cut short under the episode's name)."""
        t0 = time.perf_counter()
        whole = False
        try:
            self._flush(len(self.steps))
            if nodes is not None:
                self.logger.nodes(nodes)
            self.logger.properties(episode, self.frames_every if self.encoder is not None else 0)
            self.logger.send_blueprint()
            within("flush the recording", lambda: self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S), self.path,
                   FLUSH_TIMEOUT_S + SINK_TIMEOUT_S)
            whole = True
        finally:
            # writes the .rrd footer (without it the file is incomplete); a sink that died waited here for good
            close(self.rec, self.partial, self.path, whole=whole, timeout_s=SINK_TIMEOUT_S)
            self.cost_s += time.perf_counter() - t0
            last_stats.clear()
            last_stats.update(import_s=IMPORT_S, setup_s=self.setup_s, log_s=self.cost_s,
                              steps=float(len(self.steps)), frames=float(self._frames))


def open_recorder(spec: Any, env: Any, steps: StepLog) -> tuple[LiveEpisodeRecorder | None, str | None]:
    """A recorder for ``spec``, or None and why Rerun cannot record (one line, for the command to say: a game
    host's own stderr goes nowhere): the episode is played and stored either way."""
    try:
        return LiveEpisodeRecorder(spec, getattr(env.unwrapped, "ale", None), steps), None
    except Exception as exc:  # noqa: BLE001 - a viewer problem must never cost the episode
        return None, problem(exc)


def finish_recorder(recorder: LiveEpisodeRecorder, episode: Mapping[str, Any], nodes: pa.Table | None) -> str | None:
    """Finish the recording; None, or why it is not whole (its file is then removed)."""
    try:
        recorder.finish(episode, nodes)
    except Exception as exc:  # noqa: BLE001 - a viewer problem must never cost the episode
        return problem(exc)
    return None


def problem(exc: BaseException) -> str:
    """One line that says why a recording failed: an ``OSError`` from :func:`~viewers.rerun_recording.within`
    names its file; anything else its class."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    return f"{type(exc).__name__}: {exc}"
