"""Run episodes in isolated local worker processes (or in-process with ``workers=0``, for debugging).

Worker processes are forked from this one after the environment stack has been imported here
(``pipeline.worker_preload``), so a worker starts in milliseconds with everything loaded, and each plays
the tasks of one call one after another (forking per episode cost about a tenth of an episode). Every
episode still loads its policy afresh (``run_episode``), so no policy state carries over. We fork rather
than use a forkserver or spawn: those re-import the caller's ``__main__`` in every worker (slow for scripts,
and broken for scripts without an ``if __name__ == "__main__"`` guard). The parent keeps no threads of its
own at fork time (tqdm's monitor thread is off; the store's DuckDB instance closes itself before a fork). Inside a
worker, before any policy code runs, :func:`harden_worker` caps the address space (a 10 GB allocation fails with MemoryError instead of swapping the machine) and installs an
audit hook that refuses file writes, process spawning, sockets, signals to other processes and native-code
loading. Whatever the policy does, the parent survives: a worker that dies (``os._exit``, a segfault, the
OOM killer) or outlives its episode limit is recorded as a ``crashed`` or ``timeout`` episode.

Only the parent writes to the store: workers send back :class:`~pipeline.rollout.EpisodeOutcome` objects
(Arrow tables pickle compactly) and progress counts over a pipe.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import resource
import signal
import sys
import time
import traceback
from collections import deque
from multiprocessing.connection import Connection, wait
from typing import Any, Callable, Iterable, Iterator, TypeVar

from games.envs import shared_env
from pipeline.rollout import EpisodeOutcome, EpisodeSpec, crashed_outcome, run_episode

KILL_GRACE_S = 30.0
"""How long past its episode time limit a worker may run before the parent kills it."""

T = TypeVar("T")
R = TypeVar("R")

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


def die_with_parent(parent_pid: int) -> None:
    """Ask Linux to kill this (just forked) process when its parent dies (a killed run must not leave workers
    playing on). ``parent_pid``, the parent's pid taken before the fork: a parent that died before the request
    was made (a child can wait long for its first time slice on busy cores) ends this process at once."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux/glibc: orphans finish their episode and exit on the broken pipe
        pass
    if os.getppid() != parent_pid:
        os._exit(1)  # orphaned already: the death signal will never come


def harden_worker(memory_limit_mb: int | None, parent_pid: int) -> None:
    """Limit this (worker) process before policy code runs: memory cap, no core dumps, audit hook."""
    die_with_parent(parent_pid)
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if memory_limit_mb:
        with open("/proc/self/statm") as f:
            current = int(f.read().split()[0]) * resource.getpagesize()
        limit = current + memory_limit_mb * 2**20
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    sys.addaudithook(_audit)


def _worker_loop(task: Callable, memory_limit_mb: int | None, conn: Connection, parent_pid: int) -> None:
    """A worker: harden once, then run each task the parent sends until it says stop (or goes away)."""
    harden_worker(memory_limit_mb, parent_pid)
    # The heap inherited from the parent (every imported module) never becomes garbage: keep the cyclic
    # collector from walking it again and again while an episode allocates (10% of Space Invaders' time).
    gc.freeze()
    while True:
        try:
            kind, item = conn.recv()
        except (EOFError, OSError):
            return
        if kind == "stop":
            return
        try:
            result = task(item, lambda n: conn.send(("progress", n)))
            conn.send(("result", result))
        except BaseException:  # noqa: BLE001 - report anything to the parent
            try:
                conn.send(("error", traceback.format_exc(limit=8)))
            except Exception:
                return


STOP_GRACE_S = 5.0
"""How long a worker told to stop may take to exit before it is killed."""

_exiting: list[tuple[multiprocessing.process.BaseProcess, float]] = []
"""Workers told to stop (or killed) and not yet collected, each with the time after which it is killed.
A call does not wait for its workers to exit (~8 ms, a tenth of an evaluation's fixed cost); they are
collected by the next call, and at exit by multiprocessing, which joins its children."""
os.register_at_fork(after_in_child=_exiting.clear)  # a child must never collect, let alone kill, its siblings


def reap_workers() -> None:
    """Collect the workers that have exited; kill one still running past its grace period."""
    now = time.monotonic()
    for entry in list(_exiting):
        process, kill_after = entry
        if process.exitcode is None and now >= kill_after:
            process.kill()
            process.join(1)
        if process.exitcode is not None:
            _exiting.remove(entry)


def _mp_context():
    import pipeline.worker_preload  # noqa: F401  (imported once here, inherited by every fork)

    return multiprocessing.get_context("fork")


def run_tasks(
    task: Callable[[T, Callable[[int], None]], R],
    items: Iterable[T],
    workers: int,
    failed: Callable[[T, str, bool], R],
    time_limit_s: Callable[[T], float | None] = lambda item: None,
    memory_limit_mb: Callable[[T], int | None] = lambda item: None,
    progress: ProgressCallback | None = None,
    started: Callable[[], None] | None = None,
) -> Iterator[tuple[int, R]]:
    """Run ``task(item, report_progress)`` for every item in hardened worker processes, at most ``workers``
    at once (each worker runs one item after another); yield ``(index, result)`` as each finishes.

    A worker that dies, raises, or outlives ``time_limit_s(item)`` plus a grace period yields
    ``failed(item, why, timed_out)`` instead. ``started`` is called once the first workers are running, so the
    caller can do its own set-up meanwhile. ``workers=0`` runs the tasks one after another in this process
    (no isolation; for debugging).
    """
    items = list(items)
    if workers <= 0:
        if started is not None:
            started()
        for i, item in enumerate(items):
            yield i, task(item, (lambda n, i=i: progress(i, n)) if progress is not None else (lambda n: None))
        return

    ctx = _mp_context()
    pending = deque(enumerate(items))
    idle: list[tuple[multiprocessing.process.BaseProcess, Connection]] = []
    busy: dict[Connection, tuple[multiprocessing.process.BaseProcess, int, Any, float]] = {}

    def spawn(item: Any) -> tuple[multiprocessing.process.BaseProcess, Connection]:
        parent_end, child_end = ctx.Pipe(duplex=True)
        process = ctx.Process(target=_worker_loop, args=(task, memory_limit_mb(item), child_end, os.getpid()),
                              daemon=True, name="codearcade-worker")
        process.start()
        child_end.close()  # so that the parent sees EOF when the worker dies
        return process, parent_end

    def retire(process: multiprocessing.process.BaseProcess, conn: Connection, kill: bool = False) -> None:
        if kill:
            process.kill()
        conn.close()
        _exiting.append((process, time.monotonic() + STOP_GRACE_S))

    def fill() -> None:
        while pending and len(busy) < workers:
            i, item = pending.popleft()
            process, conn = idle.pop() if idle else spawn(item)
            try:
                conn.send(("task", item))
            except (BrokenPipeError, OSError):  # an idle worker that died: give the task to a new one
                retire(process, conn)
                process, conn = spawn(item)
                conn.send(("task", item))
            busy[conn] = (process, i, item, time.monotonic())

    try:
        fill()
        if started is not None:
            started()
        while pending or busy:
            fill()
            finished: list[tuple[int, R]] = []
            for conn in wait(list(busy), timeout=1.0):
                process, i, item, begun = busy[conn]
                try:
                    kind, payload = conn.recv()
                except (EOFError, OSError):
                    del busy[conn]
                    process.join(5)
                    code = process.exitcode
                    how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                    retire(process, conn)
                    finished.append((i, failed(item, f"worker process died ({how}) before reporting", False)))
                    continue
                if kind == "progress":
                    if progress is not None:
                        progress(i, payload)
                    continue
                del busy[conn]
                idle.append((process, conn))
                if kind == "result":
                    finished.append((i, payload))
                else:
                    finished.append((i, failed(item, f"worker failed: {payload.strip().splitlines()[-1]}", False)))
            now = time.monotonic()
            for conn, (process, i, item, begun) in list(busy.items()):
                limit = time_limit_s(item)
                if limit is not None and now - begun > limit + KILL_GRACE_S:
                    del busy[conn]
                    retire(process, conn, kill=True)
                    finished.append((i, failed(item, f"worker killed after {now - begun:.0f} s "
                                                     f"(time limit {limit:g} s)", True)))
            fill()  # before handing results out, so that workers play while the caller writes them
            reap_workers()
            yield from finished
    finally:
        for process, conn in idle:
            try:
                conn.send(("stop", None))
            except (BrokenPipeError, OSError):
                pass
            retire(process, conn)
        for conn, (process, *_rest) in busy.items():
            retire(process, conn, kill=True)
        reap_workers()  # without waiting: the workers exit by themselves within milliseconds


def _episode_failed(spec: EpisodeSpec, error: str, timed_out: bool) -> EpisodeOutcome:
    outcome = crashed_outcome(spec, error)
    if timed_out:
        outcome.episode["end_reason"] = "timeout"
    return outcome


def run_episodes(
    specs: Iterable[EpisodeSpec],
    workers: int = 1,
    progress: ProgressCallback | None = None,
    started: Callable[[], None] | None = None,
) -> Iterator[tuple[int, EpisodeOutcome]]:
    """Play ``specs`` in worker processes (see :func:`run_tasks`); a worker that dies or hangs yields an
    episode with end reason ``crashed`` or ``timeout``."""
    specs = list(specs)
    if workers > 0:
        # Build each environment here, once per process (~0.1-0.2 s each): forked workers inherit it ready,
        # and the next call (the optimizer's next iteration) skips building it again.
        for game, sticky, noop_max in {(s.game, s.sticky, s.noop_max) for s in specs}:
            try:
                shared_env(game, sticky=sticky, noop_max=noop_max)
            except Exception:  # noqa: BLE001 - the worker meets the same error and records it with the episode
                pass
    return run_tasks(
        run_episode, specs, workers, _episode_failed,
        time_limit_s=lambda spec: spec.episode_time_limit_s,
        memory_limit_mb=lambda spec: spec.memory_limit_mb,
        progress=progress, started=started,
    )
