"""Run episodes in isolated local worker processes (or in-process with ``workers=0``, for debugging).

Each episode gets a fresh process forked from this one after the environment stack has been imported here
(``pipeline.worker_preload``), so a worker starts in milliseconds with everything loaded. We fork rather
than use a forkserver or spawn: those re-import the caller's ``__main__`` in every worker (slow for scripts,
and broken for scripts without an ``if __name__ == "__main__"`` guard). The parent keeps no threads of its
own at fork time (tqdm's monitor thread is off; DuckDB connections are closed between writes). Inside it, before any policy code runs, :func:`harden_worker` caps the
address space (a 10 GB allocation fails with MemoryError instead of swapping the machine) and installs an
audit hook that refuses file writes, process spawning, sockets, signals to other processes and native-code
loading. Whatever the policy does, the parent survives: a worker that dies (``os._exit``, a segfault, the
OOM killer) or outlives its episode limit is recorded as a ``crashed`` or ``timeout`` episode.

Only the parent writes to the store: workers send back :class:`~pipeline.rollout.EpisodeOutcome` objects
(Arrow tables pickle compactly) and progress counts over a pipe.
"""

from __future__ import annotations

import multiprocessing
import os
import resource
import sys
import time
import traceback
from collections import deque
from multiprocessing.connection import Connection, wait
from typing import Callable, Iterable, Iterator

from pipeline.rollout import EpisodeOutcome, EpisodeSpec, crashed_outcome, run_episode

KILL_GRACE_S = 30.0
"""How long past its episode time limit a worker may run before the parent kills it."""

ProgressCallback = Callable[[int, int], None]
"""Called with (index of the spec, steps done so far)."""

_DENIED_EVENTS = (
    "os.system", "os.exec", "os.posix_spawn", "os.spawn", "os.fork", "os.forkpty", "subprocess.Popen",
    "pty.spawn", "socket.connect", "socket.bind", "socket.sendto", "socket.sendmsg", "ctypes.dlopen",
    "ctypes.dlsym", "ctypes.cdata", "os.remove", "os.unlink", "os.rename", "os.replace", "os.rmdir",
    "os.mkdir", "os.chmod", "os.chown", "os.truncate", "os.link", "os.symlink", "os.kill", "os.killpg",
    "shutil.rmtree", "shutil.copyfile", "shutil.move",
)
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC


def _audit(event: str, args: tuple) -> None:
    if event == "open":
        mode, flags = args[1], args[2]
        if (isinstance(mode, str) and any(c in mode for c in "wax+")) or (isinstance(flags, int) and flags & _WRITE_FLAGS):
            raise PermissionError(f"codearcade sandbox: writing files is not allowed ({args[0]!r})")
    elif event.startswith(_DENIED_EVENTS):
        raise PermissionError(f"codearcade sandbox: '{event}' is not allowed in a policy worker")


def harden_worker(memory_limit_mb: int | None) -> None:
    """Limit this (worker) process before policy code runs: memory cap, no core dumps, audit hook."""
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if memory_limit_mb:
        with open("/proc/self/statm") as f:
            current = int(f.read().split()[0]) * resource.getpagesize()
        limit = current + memory_limit_mb * 2**20
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    sys.addaudithook(_audit)


def _worker_main(spec: EpisodeSpec, conn: Connection) -> None:
    try:
        harden_worker(spec.memory_limit_mb)
        outcome = run_episode(spec, progress=lambda n: conn.send(("progress", n)))
        conn.send(("outcome", outcome))
    except BaseException:  # noqa: BLE001 - report anything to the parent
        try:
            conn.send(("error", traceback.format_exc(limit=8)))
        except Exception:
            pass
    finally:
        conn.close()


def _mp_context():
    import pipeline.worker_preload  # noqa: F401  (imported once here, inherited by every fork)

    return multiprocessing.get_context("fork")


def default_workers() -> int:
    return os.cpu_count() or 1


def run_episodes(
    specs: Iterable[EpisodeSpec],
    workers: int = 1,
    progress: ProgressCallback | None = None,
    started: Callable[[], None] | None = None,
) -> Iterator[tuple[int, EpisodeOutcome]]:
    """Play ``specs`` with at most ``workers`` processes at once; yield ``(index, outcome)`` as each ends.

    ``started`` is called once the first workers are playing, so the caller can do its own set-up writes
    meanwhile. ``workers=0`` plays them one after another in this process (no isolation; for debugging).
    """
    specs = list(specs)
    if workers <= 0:
        if started is not None:
            started()
        for i, spec in enumerate(specs):
            yield i, run_episode(spec, None if progress is None else (lambda n, i=i: progress(i, n)))
        return

    ctx = _mp_context()
    pending = deque(enumerate(specs))
    running: dict[Connection, tuple[int, EpisodeSpec, multiprocessing.process.BaseProcess, float]] = {}

    exiting: list[multiprocessing.process.BaseProcess] = []

    def finish(conn: Connection, outcome: EpisodeOutcome) -> tuple[int, EpisodeOutcome]:
        # the worker is exiting by itself; reap it later rather than wait for its teardown now
        i, _, process, _ = running.pop(conn)
        conn.close()
        exiting.append(process)
        return i, outcome

    def reap(timeout: float = 0.0) -> None:
        for process in list(exiting):
            process.join(timeout)
            if process.exitcode is not None:
                exiting.remove(process)
            elif timeout:
                process.kill()
                process.join(1)
                exiting.remove(process)

    def fill() -> None:
        while pending and len(running) < workers:
            i, spec = pending.popleft()
            parent_end, child_end = ctx.Pipe(duplex=False)
            process = ctx.Process(target=_worker_main, args=(spec, child_end), daemon=True,
                                  name=f"codearcade-episode-{spec.episode_id}")
            process.start()
            child_end.close()  # so that the parent sees EOF when the worker dies
            running[parent_end] = (i, spec, process, time.monotonic())

    try:
        fill()
        if started is not None:
            started()
        while pending or running:
            fill()
            finished: list[tuple[int, EpisodeOutcome]] = []
            for conn in wait(list(running), timeout=1.0):
                i, spec, process, started = running[conn]
                try:
                    kind, payload = conn.recv()
                except (EOFError, OSError):
                    process.join(5)
                    code = process.exitcode
                    how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                    finished.append(finish(conn, crashed_outcome(
                        spec, f"worker process died ({how}) before reporting", time.monotonic() - started)))
                    continue
                if kind == "progress":
                    if progress is not None:
                        progress(i, payload)
                elif kind == "outcome":
                    finished.append(finish(conn, payload))
                else:
                    finished.append(finish(conn, crashed_outcome(
                        spec, f"worker failed: {payload.strip().splitlines()[-1]}", time.monotonic() - started)))
            now = time.monotonic()
            for conn, (i, spec, process, started) in list(running.items()):
                if now - started > spec.episode_time_limit_s + KILL_GRACE_S:
                    process.kill()
                    outcome = crashed_outcome(spec, f"worker killed after {now - started:.0f} s "
                                                    f"(episode limit {spec.episode_time_limit_s:g} s)", now - started)
                    outcome.episode["end_reason"] = "timeout"
                    finished.append(finish(conn, outcome))
            fill()  # before handing results out, so that workers play while the caller writes them
            reap()
            yield from finished
    finally:
        for conn, (_, _, process, _) in running.items():
            process.kill()
            exiting.append(process)
            conn.close()
        reap(timeout=5.0)
