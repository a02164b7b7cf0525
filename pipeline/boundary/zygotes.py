"""The parent's handle on the zygote processes, started once per process, and the game hosts kept between calls.
Running tasks on them is ``pipeline/boundary/workers.py``'s job.

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
  hosts idle at the end of one call of :func:`~pipeline.boundary.workers.run_tasks` are kept for the next call
  that plays the same task on the same environments (the optimizer assesses many times), and exit when the block
  ends.

A missing kernel feature stops the run with a one-line error unless ``CODEARCADE_ALLOW_WEAK_SANDBOX=1`` (then a
warning is printed on every run).
"""

from __future__ import annotations

import atexit
import json
import os
import re
import select
import socket
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from pipeline.boundary import wire
from pipeline.boundary.confine import SandboxUnavailable, WEAK_ENV, weak_sandbox_allowed
from pipeline.boundary.mounts import SCRATCH_PREFIX, remove_tree, sweep_stale_scratch

GO_TIMEOUT_S = 30.0
"""How long the parent waits for room to send a staged worker its go-ahead (behind a large task it is reading)."""
START_TIMEOUT_S = 180.0
"""How long the zygote may take to import the environment stack and say hello."""

ROOT = Path(__file__).resolve().parents[2]
_ALLOWED_ENV = re.compile(r"^(PATH|LANG|LANGUAGE|LC_[A-Z]+|TZ|TERM|OMP_[A-Z_]+|OPENBLAS_[A-Z_]+|MKL_[A-Z_]+|"
                          r"SDL_[A-Z_]+|ALE_[A-Z_]+|PYTHONHASHSEED|PYTHONDONTWRITEBYTECODE|CODEARCADE_GAME_MODULES)$")
_SECRET_ENV = re.compile(r"(KEY|TOKEN|SECRET|PASSWORD|PASSWD|CREDENTIAL|AUTH|COOKIE|SESSION)", re.IGNORECASE)


SINGLE_THREADED = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""Both zygotes' numeric libraries start no thread pool: a policy process may not start threads (seccomp), and a
game host plays on one core beside its policy process, where a pool's threads would only spin (the game zygote's
OpenBLAS pools, numpy's and scipy's, spun ~175 ms of CPU as it started, beside the command's own start)."""


def worker_environment(home: str) -> dict[str, str]:
    """A zygote's whole environment: an allow-list of harmless variables, never a secret."""
    env = {k: v for k, v in os.environ.items() if _ALLOWED_ENV.match(k) and not _SECRET_ENV.search(k)}
    paths = [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    env.update(HOME=home, TMPDIR=home, PYTHONPATH=os.pathsep.join(dict.fromkeys(paths)),
               PYTHONDONTWRITEBYTECODE="1")
    env.update(SINGLE_THREADED)
    if weak_sandbox_allowed():
        env[WEAK_ENV] = "1"
    return env


class Zygote:
    """A process that forks workers (``pipeline/boundary/zygote.py``) in one role (``policy`` or ``game``), seen
    from the parent."""

    def __init__(self, role: str = "policy", greet: bool = True) -> None:
        """Start the zygote; with ``greet``, wait for its hello (:meth:`greet`), else the caller does later."""
        self.role = role
        self.greeted = False
        self.scratch = tempfile.mkdtemp(prefix=SCRATCH_PREFIX)
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.ctl = ours
        self.log_path = os.path.join(self.scratch, "zygote.log")
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "pipeline.boundary.zygote", role, str(theirs.fileno())],
                env=worker_environment(self.scratch), cwd=self.scratch, pass_fds=[theirs.fileno()],
                stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        theirs.close()
        self.events: dict[int, dict[str, Any]] = {}
        self.next_id = 0
        if greet:
            self.greet()

    def greet(self) -> None:
        """Wait for the zygote's hello (it says it once it has imported its tasks' modules): raise
        SandboxUnavailable, the zygote closed, if it did not start or lacks what the sandbox needs."""
        if self.greeted:
            return
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
        self.greeted = True
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
    def go(conn: socket.socket, cpu: int | None = None, within_s: float = GO_TIMEOUT_S) -> None:
        """Let a staged worker run its task, on ``cpu`` if given (a worker that died meanwhile is seen at its EOF).
        The go-ahead waits for room behind the task, which the worker may not have read yet: a task that filled
        the socket's buffer (a policy file near its size cap, as JSON) left no room, the go-ahead was dropped, and
        the episode waited out its time limit with no step played. A worker that does not read its task within
        ``within_s`` is ended by that limit."""
        frame = memoryview(wire.GO.pack(b"G", -1 if cpu is None else cpu))
        deadline = time.monotonic() + within_s
        while frame:
            try:
                frame = frame[conn.send(frame):]
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                select.select([], [conn], [], left)
            except OSError:
                return

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
        self.let_go()
        self.wait_gone()

    def let_go(self) -> None:
        """Tell it to end (its workers end with it), without waiting: :meth:`wait_gone` does."""
        try:
            self.ctl.close()
        except OSError:
            pass
        if not self.greeted and self.proc.poll() is None:  # still starting: it has no workers, and it would read
            self.proc.kill()  # the closed socket only once its imports are done

    def wait_gone(self) -> None:
        """Wait for it to end (killed after 2 s), and remove its scratch directory."""
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
    """This process's zygote of ``role``, started on first use (and again if it died), greeted. Raises
    SandboxUnavailable."""
    with _lock:
        existing = _started(role)
        try:
            existing.greet()
        except SandboxUnavailable:
            _zygotes.pop(role, None)
            raise
        return existing


def start_zygotes(*roles: str) -> None:
    """Start this process's zygotes of ``roles`` that are not running, without waiting for them: a command that
    will check a policy and then play it (``eval``, ``optimize``) starts its game zygote beside the policy zygote
    (each ~0.4-0.6 s of imports here, side by side on two cores) rather than after it. :func:`zygote` waits for
    the hello, and says what kept one from starting."""
    with _lock:
        for role in roles:
            _started(role)


def _started(role: str) -> Zygote:
    """This process's zygote of ``role``, started now if it is not running (not waited for); under ``_lock``."""
    global _zygotes_pid
    if _zygotes_pid != os.getpid():
        _zygotes.clear()  # a forked copy of this process must not share its parent's zygotes
        _zygotes_pid = os.getpid()
    existing = _zygotes.get(role)
    if existing is not None and not existing.alive():
        existing.close()
        existing = None
    if existing is None:
        if not _zygotes:  # the first of this process: sweep what zygotes killed with their parents left
            sweep_stale_scratch()
        existing = _zygotes[role] = Zygote(role, greet=False)
    return existing


@atexit.register
def stop_zygote() -> None:
    """Close this process's zygotes (their workers end with them). A Ctrl-C that lands meanwhile kills what is left
    instead of waiting for it: the process is ending anyway (a batch's run pressed as it finished printed
    "Exception ignored" and a traceback into its log, from the wait for its zygote)."""
    mine = _zygotes_pid == os.getpid()
    closing = list(_zygotes.values()) if mine else []
    try:
        KEPT.let_go()
        with _lock:  # a thread still starting one (a server's request at exit) must not change the dict mid-loop
            closing = list(_zygotes.values()) if mine else []
            _zygotes.clear()
        for zyg in closing:  # all told first, then waited for: they end side by side
            zyg.let_go()
        for zyg in closing:
            zyg.wait_gone()
    except KeyboardInterrupt:
        for zyg in closing:
            try:
                zyg.proc.kill()
            except OSError:
                pass


ZYGOTE_USE = threading.RLock()
"""Held by the thread whose tasks the zygotes are running: their requests and answers share one socket each."""


@dataclass
class _KeptHosts:
    """Game hosts idle at the end of a :func:`run_tasks` call, kept for the next (inside :func:`keep_hosts`).
    Its own lock, never :data:`ZYGOTE_USE`: a command that ends while another thread still plays (the proposal
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
        :data:`ZYGOTE_USE`."""
        with self.lock:
            if self.zygote is zyg and self.key == key and self.pid == os.getpid():
                hosts, self.hosts = self.hosts, []
                return hosts
            self._let_go()
            return []

    def keep(self, zyg: Zygote, key: tuple, hosts: list[tuple[int, socket.socket]]) -> bool:
        """Keep ``hosts`` for the next call, if a :func:`keep_hosts` block is still open (False: the caller lets them
        go); the caller holds :data:`ZYGOTE_USE`."""
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
        # read under ZYGOTE_USE); otherwise the record stays, a few bytes, until the zygote's next report on it
        mine = self.zygote is not None and self.pid == os.getpid() and ZYGOTE_USE.acquire(blocking=False)
        try:
            for task_id, conn in hosts:
                conn.close()
                if mine:
                    self.zygote.forget(task_id)
        finally:
            if mine:
                ZYGOTE_USE.release()
        self.zygote = self.key = None


KEPT = _KeptHosts()


@contextmanager
def keep_hosts() -> Iterator[None]:
    """Keep the game hosts idle at the end of each :func:`run_tasks` call for the next call in the block, instead
    of letting them exit (the module docstring); when the outermost block ends, they exit. A host runs no policy
    code: what one episode leaves in it is the environment, reset with the next episode's seed, as between the
    episodes of one call. Forking a host costs its first episode 11-17 ms before it can start, and ~35 ms of CPU
    with its copy-on-write faults (docs/benchmarks.md)."""
    with KEPT.lock:
        KEPT.depth += 1
    try:
        yield
    finally:
        with KEPT.lock:
            KEPT.depth -= 1
            if KEPT.depth == 0:
                KEPT._let_go()
