"""Run tasks in confined worker processes, behind the operating-system boundary, or in-process with
``workers=0`` (for debugging; no isolation at all). The tasks themselves (an episode, a candidate's checks) are
``pipeline/play``'s: :class:`Task` says how one goes out and comes back, :func:`run_tasks` runs many.

Policy code never runs in this process, nor in any process that holds this one's memory or environment
(API keys, the store path). A :class:`Zygote` is started once per process with ``subprocess``: a fresh
interpreter with an allow-listed environment (:func:`worker_environment`) that imports the environment stack
and forks one worker per task (``pipeline/boundary/zygote.py``), so every episode starts from the same clean state
(nothing a policy changes, module attributes included, survives into the next). The next worker is forked and
confined while the current one plays (``staged``), and loads its policy and resets its environment (ALE's
seeded reset reloads the ROM, ~0.1 s), so neither the fork (~5-20 ms) nor the reset sits between episodes. Each
worker is confined by the kernel before it loads policy code (``pipeline/boundary/confine.py``: no exec, no fork, no
network, no writes outside its scratch directory, no reads outside Python's and the project's files, rlimits),
and its stdout/stderr go to /dev/null. A missing kernel feature stops the run with a one-line error unless
``CODEARCADE_ALLOW_WEAK_SANDBOX=1`` (then a warning is printed on every run).

Only plain data crosses: the task goes out as one JSON frame, the answer comes back as JSON frames and Arrow
IPC streams (``pipeline/boundary/wire.py``), every value checked here; nothing is unpickled. Whatever a worker does,
this process survives: a worker that dies (``os._exit``, a segfault, the OOM killer, SIGXCPU), sends anything
malformed, or outlives its time limit by :data:`KILL_GRACE_S` is killed and recorded as a ``crashed`` or
``timeout`` episode. Only this process writes to the store.
"""

from __future__ import annotations

import atexit
import json
import math
import os
import re
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, TypeVar

from pipeline.boundary import wire
from pipeline.boundary.confine import SandboxUnavailable, WEAK_ENV, weak_sandbox_allowed

KILL_GRACE_S = 30.0
"""How long past its time limit a worker may run before the parent kills it."""
START_TIMEOUT_S = 180.0
"""How long the zygote may take to import the environment stack and say hello."""

T = TypeVar("T")
R = TypeVar("R")

ProgressCallback = Callable[[int, int], None]
"""Called with (index of the item, steps done so far)."""

ROOT = Path(__file__).resolve().parents[2]
_ALLOWED_ENV = re.compile(r"^(PATH|LANG|LANGUAGE|LC_[A-Z]+|TZ|TERM|OMP_[A-Z_]+|OPENBLAS_[A-Z_]+|MKL_[A-Z_]+|"
                          r"SDL_[A-Z_]+|ALE_[A-Z_]+|PYTHONHASHSEED|PYTHONDONTWRITEBYTECODE|CODEARCADE_GAME_MODULES)$")
_SECRET_ENV = re.compile(r"(KEY|TOKEN|SECRET|PASSWORD|PASSWD|CREDENTIAL|AUTH|COOKIE|SESSION)", re.IGNORECASE)


def worker_environment(home: str) -> dict[str, str]:
    """The zygote's whole environment: an allow-list of harmless variables, never a secret."""
    env = {k: v for k, v in os.environ.items() if _ALLOWED_ENV.match(k) and not _SECRET_ENV.search(k)}
    paths = [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    env.update(HOME=home, TMPDIR=home, PYTHONPATH=os.pathsep.join(dict.fromkeys(paths)),
               PYTHONDONTWRITEBYTECODE="1")
    if weak_sandbox_allowed():
        env[WEAK_ENV] = "1"
    return env


class Zygote:
    """The process that forks confined workers (``pipeline/boundary/zygote.py``), seen from the parent."""

    def __init__(self) -> None:
        self.scratch = tempfile.mkdtemp(prefix="codearcade-sandbox-")
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.ctl = ours
        self.log_path = os.path.join(self.scratch, "zygote.log")
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "pipeline.boundary.zygote", str(theirs.fileno())], env=worker_environment(self.scratch),
                cwd=self.scratch, pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        theirs.close()
        self.events: dict[int, dict[str, Any]] = {}
        self.next_id = 0
        hello = self._recv(START_TIMEOUT_S)
        if hello is None or hello.get("kind") != "hello":
            tail = Path(self.log_path).read_text(errors="replace").strip().splitlines()[-1:] or ["no output"]
            self.close()
            raise SandboxUnavailable(f"the policy worker process did not start: {tail[0][:300]}")
        self.missing: list[str] = list(hello.get("missing", []))
        if self.missing:
            if not weak_sandbox_allowed():
                self.close()
                raise SandboxUnavailable(
                    f"the policy sandbox needs kernel features this machine lacks: {'; '.join(self.missing)}. "
                    f"Run on Linux >= 5.13 with Landlock and seccomp, as root or with user namespaces (see "
                    f"docs/sandbox.md), or set {WEAK_ENV}=1 to run untrusted policies without them")
        self.warn()

    def warn(self) -> None:
        if self.missing:
            print(f"codearcade: WARNING: weak sandbox ({WEAK_ENV}=1): policy workers run without "
                  f"{'; '.join(self.missing)}", file=sys.stderr)

    def alive(self) -> bool:
        return self.proc.poll() is None and self.ctl.fileno() >= 0

    def _recv(self, timeout: float | None) -> dict[str, Any] | None:
        ready, _, _ = select.select([self.ctl], [], [], timeout)
        if not ready:
            return None
        try:
            data = self.ctl.recv(65536)
        except OSError:
            return None
        if not data:
            return None
        return json.loads(data)

    def pump(self, timeout: float = 0.0) -> None:
        """Read the zygote's reports (``started``, ``exited``) waiting at most ``timeout`` for the first."""
        while True:
            try:
                msg = self._recv(timeout)
            except ValueError:
                return
            if msg is None:
                return
            timeout = 0.0
            if msg.get("id") in self.events:  # reports on tasks already settled are dropped
                self.events[msg["id"]].update(msg)

    def send(self, msg: dict[str, Any], fds: list[int] = ()) -> None:
        socket.send_fds(self.ctl, [json.dumps(msg).encode()], list(fds))

    def start(self, task: str, item: dict[str, Any], limits: dict[str, Any],
              staged: bool = False) -> tuple[int, socket.socket]:
        """Fork a worker for ``task`` and send it ``item``; the task id and the socket its answer comes on.
        A ``staged`` worker sets itself up, then waits for :meth:`go`."""
        self.next_id += 1
        task_id = self.next_id
        self.events[task_id] = {}
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.send({"op": "run", "id": task_id, "task": task, "limits": limits, "staged": staged},
                      [theirs.fileno()])
        except OSError:
            pass  # the zygote died: the worker's socket reads EOF, and the task is recorded as crashed
        finally:
            theirs.close()
        ours.settimeout(60)
        try:
            ours.sendall(wire.json_frame(item))
        except OSError:
            pass  # the worker died before reading: its EOF is reported as a crash
        ours.setblocking(False)
        return task_id, ours

    @staticmethod
    def go(conn: socket.socket) -> None:
        """Let a staged worker run its task (a worker that died meanwhile is seen at its EOF)."""
        try:
            conn.send(b"G")
        except OSError:
            pass

    def kill(self, task_id: int) -> None:
        try:
            self.send({"op": "kill", "id": task_id})
        except OSError:
            pass

    def exit_code(self, task_id: int, wait_s: float = 2.0) -> int | None:
        deadline = time.monotonic() + wait_s
        while "code" not in self.events.get(task_id, {}) and time.monotonic() < deadline and self.alive():
            self.pump(deadline - time.monotonic())
        code = self.events.get(task_id, {}).get("code")
        return code if isinstance(code, int) else None

    def forget(self, task_id: int) -> None:
        self.events.pop(task_id, None)

    def children(self) -> list[int]:
        """The pids of the workers alive now."""
        try:
            with open(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children") as f:
                return [int(p) for p in f.read().split()]
        except OSError:
            return []

    def close(self) -> None:
        try:
            self.ctl.close()
        except OSError:
            pass
        if self.proc.poll() is None:
            try:
                self.proc.wait(2)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(self.scratch, ignore_errors=True)


_zygote: Zygote | None = None
_zygote_pid: int | None = None
_lock = threading.RLock()


def zygote() -> Zygote:
    """This process's zygote, started on first use (and again if it died). Raises SandboxUnavailable."""
    global _zygote, _zygote_pid
    with _lock:
        if _zygote is not None and (_zygote_pid != os.getpid() or not _zygote.alive()):
            if _zygote_pid == os.getpid():
                _zygote.close()
            _zygote = None  # a forked copy of this process must not share its parent's zygote
        if _zygote is None:
            _zygote, _zygote_pid = Zygote(), os.getpid()
        return _zygote


@atexit.register
def stop_zygote() -> None:
    global _zygote
    if _zygote is not None and _zygote_pid == os.getpid():
        _zygote.close()
    _zygote = None


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
    """The worker's :class:`pipeline.boundary.confine.Limits` for an item, as keyword arguments."""


@dataclass
class _Running:
    index: int
    item: Any
    task_id: int
    conn: socket.socket
    begun: float
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
    on_actions: Callable[[int, list[int]], None] | None = None,
) -> Iterator[tuple[int, R]]:
    """Run ``task`` on every item in a confined worker of its own, at most ``workers`` at once; yield
    ``(index, result)`` as each finishes. ``on_actions(index, actions)`` gets the actions an episode reports
    while it plays (checked: a list of small ints), so the caller can verify its score as it goes.

    A worker that dies, raises, sends a malformed answer, or outlives ``time_limit_s(item)`` plus a grace period
    yields ``failed(item, why, timed_out)`` instead. ``started`` is called once the first workers are running,
    so the caller can do its own set-up meanwhile. ``workers=0`` runs the tasks one after another in this
    process (no isolation; for debugging).
    """
    items = list(items)
    if workers <= 0:
        if started is not None:
            started()
        for i, item in enumerate(items):
            yield i, task.local(item, (lambda n, i=i: progress(i, n)) if progress is not None else (lambda n: None))
        return

    zyg = zygote()
    if prepare is not None:
        prepare(zyg)
    pending = deque(enumerate(items))
    busy: dict[int, _Running] = {}  # by fd
    staged: deque[_Running] = deque()
    """The next worker, forked, confined and prepared (policy loaded, environment reset) while the others play:
    the fork of the zygote (~5-20 ms) and ALE's seeded reset (~0.1 s) would otherwise come between one episode
    and the next."""

    def start(staged_: bool) -> _Running:
        i, item = pending.popleft()
        limits = task.limits(item)
        limit = time_limit_s(item)
        if limit is not None and "cpu_s" not in limits:
            limits["cpu_s"] = int(math.ceil(limit + KILL_GRACE_S + 10))
        task_id, conn = zyg.start(task.name, task.encode(item), limits, staged=staged_)
        return _Running(i, item, task_id, conn, time.monotonic())

    def fill() -> None:
        while (staged or pending) and len(busy) < workers:
            if staged:
                run = staged.popleft()
                zyg.go(run.conn)
                run.begun = time.monotonic()
            else:
                run = start(False)
            busy[run.conn.fileno()] = run
        if pending and not staged:
            staged.append(start(True))

    def end(run: _Running, kill: bool = False) -> None:
        del busy[run.conn.fileno()]
        run.conn.close()
        if kill:
            zyg.kill(run.task_id)

    def died(run: _Running) -> R:
        code = zyg.exit_code(run.task_id)
        zyg.forget(run.task_id)
        if code == -signal.SIGXCPU:
            return failed(run.item, "worker exceeded its CPU-time limit", True)
        how = "unknown exit status" if code is None else (f"signal {-code}" if code < 0 else f"exit code {code}")
        return failed(run.item, f"worker process died ({how}) before reporting", False)

    def handle(run: _Running, frames: list[tuple[bytes, bytes]]) -> R | None:
        for kind, payload in frames:
            if run.result is not None:
                if kind != b"A":
                    raise wire.BadMessage("a JSON message where an Arrow table was expected")
                run.tables.append(payload)
            else:
                if kind != b"J":
                    raise wire.BadMessage("an Arrow table before the result")
                msg = wire.parse_message(payload)  # kind and fields checked
                if msg["kind"] == "actions":
                    if on_actions is not None:
                        on_actions(run.index, msg["actions"])
                    continue
                if msg["kind"] == "progress":
                    if progress is not None:
                        progress(run.index, msg["n"])
                    continue
                if msg["kind"] == "error":
                    return failed(run.item, f"worker failed: {msg['error']}", False)
                run.result = msg
            if run.result is not None:
                wanted = task.tables(run.result)
                if len(run.tables) > wanted:
                    raise wire.BadMessage("more Arrow tables than announced")
                if len(run.tables) == wanted:
                    return task.decode(run.item, run.result, run.tables)
        return None

    try:
        fill()
        if started is not None:
            started()
        while pending or staged or busy:
            fill()
            finished: list[tuple[int, R]] = []
            ready, _, _ = select.select(list(busy) + [zyg.ctl.fileno()], [], [], 0.5)
            if zyg.ctl.fileno() in ready:
                zyg.pump()
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
                except Exception as exc:  # noqa: BLE001 - whatever a worker sends, this process goes on
                    if not isinstance(exc, wire.BadMessage):
                        exc = f"{type(exc).__name__}: {str(exc)[:300]}"
                    end(run, kill=True)
                    zyg.forget(run.task_id)
                    finished.append((run.index, failed(run.item, f"the worker sent a malformed message: {exc}",
                                                       False)))
                    continue
                if result is not None:
                    end(run)
                    zyg.forget(run.task_id)
                    finished.append((run.index, result))
            now = time.monotonic()
            for run in list(busy.values()):
                limit = time_limit_s(run.item)
                if limit is not None and now - run.begun > limit + KILL_GRACE_S:
                    end(run, kill=True)
                    zyg.forget(run.task_id)
                    finished.append((run.index, failed(run.item, f"worker killed after {now - run.begun:.0f} s "
                                                                 f"(time limit {limit:g} s)", True)))
            if not zyg.alive():
                for run in list(busy.values()):
                    end(run)
                    finished.append((run.index, failed(run.item, "the worker's zygote process died", False)))
            fill()  # before handing results out, so that workers play while the caller writes them
            yield from finished
    finally:
        for run in list(busy.values()):
            end(run, kill=True)
            zyg.forget(run.task_id)
        for run in staged:
            run.conn.close()  # EOF instead of G: the worker exits without running anything
            zyg.forget(run.task_id)


def run_json_task(name: str, item: dict[str, Any], local: Callable[[dict[str, Any]], dict[str, str | None]],
                  time_limit_s: float, memory_mb: int | None = 4096, workers: int = 1) -> tuple[bool, Any]:
    """Run a task whose answer is ``{"kind": "result", FIELD: str | None, ...}`` (``local`` returns the fields)
    in a confined worker: (True, the fields) when it answered, (False, why not) when it crashed, misbehaved or
    timed out."""
    (result,) = run_json_tasks(name, [item], local, lambda it: time_limit_s, lambda it: memory_mb, workers)
    return result


def run_json_tasks(name: str, items: list[dict[str, Any]], local: Callable[[dict[str, Any]], dict[str, str | None]],
                   time_limit_s: Callable[[dict[str, Any]], float],
                   memory_mb: Callable[[dict[str, Any]], int | None] = lambda item: 4096,
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
