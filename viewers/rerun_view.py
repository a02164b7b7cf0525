"""``codearcade view``: pick a run's recording or one of its episodes, rebuild it from the store, send it out.

What is shown: ``--episode E`` an episode (an index of the iteration's evaluation episodes, ``train`` for its
training rollout, or a whole episode id); ``--iteration I`` alone that iteration's training rollout (the
traced one; an eval run's first episode); neither: the run recording of an optimization run, or the first
episode of an eval run. Where it goes: a file (``--save``, default ``./<recording id>.rrd``), a viewer
(``--spawn``, ``--connect URL``) or the web viewer served on 127.0.0.1 (``--serve-web``).
"""

from __future__ import annotations

import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from store import Store
from store.readers import get_run
from store.showing import episode_list
from viewers.rerun_sinks import ViewerError, spawn_viewer, start_web_viewer


class ViewError(ValueError):
    """Nothing to view (unknown run, iteration or episode); the message says what exists."""


@dataclass
class Selection:
    run_id: str
    run_kind: str
    episode_id: str | None  # None: the run recording

    @property
    def recording_id(self) -> str:
        return self.episode_id or self.run_id


def select(store: Store, run_id: str, iteration: int | None = None, episode: str | None = None) -> Selection:
    """What ``codearcade view RUN [--iteration I] [--episode E]`` shows (see the module docstring)."""
    with store.read() as con:
        run = get_run(con, run_id)
        if run is None:
            raise ViewError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
        episodes = episode_list(con, run_id)
    kind = run["kind"]
    ids = [e[0] for e in episodes]
    if episode is not None and "." in episode:
        if episode not in ids:
            raise ViewError(f"run {run_id} has no episode {episode}")
        return Selection(run_id, kind, episode)
    if episode is None and iteration is None:
        if kind == "eval":
            if not ids:
                raise ViewError(f"run {run_id} has no episodes yet")
            return Selection(run_id, kind, ids[0])
        return Selection(run_id, kind, None)
    it = 0 if iteration is None else iteration
    in_iteration = [e for e in episodes if e[1] == it]
    if not in_iteration:
        have = sorted({e[1] for e in episodes})
        raise ViewError(f"run {run_id} has no episodes in iteration {it} (iterations with episodes: "
                        f"{', '.join(map(str, have)) or 'none'})")
    if episode is None:
        train = [e[0] for e in in_iteration if e[2] == "train"]
        return Selection(run_id, kind, train[0] if train else in_iteration[0][0])
    if episode == "train":
        wanted = [e[0] for e in in_iteration if e[2] == "train"]
    else:
        try:
            index = int(episode)
        except ValueError:
            raise ViewError(f"--episode {episode}: give an evaluation episode index, 'train' or an episode id") from None
        wanted = [e[0] for e in in_iteration if e[2] == "eval" and e[3] == index]
    if not wanted:
        raise ViewError(f"run {run_id} has no episode {episode} in iteration {it}; it has "
                        f"{', '.join(e[0] for e in in_iteration)}")
    return Selection(run_id, kind, wanted[0])


def view(store: Store, run_id: str, iteration: int | None = None, episode: str | None = None,
         save: str | None = None, connect: str | None = None, spawn: bool = False, serve_web: bool = False,
         frames_every: int = 4, out: Callable[[str], None] = print, warn: Callable[[str], None] = print,
         wait: Callable[[], None] | None = None, run_label: str | None = None,
         waiting: Callable[[Callable[[float], bool]], None] | None = None) -> Selection:
    """Rebuild the selected recording and send it to one sink (see the module docstring). ``run_label``: the run
    as the lines given to ``out`` name it (the command line's shortest unique prefix; the id by default).

    With ``serve_web`` it serves until interrupted (or until ``wait`` returns, for tests), then stops the server;
    ``waiting(done)`` is the command's wait, until a stop or ``done(timeout)`` (the server ended); a Ctrl-C ends it
    as it ends every command (it was taken as the end of the serving: exit 0).
    """
    if frames_every < 0:
        raise ViewError("--frames-every must be 0 (no frames) or more")
    selection = select(store, run_id, iteration, episode)
    from viewers.rerun_recording import close, new_recording, save_whole  # imports Rerun: never in a process that forks

    rec = new_recording(selection.recording_id)
    viewer = partial = None
    if serve_web:
        viewer = start_web_viewer()
        rec.connect_grpc(viewer.grpc_url)
    elif spawn:
        rec.connect_grpc(spawn_viewer())
    elif connect:
        rec.connect_grpc(connect)
    else:
        save = save or f"{selection.recording_id}.rrd"
        partial = save_whole(rec, save)
    try:
        if selection.episode_id is None:
            from viewers.rerun_run import log_run, read_run

            with store.read() as con:
                data = read_run(con, run_id)
            log_run(data, rec)
            out(f"run {run_label or run_id}: {len(data['iterations'])} iteration(s)")
        else:
            from viewers.rerun_replay import log_stored_episode, read_episode

            with store.read() as con:
                data = read_episode(con, selection.episode_id)
            check = log_stored_episode(data, rec, frames_every)
            e = data.episode
            out(f"episode {selection.episode_id}: {e['length']} steps, return {e['return']:g}, {e['end_reason']}; "
                f"{check.describe()}")
            if not check.faithful:
                warn(f"codearcade: warning: episode {selection.episode_id}: {check.describe()}")
    except BaseException:
        close(rec, partial, save, whole=False)
        raise
    try:
        close(rec, partial, save)
    except RuntimeError as exc:  # Rerun's flush gives up on a URL nothing answers at (after 6 s): not a traceback
        if connect and "unable to connect" in str(exc):
            raise ViewerError(f"no Rerun viewer answered at {connect}: start one (`rerun`), or give --spawn, "
                              "--serve-web or --save instead") from None
        raise
    if save:
        out(f"saved {Path(save).resolve()} (recording {selection.recording_id})")
    elif viewer is not None:
        out(f"serving the Rerun web viewer on 127.0.0.1: open {viewer.url}")
        previous = signal.signal(signal.SIGTERM, _interrupt)
        try:  # the server stops however this ends, a press right after the line below included
            out("press Ctrl-C to stop")
            if wait is not None:
                wait()
            elif waiting is not None:  # the command's own wait, which also sees a press Python swallowed
                waiting(lambda timeout: _ended(viewer.process, timeout))
            else:
                viewer.process.wait()
        finally:
            signal.signal(signal.SIGTERM, previous)
            viewer.stop()
    else:
        out(f"sent recording {selection.recording_id} to the viewer")
    return selection


def _ended(process: subprocess.Popen, timeout: float) -> bool:
    """Whether ``process`` ended within ``timeout`` seconds."""
    try:
        process.wait(timeout=timeout)
        return True
    except subprocess.TimeoutExpired:
        return False


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt
