"""Run tasks in worker processes, policy code always behind the operating-system boundary, or in-process with
``workers=0`` (for debugging; no isolation at all). The tasks themselves (an episode, a candidate's checks) are
``pipeline/play``'s: :class:`Task` says how one goes out and comes back, :func:`run_tasks` runs many. The workers
are forked by the two zygotes, the policy's and the game's, whose parent side (and the game hosts kept between
calls) is ``pipeline/boundary/zygotes.py``.

An episode is a *paired* task: a host and a policy process joined by a socket of their own, one round trip per
step, pinned to one CPU (a round trip across cores costs tens of microseconds here, on one a few: NOTES.md).
The next episode's pair is forked and prepared while the current one plays (``staged``): the host resets its
environment (a few ms without sticky actions; with them ALE reloads the ROM, ~0.15 s) and its policy process
loads the policy, so neither the forks nor the reset sit between episodes; it has its go-ahead as soon as the
answer of the episode before has come whole, and that answer is checked here while it plays.

Only plain data crosses: the task goes out as one JSON frame, the answer comes back as JSON frames and Arrow
IPC streams (``pipeline/boundary/wire.py``), every value checked here; nothing is unpickled. Whatever a worker does,
this process survives: a worker that dies (``os._exit``, a segfault, the OOM killer, SIGXCPU), sends anything
malformed, or outlives its time limit by :data:`KILL_GRACE_S` is killed and recorded as a ``crashed`` or
``timeout`` episode. Only this process writes to the store.
"""

from __future__ import annotations

import math
import os
import select
import signal
import socket
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Iterable, Iterator, TypeVar

from pipeline.boundary import wire
from pipeline.boundary.zygotes import KEPT, ZYGOTE_USE, Zygote, zygote
from pipeline.settings import EpisodeLimits
from pipeline.stopping import raise_if_stopped

KILL_GRACE_S = 30.0
"""How long past its time limit a worker may run before the parent kills it."""

T = TypeVar("T")
R = TypeVar("R")

ProgressCallback = Callable[[int, int], None]
"""Called with (index of the item, steps done so far)."""


@dataclass(frozen=True)
class Task:
    """A kind of work for a worker: how its item goes out and its answer comes back."""

    name: str
    """The zygote's name for it (``pipeline/boundary/zygote.py`` TASKS)."""
    local: Callable[[Any, Callable[[int], None]], Any]
    """Runs it in this process (``workers=0``)."""
    encode: Callable[[Any], dict[str, Any]]
    decode: Callable[[Any, dict[str, Any], list[bytes]], Any]
    """(item, the result message, the Arrow payloads that followed it) -> result; raises wire.BadMessage."""
    tables: Callable[[dict[str, Any]], int] = lambda msg: 0
    """How many Arrow frames follow a result message."""
    limits: Callable[[Any], dict[str, Any]] = lambda item: {}
    """The (policy) worker's :class:`pipeline.boundary.confine.Limits` for an item, as keyword arguments."""
    paired: bool = False
    """Each item is played by a host of the game zygote (the task ``name``) with a policy process of its own from
    the policy zygote (task ``policy``), joined by a socket; both pinned to one CPU."""
    after_pair: Callable[[Any, Callable[[], int | None]], Any] | None = None
    """For a paired task: (result, the policy process's exit code when asked) -> result."""


class DeadlinePassed(Exception):
    """The caller's deadline passed while tasks ran (:func:`run_tasks`): those running were ended, none yielded."""


_WHOLE = object()
"""A worker's answer has come whole (:func:`run_tasks`): what it says is checked next."""


class _CallerFailed(Exception):
    """The caller's progress callback raised (its ``__cause__``): its error, not a message the worker got wrong."""


@dataclass
class _Running:
    index: int
    item: Any
    task_id: int
    conn: socket.socket
    begun: float
    policy_id: int | None = None
    """A paired task's policy process."""
    cpu: int | None = None
    reader: wire.FrameReader = field(default_factory=wire.FrameReader)
    result: dict[str, Any] | None = None
    tables: list[bytes] = field(default_factory=list)


def run_tasks(
    task: Task,
    items: Iterable[T],
    workers: int,
    failed: Callable[[T, str, bool], R],
    time_limit_s: Callable[[T], float | None] = lambda item: None,
    progress: ProgressCallback | None = None,
    started: Callable[[], None] | None = None,
    prepare: Callable[[Zygote], None] | None = None,
    hosts_key: Hashable | None = None,
    deadline: float | None = None,
) -> Iterator[tuple[int, R]]:
    """Run ``task`` on every item in a worker of its own (a paired task: a host and a policy process), at most
    ``workers`` at once; yield ``(index, result)`` as each finishes.

    A worker that dies, raises, sends a malformed answer, or outlives ``time_limit_s(item)`` plus a grace period
    yields ``failed(item, why, timed_out)`` instead. ``started`` is called once the first workers are running,
    so the caller can do its own set-up meanwhile. ``prepare(zygote)`` may warm the (host's) zygote first.
    ``workers=0`` runs the tasks one after another in this process (no isolation; for debugging).
    ``hosts_key`` (a paired task): what its hosts were prepared for (the environments ``prepare`` builds); inside
    :func:`keep_hosts`, the hosts idle at the end are kept for the next call with the same task and key.
    ``deadline`` (``time.monotonic()``): past it the workers still running are ended and :class:`DeadlinePassed`
    is raised (what they would have played is nobody's fault, so none of it is a result).
    """
    items = list(items)
    if workers <= 0:
        if started is not None:
            started()
        for i, item in enumerate(items):
            yield i, task.local(item, (lambda n, i=i: progress(i, n)) if progress is not None else (lambda n: None))
        return
    with ZYGOTE_USE:  # the zygotes serve one caller at a time (the proposal pool's threads share them)
        yield from _run_tasks(task, items, workers, failed, time_limit_s, progress, started, prepare, hosts_key,
                              deadline)



def _run_tasks(task: Task, items: list, workers: int, failed, time_limit_s, progress, started,
               prepare, hosts_key, deadline: float | None = None) -> Iterator[tuple[int, Any]]:
    """:func:`run_tasks` with worker processes (under :data:`ZYGOTE_USE`)."""
    zyg = zygote("game" if task.paired else "policy")
    policies = zygote("policy") if task.paired else None
    if prepare is not None:
        prepare(zyg)
    cpus = sorted(os.sched_getaffinity(0))
    pending = deque(enumerate(items))
    busy: dict[int, _Running] = {}  # by fd
    staged: deque[_Running] = deque()
    """The next worker, forked, confined and prepared (policy loaded, environment reset) while the others play:
    the forks (~5-20 ms) and the seeded reset (up to ~0.15 s) would otherwise come between one episode and the
    next."""

    def limits_of(item: Any) -> dict[str, Any]:
        limits = task.limits(item)
        limit = time_limit_s(item)
        if limit is not None and "cpu_s" not in limits:
            limits["cpu_s"] = int(math.ceil(limit + KILL_GRACE_S + 10))
        return limits

    keeping = policies is not None and hosts_key is not None and KEPT.depth > 0  # re-checked under its lock
    kept_key = (task.name, hosts_key)
    idle: list[tuple[int, socket.socket]] = KEPT.take(zyg, kept_key) if keeping else []
    """Game hosts whose episode is done, ready to play another (task id, socket): a host runs no policy code, so
    it need not be fresh, and handing it the next episode saves the fork and the teardown of a process that holds
    the whole emulator stack (``zygote.Role.serves_many``); inside :func:`keep_hosts`, those an earlier call kept."""

    def start(staged_: bool) -> _Running:
        i, item = pending.popleft()
        if policies is None:
            task_id, conn = zyg.start(task.name, task.encode(item), limits_of(item), staged=staged_)
            return _Running(i, item, task_id, conn, time.monotonic())
        host_end, policy_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        policy_id = policies.attach("policy", policy_end, limits_of(item))  # always a fresh policy process
        while idle:
            task_id, conn = idle.pop()
            if zyg.hand(conn, task.encode(item), host_end):
                host_end.close()
                return _Running(i, item, task_id, conn, time.monotonic(), policy_id=policy_id)
            conn.close()  # that host is gone: its exit is of no interest now
            zyg.forget(task_id)
        # a host always waits for its go-ahead, which names its CPU
        task_id, conn = zyg.start(task.name, task.encode(item), {}, staged=True, extra=host_end)
        return _Running(i, item, task_id, conn, time.monotonic(), policy_id=policy_id)

    def free_cpu() -> int | None:
        """A CPU no running pair holds (a pair alternates between its two processes: one core is all it needs)."""
        if policies is None:
            return None
        held = {run.cpu for run in busy.values()}
        return next((cpu for cpu in cpus if cpu not in held), None)

    def fill(stage: bool = True) -> None:
        """Start what the free places allow (the staged worker first: it only needs its go-ahead), then, with
        ``stage``, stage the next."""
        while (staged or pending) and len(busy) < workers:
            if staged:
                run, waiting = staged.popleft(), True
            elif not stage:
                break
            else:
                run, waiting = start(False), policies is not None  # a host always waits for its go-ahead
            run.cpu = free_cpu()
            if waiting:
                zyg.go(run.conn, run.cpu)
            run.begun = time.monotonic()
            busy[run.conn.fileno()] = run
        if stage and pending and not staged:
            staged.append(start(True))

    def end(run: _Running, kill: bool = False) -> None:
        busy.pop(run.conn.fileno(), None)  # gone already when the staged pair took its place (below)
        run.conn.close()
        if kill:
            zyg.kill(run.task_id)
        if policies is not None and run.policy_id is not None:
            policies.kill(run.policy_id)  # done with its episode (or stuck): either way, it goes

    def settle(run: _Running) -> None:
        zyg.forget(run.task_id)
        if policies is not None and run.policy_id is not None:
            policies.forget(run.policy_id)

    def done(run: _Running) -> None:
        """A task that answered in full: its host (paired) waits for the next episode, its policy process goes."""
        # a host that reported an error has exited (or is about to); one that sent anything past its answer is
        # not trusted with another
        if policies is None or run.result is None or run.reader.held:
            end(run)
            settle(run)
            return
        busy.pop(run.conn.fileno(), None)
        idle.append((run.task_id, run.conn))
        if run.policy_id is not None:
            policies.kill(run.policy_id)
            policies.forget(run.policy_id)

    def died(run: _Running) -> R:
        code = zyg.exit_code(run.task_id)
        settle(run)
        if code == -signal.SIGXCPU:
            return failed(run.item, "worker exceeded its CPU-time limit", True)
        how = "unknown exit status" if code is None else (f"signal {-code}" if code < 0 else f"exit code {code}")
        return failed(run.item, f"worker process died ({how}) before reporting", False)

    def handle(run: _Running, frames: list[tuple[bytes, bytes]]) -> Any:
        """Take in what ``run``'s worker sent: None while its answer is not whole, :data:`_WHOLE` once it is (then
        :func:`decoded`), or the result of a worker that reported its failure."""
        for kind, payload in frames:
            if run.result is not None:
                if kind != b"A":
                    raise wire.BadMessage("a JSON message where an Arrow table was expected")
                run.tables.append(payload)
            else:
                if kind != b"J":
                    raise wire.BadMessage("an Arrow table before the result")
                msg = wire.parse_message(payload)  # kind and fields checked
                if msg["kind"] == "progress":
                    if progress is not None:
                        try:
                            progress(run.index, msg["n"])
                        except Exception as exc:  # noqa: BLE001 - the caller's own failure, raised as it is below
                            raise _CallerFailed from exc
                    continue
                if msg["kind"] == "error":
                    return failed(run.item, f"worker failed: {msg['error']}", False)
                run.result = msg
            if run.result is not None:
                wanted = task.tables(run.result)
                if len(run.tables) > wanted:
                    raise wire.BadMessage("more Arrow tables than announced")
                if len(run.tables) == wanted:
                    return _WHOLE
        return None

    def decoded(run: _Running) -> R:
        """The result of ``run``'s whole answer, every value checked (wire.BadMessage otherwise)."""
        result = task.decode(run.item, run.result, run.tables)
        if policies is not None and task.after_pair is not None:
            result = task.after_pair(result, lambda: policies.exit_code(run.policy_id, wait_s=1.0))
        return result

    checking: list[_Running] = []
    """A paired task whose answer is being checked, its place already given to the next (at most one)."""
    controls = [zyg] + ([policies] if policies is not None else [])
    try:
        fill()
        if started is not None:
            started()
        while pending or staged or busy:
            fill()
            finished: list[tuple[int, R]] = []
            ready, _, _ = select.select(list(busy) + [z.ctl.fileno() for z in controls], [], [], 0.5)
            # a press Python swallowed (raised in a finalizer) played the games on to their end: stop as it would
            raise_if_stopped()
            for z in controls:
                if z.ctl.fileno() in ready:
                    z.pump()
            for fd in ready:
                run = busy.get(fd)
                if run is None:
                    continue
                try:
                    data = run.conn.recv(1 << 20)
                except BlockingIOError:
                    continue
                except OSError:
                    data = b""
                if not data:
                    end(run)
                    finished.append((run.index, died(run)))
                    continue
                try:
                    result = handle(run, run.reader.feed(data))
                    if result is _WHOLE:
                        if policies is not None:  # the pair has played: the staged pair plays on its CPU while
                            # the answer is checked here (a traced episode's node rows take milliseconds)
                            checking.append(busy.pop(fd))
                            fill(stage=False)
                        result = decoded(run)
                        checking.clear()
                except _CallerFailed as exc:  # not the worker's doing: the caller hears its own error
                    raise exc.__cause__ from None
                except Exception as exc:  # noqa: BLE001 - whatever a worker sends, this process goes on
                    if not isinstance(exc, wire.BadMessage):
                        exc = f"{type(exc).__name__}: {str(exc)[:300]}"
                    checking.clear()  # ended here
                    end(run, kill=True)
                    settle(run)
                    finished.append((run.index, failed(run.item, f"the worker sent a malformed message: {exc}",
                                                       False)))
                    continue
                if result is not None:
                    done(run)
                    finished.append((run.index, result))
            now = time.monotonic()
            if deadline is not None and now > deadline and (busy or pending or staged):
                raise DeadlinePassed(f"{len(busy)} task(s) still running and {len(pending) + len(staged)} to start")
            for run in list(busy.values()):
                limit = time_limit_s(run.item)
                if limit is not None and now - run.begun > limit + KILL_GRACE_S:
                    end(run, kill=True)
                    settle(run)
                    finished.append((run.index, failed(run.item, f"worker killed after {now - run.begun:.0f} s "
                                                                 f"(time limit {limit:g} s)", True)))
            if not all(z.alive() for z in controls):
                for run in list(busy.values()):
                    end(run, kill=True)
                    settle(run)
                    finished.append((run.index, failed(run.item, "a zygote process died", False)))
            fill()  # before handing results out, so that workers play while the caller writes them
            yield from finished
    finally:
        for run in list(busy.values()) + checking:
            end(run, kill=True)
            settle(run)
        for run in staged:
            run.conn.close()  # EOF instead of G: the worker exits without running anything
            if policies is not None and run.policy_id is not None:
                policies.kill(run.policy_id)
            settle(run)
        # for the next call (keep_hosts); they exit when its block ends
        if not (keeping and zyg.alive() and KEPT.keep(zyg, kept_key, idle)):
            for task_id, conn in idle:
                conn.close()  # EOF instead of the next task: the host exits
                zyg.forget(task_id)


def run_json_task(name: str, item: dict[str, Any], local: Callable[[dict[str, Any]], dict[str, str | None]],
                  time_limit_s: float, memory_mb: int | None = EpisodeLimits.memory_limit_mb, workers: int = 1) -> tuple[bool, Any]:
    """Run a task whose answer is ``{"kind": "result", FIELD: str | None, ...}`` (``local`` returns the fields)
    in a confined worker: (True, the fields) when it answered, (False, why not) when it crashed, misbehaved or
    timed out."""
    (result,) = run_json_tasks(name, [item], local, lambda it: time_limit_s, lambda it: memory_mb, workers)
    return result


def run_json_tasks(name: str, items: list[dict[str, Any]], local: Callable[[dict[str, Any]], dict[str, str | None]],
                   time_limit_s: Callable[[dict[str, Any]], float],
                   memory_mb: Callable[[dict[str, Any]], int | None] = lambda item: EpisodeLimits.memory_limit_mb,
                   workers: int = 1) -> list[tuple[bool, Any]]:
    """:func:`run_json_task` of each item (limits per item), up to ``workers`` at once; results in item order."""
    def decode(_item: Any, msg: dict[str, Any], _tables: list[bytes]) -> tuple[bool, Any]:
        return True, wire.text_answer(msg)

    if not items:
        return []
    task = Task(name, lambda it, _p: (True, local(it)), lambda it: it, decode,
                limits=lambda it: dict(memory_mb=memory_mb(it), cpu_s=int(math.ceil(time_limit_s(it))) + 5))
    results: list[Any] = [None] * len(items)
    for i, result in run_tasks(task, items, workers, lambda it, why, timed_out: (False, why),
                               time_limit_s=time_limit_s):
        results[i] = result
    return results
