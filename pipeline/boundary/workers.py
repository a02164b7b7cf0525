"""Run tasks in worker processes, policy code always behind the operating-system boundary, or in-process with
``workers=0`` (for debugging; no isolation at all). The tasks themselves (an episode, a candidate's checks) are
``pipeline/play``'s: :class:`Task` says how one goes out and comes back, :func:`run_tasks` runs many.

Policy code never runs in this process, nor in any process that holds this one's memory or environment
(API keys, the store path), nor in one that holds the emulator. Two :class:`Zygote` processes are started once
per process with ``subprocess`` (``pipeline/boundary/zygote.py``), fresh interpreters with an allow-listed
environment (:func:`worker_environment`), each forking one worker per task so that every task starts from the same
clean state (nothing a policy changes, module attributes included, survives into the next):

- the **policy** zygote's workers run policy code, confined by the kernel before it loads
  (``pipeline/boundary/confine.py``: no exec, no fork, no threads, no network, no writes outside a scratch
  directory, no reads of the emulator or outside Python's and the project's files, nothing that names another
  process, rlimits), in pid, IPC and network namespaces of their own;
- the **game** zygote's workers are game hosts: the environment, the score, the step log, live recordings. A
  host whose episode is done is handed the next one of the same call (with a new policy process) rather than
  forked again: no policy code runs there, and the fork and teardown cost more than the episode's reset.
  Inside :func:`keep_hosts` (a command's whole run: ``codearcade`` and a batch's run processes enter it), the
  hosts idle at the end of one call of :func:`run_tasks` are kept for the next call that plays the same task on
  the same environments (the optimizer assesses many times), and exit when the block ends.

An episode is a *paired* task: a host and a policy process joined by a socket of their own, one round trip per
step, pinned to one CPU (a round trip across cores costs tens of microseconds here, on one a few: NOTES.md).
The next episode's pair is forked and prepared while the current one plays (``staged``): the host resets its
environment (a few ms without sticky actions; with them ALE reloads the ROM, ~0.15 s) and its policy process
loads the policy, so neither the forks nor the reset sit between episodes. A missing kernel feature stops the
run with a one-line error unless ``CODEARCADE_ALLOW_WEAK_SANDBOX=1`` (then a warning is printed on every run).

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
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Hashable, Iterable, Iterator, TypeVar

from pipeline.boundary import wire
from pipeline.boundary.confine import SandboxUnavailable, WEAK_ENV, weak_sandbox_allowed
from pipeline.boundary.mounts import remove_tree
from pipeline.settings import EpisodeLimits

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


SINGLE_THREADED = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""A policy process may not start threads (seccomp): numeric libraries must not try."""


def worker_environment(home: str, role: str = "policy") -> dict[str, str]:
    """A zygote's whole environment: an allow-list of harmless variables, never a secret."""
    env = {k: v for k, v in os.environ.items() if _ALLOWED_ENV.match(k) and not _SECRET_ENV.search(k)}
    paths = [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    env.update(HOME=home, TMPDIR=home, PYTHONPATH=os.pathsep.join(dict.fromkeys(paths)),
               PYTHONDONTWRITEBYTECODE="1")
    if role == "policy":
        env.update(SINGLE_THREADED)
    if weak_sandbox_allowed():
        env[WEAK_ENV] = "1"
    return env


class Zygote:
    """A process that forks workers (``pipeline/boundary/zygote.py``) in one role (``policy`` or ``game``), seen
    from the parent."""

    def __init__(self, role: str = "policy") -> None:
        self.role = role
        self.scratch = tempfile.mkdtemp(prefix="codearcade-sandbox-")
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.ctl = ours
        self.log_path = os.path.join(self.scratch, "zygote.log")
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "pipeline.boundary.zygote", role, str(theirs.fileno())],
                env=worker_environment(self.scratch, role), cwd=self.scratch, pass_fds=[theirs.fileno()],
                stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        theirs.close()
        self.events: dict[int, dict[str, Any]] = {}
        self.next_id = 0
        hello = self._recv(START_TIMEOUT_S)
        if hello is None or hello.get("kind") != "hello":
            tail = Path(self.log_path).read_text(errors="replace").strip().splitlines()[-1:] or ["no output"]
            self.close()
            raise SandboxUnavailable(f"the {self.role} worker process did not start: {tail[0][:300]}")
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

    def start(self, task: str, item: dict[str, Any], limits: dict[str, Any], staged: bool = False,
              extra: socket.socket | None = None) -> tuple[int, socket.socket]:
        """Fork a worker for ``task`` and send it ``item``; the task id and the socket its answer comes on.
        A ``staged`` worker sets itself up, then waits for :meth:`go`. ``extra``: a second socket handed to the
        worker (a host's, to its policy process)."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        task_id = self._run(task, theirs, limits, staged, extra)
        ours.settimeout(60)
        try:
            ours.sendall(wire.json_frame(item))
        except OSError:
            pass  # the worker died before reading: its EOF is reported as a crash
        ours.setblocking(False)
        return task_id, ours

    def attach(self, task: str, sock: socket.socket, limits: dict[str, Any]) -> int:
        """Fork a worker for ``task`` on ``sock``, a socket whose other end is not this process's (a policy process
        and its host): the worker reads its task from there and answers there. The task id."""
        return self._run(task, sock, limits, False, None)

    def _run(self, task: str, sock: socket.socket, limits: dict[str, Any], staged: bool,
             extra: socket.socket | None) -> int:
        self.next_id += 1
        task_id = self.next_id
        self.events[task_id] = {}
        try:
            self.send({"op": "run", "id": task_id, "task": task, "limits": limits, "staged": staged},
                      [sock.fileno()] + ([extra.fileno()] if extra is not None else []))
        except OSError:
            pass  # the zygote died: the worker's socket reads EOF, and the task is recorded as crashed
        finally:
            sock.close()
            if extra is not None:
                extra.close()
        return task_id

    @staticmethod
    def hand(conn: socket.socket, item: dict[str, Any], extra: socket.socket) -> bool:
        """Give a worker whose task is done (a game host: ``serves_many``) the next one, ``item`` with ``extra``, a
        socket for it (a host's, to its new policy process; the caller closes its copy). False if the worker is
        gone."""
        conn.settimeout(60)
        try:
            socket.send_fds(conn, [wire.NEXT], [extra.fileno()])
            conn.sendall(wire.json_frame(item))
            return True
        except OSError:
            return False
        finally:
            conn.setblocking(False)

    @staticmethod
    def go(conn: socket.socket, cpu: int | None = None) -> None:
        """Let a staged worker run its task, on ``cpu`` if given (a worker that died meanwhile is seen at its EOF)."""
        try:
            conn.send(wire.GO.pack(b"G", -1 if cpu is None else cpu))
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

    def count(self, timeout: float = 5.0) -> int | None:
        """How many workers of this zygote are alive now (None: it did not say)."""
        try:
            self.send({"op": "count"})
        except OSError:
            return None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            msg = self._recv(deadline - time.monotonic())
            if msg is None:
                return None
            if msg.get("kind") == "count":
                return int(msg["workers"])
            if msg.get("id") in self.events:
                self.events[msg["id"]].update(msg)
        return None

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
        remove_tree(self.scratch)  # never raises, however deep what a worker left (a weak sandbox's scratch)


_zygotes: dict[str, Zygote] = {}
_zygotes_pid: int | None = None
_lock = threading.RLock()


def zygote(role: str = "policy") -> Zygote:
    """This process's zygote of ``role``, started on first use (and again if it died). Raises SandboxUnavailable."""
    global _zygotes_pid
    with _lock:
        if _zygotes_pid != os.getpid():
            _zygotes.clear()  # a forked copy of this process must not share its parent's zygotes
            _zygotes_pid = os.getpid()
        existing = _zygotes.get(role)
        if existing is not None and not existing.alive():
            existing.close()
            existing = None
        if existing is None:
            existing = _zygotes[role] = Zygote(role)
        return existing


@atexit.register
def stop_zygote() -> None:
    """Close this process's zygotes (their workers end with them)."""
    _KEPT.let_go()
    if _zygotes_pid == os.getpid():
        for zyg in _zygotes.values():
            zyg.close()
    _zygotes.clear()


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
) -> Iterator[tuple[int, R]]:
    """Run ``task`` on every item in a worker of its own (a paired task: a host and a policy process), at most
    ``workers`` at once; yield ``(index, result)`` as each finishes.

    A worker that dies, raises, sends a malformed answer, or outlives ``time_limit_s(item)`` plus a grace period
    yields ``failed(item, why, timed_out)`` instead. ``started`` is called once the first workers are running,
    so the caller can do its own set-up meanwhile. ``prepare(zygote)`` may warm the (host's) zygote first.
    ``workers=0`` runs the tasks one after another in this process (no isolation; for debugging).
    ``hosts_key`` (a paired task): what its hosts were prepared for (the environments ``prepare`` builds); inside
    :func:`keep_hosts`, the hosts idle at the end are kept for the next call with the same task and key.
    """
    items = list(items)
    if workers <= 0:
        if started is not None:
            started()
        for i, item in enumerate(items):
            yield i, task.local(item, (lambda n, i=i: progress(i, n)) if progress is not None else (lambda n: None))
        return
    with _ZYGOTE_USE:  # the zygotes serve one caller at a time (the proposal pool's threads share them)
        yield from _run_tasks(task, items, workers, failed, time_limit_s, progress, started, prepare, hosts_key)


_ZYGOTE_USE = threading.RLock()
"""Held by the thread whose tasks the zygotes are running: their requests and answers share one socket each."""


@dataclass
class _KeptHosts:
    """Game hosts idle at the end of a :func:`run_tasks` call, kept for the next (inside :func:`keep_hosts`).
    Its own lock, never :data:`_ZYGOTE_USE`: a command that ends while another thread still plays (the proposal
    pool's) lets its kept hosts go without waiting for that thread."""

    depth: int = 0
    """How many :func:`keep_hosts` blocks are open: hosts are kept only while one is."""
    zygote: Zygote | None = None
    """The game zygote the hosts are workers of (one that died and was started again has none of them)."""
    key: tuple | None = None
    """(task name, the call's ``hosts_key``): a host is handed only tasks of the kind it was forked for, on the
    environments its zygote had built when it forked it."""
    pid: int = 0
    hosts: list[tuple[int, socket.socket]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def take(self, zyg: Zygote, key: tuple) -> list[tuple[int, socket.socket]]:
        """The hosts kept for a call of ``key`` on ``zyg`` (the others are let go); the caller holds
        :data:`_ZYGOTE_USE`."""
        with self.lock:
            if self.zygote is zyg and self.key == key and self.pid == os.getpid():
                hosts, self.hosts = self.hosts, []
                return hosts
            self._let_go()
            return []

    def keep(self, zyg: Zygote, key: tuple, hosts: list[tuple[int, socket.socket]]) -> bool:
        """Keep ``hosts`` for the next call, if a :func:`keep_hosts` block is still open (False: the caller lets them
        go); the caller holds :data:`_ZYGOTE_USE`."""
        with self.lock:
            if self.depth == 0:
                return False
            self._let_go()
            self.zygote, self.key, self.pid, self.hosts = zyg, key, os.getpid(), hosts
            return True

    def let_go(self) -> None:
        with self.lock:
            self._let_go()

    def _let_go(self) -> None:
        """EOF to each kept host instead of a next task: it exits (a forked copy of this process only closes its
        copies of the sockets)."""
        hosts, self.hosts = self.hosts, []
        # the zygote's record of each is dropped only by a thread that may use the zygote now (its reports are
        # read under _ZYGOTE_USE); otherwise the record stays, a few bytes, until the zygote's next report on it
        mine = self.zygote is not None and self.pid == os.getpid() and _ZYGOTE_USE.acquire(blocking=False)
        try:
            for task_id, conn in hosts:
                conn.close()
                if mine:
                    self.zygote.forget(task_id)
        finally:
            if mine:
                _ZYGOTE_USE.release()
        self.zygote = self.key = None


_KEPT = _KeptHosts()


@contextmanager
def keep_hosts() -> Iterator[None]:
    """Keep the game hosts idle at the end of each :func:`run_tasks` call for the next call in the block, instead
    of letting them exit (the module docstring); when the outermost block ends, they exit. A host runs no policy
    code: what one episode leaves in it is the environment, reset with the next episode's seed, as between the
    episodes of one call. Forking a host costs its first episode 11-17 ms before it can start, and ~35 ms of CPU
    with its copy-on-write faults (docs/benchmarks.md)."""
    with _KEPT.lock:
        _KEPT.depth += 1
    try:
        yield
    finally:
        with _KEPT.lock:
            _KEPT.depth -= 1
            if _KEPT.depth == 0:
                _KEPT._let_go()


def _run_tasks(task: Task, items: list, workers: int, failed, time_limit_s, progress, started,
               prepare, hosts_key) -> Iterator[tuple[int, Any]]:
    """:func:`run_tasks` with worker processes (under :data:`_ZYGOTE_USE`)."""
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

    keeping = policies is not None and hosts_key is not None and _KEPT.depth > 0  # re-checked under its lock
    kept_key = (task.name, hosts_key)
    idle: list[tuple[int, socket.socket]] = _KEPT.take(zyg, kept_key) if keeping else []
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

    def fill() -> None:
        while (staged or pending) and len(busy) < workers:
            if staged:
                run, waiting = staged.popleft(), True
            else:
                run, waiting = start(False), policies is not None  # a host always waits for its go-ahead
            run.cpu = free_cpu()
            if waiting:
                zyg.go(run.conn, run.cpu)
            run.begun = time.monotonic()
            busy[run.conn.fileno()] = run
        if pending and not staged:
            staged.append(start(True))

    def end(run: _Running, kill: bool = False) -> None:
        del busy[run.conn.fileno()]
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
        del busy[run.conn.fileno()]
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
                    result = task.decode(run.item, run.result, run.tables)
                    if policies is not None and task.after_pair is not None:
                        result = task.after_pair(result, lambda: policies.exit_code(run.policy_id, wait_s=1.0))
                    return result
        return None

    controls = [zyg] + ([policies] if policies is not None else [])
    try:
        fill()
        if started is not None:
            started()
        while pending or staged or busy:
            fill()
            finished: list[tuple[int, R]] = []
            ready, _, _ = select.select(list(busy) + [z.ctl.fileno() for z in controls], [], [], 0.5)
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
                except Exception as exc:  # noqa: BLE001 - whatever a worker sends, this process goes on
                    if not isinstance(exc, wire.BadMessage):
                        exc = f"{type(exc).__name__}: {str(exc)[:300]}"
                    end(run, kill=True)
                    settle(run)
                    finished.append((run.index, failed(run.item, f"the worker sent a malformed message: {exc}",
                                                       False)))
                    continue
                if result is not None:
                    done(run)
                    finished.append((run.index, result))
            now = time.monotonic()
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
        for run in list(busy.values()):
            end(run, kill=True)
            settle(run)
        for run in staged:
            run.conn.close()  # EOF instead of G: the worker exits without running anything
            if policies is not None and run.policy_id is not None:
                policies.kill(run.policy_id)
            settle(run)
        # for the next call (keep_hosts); they exit when its block ends
        if not (keeping and zyg.alive() and _KEPT.keep(zyg, kept_key, idle)):
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
