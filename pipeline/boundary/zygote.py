"""The zygotes: clean processes that fork one worker per task (``python -m pipeline.boundary.zygote ROLE FD``).

The parent (``pipeline/boundary/zygotes.py``) starts two, each with a fresh interpreter, an environment
reduced to an allow-list (no API keys, no store path), its scratch directory as HOME and cwd, and one end of a
Unix ``SOCK_SEQPACKET`` socket pair as its only inherited descriptor. Each serves one :data:`ROLES` entry:

- ``policy``: untrusted code runs in its workers (an episode's policy, the checks of a candidate). It imports
  only what a policy needs (never the emulator: ``pipeline/boundary/preload.py``), takes new network, IPC and
  pid namespaces (it is pid 1 of its own, the init of every worker: when it ends, the kernel ends them all),
  mounts a small tmpfs over its scratch directory in a mount namespace of its own, probes the features of
  ``pipeline/boundary/confine.py`` in a throwaway child, and confines every worker before it loads any code. Each
  worker mounts a tmpfs of its own as its scratch directory (``mounts.worker_scratch``: bounded in bytes and
  inodes), which the zygote detaches when the worker has ended: nothing a policy left there is ever walked.
- ``game``: the game hosts (``pipeline/play/episodes.py``: ``host`` plays one episode, ``game`` the episodes of one
  continued game): the emulator and everything that computes a score. A host whose task is done waits for the
  next (:data:`wire.NEXT`, ``Role.serves_many``) instead of exiting.
  No policy code is ever loaded there. It builds each environment once (``prepare``), so that hosts start warm,
  and keeps the machine's network (a host may stream a live Rerun recording); new IPC and pid namespaces.

Both say hello with what is missing, then serve:

- ``{"op": "prepare", "envs": [[game, sticky, noop_max, one_life, observation], ...]}`` (``game``): build those environments
  once (hosts inherit them built);
- ``{"op": "run", "id", "task", "limits", "staged"}`` with one or two sockets passed alongside (SCM_RIGHTS): fork
  a worker that sends stdout/stderr to /dev/null, confines itself (role ``policy``:
  :func:`pipeline.boundary.confine.confine`), reads its task as a JSON frame from the first socket, prepares (a
  host has its policy process, on the second socket, load the policy while it resets its environment), waits for
  a go-ahead (``G`` and the CPU to run on) if ``staged`` (the executor sets up the next episode while the current
  one plays), runs the task and writes its answer as frames (``pipeline/boundary/wire.py``); answered with
  ``{"kind": "started", "id", "pid"}``;
- ``{"op": "kill", "id"}``: SIGKILL that worker; ``{"op": "count"}``: how many workers are alive.

Every worker that ends is reported as ``{"kind": "exited", "id", "code"}`` (negative: killed by that signal)
and its scratch directory removed (:func:`_forget_scratch`, which cannot raise: the zygote never runs code that what
a policy left behind can make fail; other episodes depend on it). When the parent goes away (EOF on the socket) the zygote kills its workers
and exits; workers die with the zygote (PDEATHSIG, and the pid namespace). Each policy worker is a fresh fork: no
policy or module state survives from one task to the next.
"""

from __future__ import annotations

import gc
import importlib
import json
import os
import selectors
import signal
import socket
import sys
import traceback
from dataclasses import dataclass
from typing import Any, Callable

from pipeline.boundary import confine, mounts, namespaces, view, wire

MAX_CONTROL = 64 * 1024


def _send(ctl: socket.socket, obj: dict[str, Any]) -> None:
    ctl.sendall(json.dumps(obj).encode())


# ------------------------------------------------------------------------------------------ worker tasks


@dataclass(frozen=True)
class Role:
    """What a zygote loads, how its workers are confined, and the tasks they run."""

    tasks: dict[str, tuple[str, bool]]
    """Per task name: the function that does it, by module path (the tasks live in ``pipeline/play`` and here:
    the boundary runs play's without importing them), and whether it prepares itself: ``fn(item, fd, extra_fd)``
    prepares in the worker (before a staged worker's go-ahead) and returns what runs the task on a CPU and writes
    its answer on ``fd``; otherwise ``fn(item)`` returns the text fields of one result message. Their modules are
    imported once, in the zygote (``preload``)."""
    confined: bool
    """Workers run untrusted code: confined by the kernel (``confine.py``) before it loads."""
    offline: bool
    """No network: the zygote takes a new, empty network namespace that every worker inherits."""
    no_emulator: bool
    """The zygote must never load the emulator stack (checked after its preload)."""
    serves_many: bool = False
    """A worker, its task done, may be handed the next one (:data:`wire.NEXT`) instead of exiting: game hosts, where no
    policy code runs and nothing but the environment (reset with each episode's seed) carries over. Forking a host
    from the game zygote and tearing it down cost ~20 ms of CPU per episode, against a reset's few. Never a role
    whose workers run policy code: each of those is a fresh fork."""


ROLES: dict[str, Role] = {
    "policy": Role(tasks={"policy": ("pipeline.boundary.policy:policy_task", True),
                          "check": ("pipeline.play.validate:check_here", False),
                          "vet": ("pipeline.play.validate:vet_and_check_here", False)},
                   confined=True, offline=True, no_emulator=True),
    "game": Role(tasks={"host": ("pipeline.play.episodes:host_task", True),
                        "game": ("pipeline.play.episodes:game_host_task", True)},
                 confined=False, offline=False, no_emulator=False, serves_many=True),
}


def _task(role: Role, name: str, item: dict[str, Any], fd: int,
          extra_fd: int | None) -> Callable[[int | None], bool | None]:
    """What runs task ``name`` on ``item`` and writes its answer on ``fd`` (prepared already, if it prepares); it
    may return False: its process is not to serve another task (``Role.serves_many``)."""
    path, prepares = role.tasks[name]
    module, _, attr = path.partition(":")
    function = getattr(importlib.import_module(module), attr)  # preloaded: no file is read here
    if prepares:
        return function(item, fd, extra_fd)
    return lambda cpu: wire.write_all(fd, wire.json_frame({"kind": "result", **function(item)}))


MAX_TASK = 64 * 2**20
"""The largest task frame a worker reads (a task holds a policy's text, or a game's episodes)."""


def _read_task(fd: int) -> dict[str, Any]:
    _kind, payload = wire.read_frame(fd, limit=MAX_TASK)
    return json.loads(payload)


def _worker(fds: list[int], msg: dict[str, Any], zygote_pid: int, scratch_base: str, role: Role,
            strict: bool, own_scratch: bool = False, interrupt: Any = signal.SIG_DFL) -> None:
    """In the forked worker: set up, confine (role ``policy``), run the task; never returns. ``fds[0]`` carries the
    task and its answer; a host's ``fds[1]`` is its policy process's socket. ``own_scratch``: mount a tmpfs of its
    own on its scratch directory (the zygote has a mount namespace of its own); failing that, the task fails.
    ``interrupt``: its SIGINT, the command's (ignored where the command ignores it)."""
    code = 0
    fd = fds[0]
    try:
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, interrupt)
        if not role.confined:  # a host outlives its policy process's socket: a write there is an error, not death
            signal.signal(signal.SIGPIPE, signal.SIG_IGN)
        namespaces.die_with_parent(zygote_pid)
        keep = sorted(fds + (confine.view_rule_descriptors() if role.confined else []))  # those closed once confined
        low = 3
        for kept in keep:
            os.closerange(low, kept)
            low = kept + 1
        os.closerange(low, 1 << 30)  # close_range(2): cheap whatever the bound
        scratch = os.path.join(scratch_base, f"w{int(msg['id'])}")
        os.makedirs(scratch, exist_ok=True)
        if own_scratch:
            mounts.worker_scratch(scratch)
        os.chdir(scratch)
        os.environ["HOME"] = os.environ["TMPDIR"] = scratch
        devnull = os.open("/dev/null", os.O_RDWR)
        for target in (0, 1, 2):
            os.dup2(devnull, target)
        os.close(devnull)
        if role.confined:  # before the task is read: its text (a policy's) is parsed confined, and a policy worker
            # confines itself while its host still resets the environment
            limits = confine.Limits(**msg["limits"])
            limits.write_paths = [scratch]  # nothing else, ever: recordings are written by the game host
            confine.confine(limits, strict=strict)
        item = _read_task(fd)
        extra_fd = fds[1] if len(fds) > 1 else None
        anywhere = os.sched_getaffinity(0)
        while True:
            run = _task(role, msg["task"], item, fd, extra_fd)  # a policy loads here
            cpu = None
            if msg.get("staged"):
                go = os.read(fd, wire.GO.size)
                if len(go) != wire.GO.size or go[:1] != b"G":
                    return  # staged ahead of time (set up, prepared while another task ran), then not needed
                cpu = wire.GO.unpack(go)[1]
                cpu = None if cpu < 0 else cpu
            if cpu is not None:
                try:
                    os.sched_setaffinity(0, {cpu})  # the host and its policy process share one core (NOTES.md)
                except OSError:
                    pass
            again = run(cpu)
            if not role.serves_many or again is False:  # a task may say its process should not serve another
                return
            try:
                os.sched_setaffinity(0, anywhere)  # the next task prepares while another pair holds that core
            except OSError:
                pass
            sock = socket.socket(fileno=os.dup(fd))
            try:
                data, passed, _flags, _addr = socket.recv_fds(sock, len(wire.NEXT), 1)
            finally:
                sock.close()
            if data != wire.NEXT or len(passed) != 1:
                for unexpected in passed:
                    os.close(unexpected)
                return  # EOF: no more tasks
            extra_fd = passed[0]
            item = _read_task(fd)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent as plain text
        code = 1
        try:
            last = traceback.format_exception_only(type(exc), exc)[-1].strip()
            wire.write_all(fd, wire.json_frame({"kind": "error", "error": last[:wire.MAX_TEXT]}))
        except BaseException:  # noqa: BLE001
            pass
    finally:
        os._exit(code)


# --------------------------------------------------------------------------------------------- the zygote


def _probe(scratch_base: str, own_scratch: bool) -> list[str]:
    """Apply the full confinement in a throwaway child (a worker's scratch tmpfs first, if ``own_scratch``); the
    features it could not apply."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(r)
            scratch = os.path.join(scratch_base, "probe")
            os.makedirs(scratch, exist_ok=True)
            missing = []
            if own_scratch:
                try:
                    mounts.worker_scratch(scratch)
                except OSError as exc:
                    missing.append(f"a worker's scratch tmpfs ({exc})")
            missing += confine.confine(confine.Limits(write_paths=[scratch], cpu_s=60), strict=False)
            os.write(w, json.dumps(missing).encode())
        finally:
            os._exit(0)
    os.close(w)
    data = b""
    while chunk := os.read(r, 65536):
        data += chunk
    os.close(r)
    os.waitpid(pid, 0)
    _forget_scratch(os.path.join(scratch_base, "probe"), own_scratch)
    try:
        return list(json.loads(data))
    except ValueError:
        return ["confinement probe (the probe process died)"]


def main(argv: list[str]) -> int:
    """``python -m pipeline.boundary.zygote ROLE FD``: serve the parent on the socket ``FD``."""
    role = ROLES[argv[0]]
    fd = argv[1]
    ctl = socket.socket(fileno=int(fd))
    scratch_base = os.getcwd()
    # a command started with Ctrl-C ignored (nohup, CI, `cmd &` in a script) goes on through a Ctrl-C to its group:
    # so must its workers, or its games ended as the policies' crashes (forfeits, stored for good); where it takes
    # Ctrl-C (a handler, reset to the default by exec), a worker dies of it, as the command winds its games down
    interrupt = signal.SIG_IGN if signal.getsignal(signal.SIGINT) is signal.SIG_IGN else signal.SIG_DFL
    # the parent manages our lifetime (EOF on the socket); a Ctrl-C meant for it must not end us first
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # no PDEATHSIG here: it follows the parent's *thread* that started us; EOF on the socket is the signal
    missing = namespaces.enter_namespaces(offline=role.offline)
    own_scratch = False  # each worker mounts a tmpfs of its own as its scratch (the zygote has its mount namespace)
    if not any(m.startswith("pid namespace") for m in missing):
        pid = os.fork()
        if pid:  # the outer process only waits: the namespace's init (below) ends with it, and everything in it
            ctl.close()
            while True:
                try:
                    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
                except InterruptedError:
                    continue
        namespaces.become_namespace_init()
    from pipeline.boundary import preload

    preload.warm(sorted({path.partition(":")[0] for path, _ in role.tasks.values()}), no_emulator=role.no_emulator)
    if not role.confined:
        missing = []  # hosts run no untrusted code: namespaces are a tidiness there, not a defence
    else:
        # the file view is derived from what this process loaded (pipeline/boundary/view.py): computed here, after
        # the preload, before the probe and the workers, which inherit it (also when there is no minimal root)
        view.read_paths()
        try:
            mounts.scratch_tmpfs(scratch_base)
        except OSError as exc:
            missing.append(f"scratch tmpfs ({exc})")
        else:
            own_scratch = True
            devices = ["/dev/null", "/dev/urandom"]
            read = [p for p in view.read_paths()[0] if p not in devices]
            try:
                mounts.minimal_root(read, [scratch_base], devices)
            except OSError as exc:
                missing.append(f"minimal filesystem view ({exc})")
            os.chdir(scratch_base)
        confine.prepare_workers()  # in the view just made: every worker (and the probe) inherits what it did
        missing += _probe(scratch_base, own_scratch)
        own_scratch = own_scratch and not any(m.startswith("a worker's scratch tmpfs") for m in missing)
    strict = not missing
    try:
        _send(ctl, {"kind": "hello", "pid": os.getpid(), "missing": missing})
    except OSError:  # the parent went away while we started
        _remove_scratch(scratch_base)
        return 0
    if not role.no_emulator:  # every task of the game zygote plays: the emulator stack (gymnasium, ALE, OCAtari's
        # extractors, ~0.7 s) is imported between the hello and the parent's first request (the command checks its
        # policy meanwhile), not inside that request's "prepare"
        importlib.import_module("games.envs")

    wake_r, wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *a: None)
    children: dict[int, tuple[int, str]] = {}  # pid -> (task id, scratch)
    by_id: dict[int, int] = {}
    sel = selectors.DefaultSelector()
    sel.register(ctl, selectors.EVENT_READ)
    sel.register(wake_r, selectors.EVENT_READ)
    gc.freeze()
    zygote_pid = os.getpid()
    try:
        while True:
            for key, _ in sel.select():
                if key.fileobj == wake_r:
                    try:
                        while os.read(wake_r, 4096):
                            pass
                    except BlockingIOError:
                        pass
                    while True:  # as a namespace's init, orphans are ours to reap too
                        try:
                            pid, status = os.waitpid(-1, os.WNOHANG)
                        except ChildProcessError:
                            break
                        if pid == 0:
                            break
                        task_id, scratch = children.pop(pid, (None, None))
                        if task_id is None:
                            continue
                        by_id.pop(task_id, None)
                        _forget_scratch(scratch, own_scratch)
                        _send(ctl, {"kind": "exited", "id": task_id, "code": os.waitstatus_to_exitcode(status)})
                    continue
                data, fds, _flags, _addr = socket.recv_fds(ctl, MAX_CONTROL, 2)
                if not data:
                    return 0
                msg = json.loads(data)
                op = msg.get("op")
                if op == "run":
                    task_id = int(msg["id"])
                    pid = os.fork()
                    if pid == 0:
                        sel.close()
                        _worker(fds, msg, zygote_pid, scratch_base, role, strict, own_scratch, interrupt)
                    for passed in fds:
                        os.close(passed)
                    children[pid] = (task_id, os.path.join(scratch_base, f"w{task_id}"))
                    by_id[task_id] = pid
                    _send(ctl, {"kind": "started", "id": task_id, "pid": pid})
                else:
                    for passed in fds:
                        os.close(passed)
                    if op == "kill" and int(msg["id"]) in by_id:
                        try:
                            os.kill(by_id[int(msg["id"])], signal.SIGKILL)
                        except ProcessLookupError:
                            pass
                    elif op == "prepare" and not role.confined:
                        from games.envs import shared_env

                        for game, sticky, noop_max, one_life, observation in msg["envs"]:
                            try:
                                shared_env(game, sticky=sticky, noop_max=noop_max, one_life=one_life,
                                           observation=observation)
                            except Exception:  # noqa: BLE001 - the host meets the same error and reports it
                                pass
                        gc.freeze()
                    elif op == "count":
                        _send(ctl, {"kind": "count", "workers": len(children)})
                    elif op == "stop":
                        return 0
    except (BrokenPipeError, ConnectionResetError):
        return 0
    finally:
        for pid in children:
            try:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
            except (ProcessLookupError, ChildProcessError):
                pass
        _remove_scratch(scratch_base)


def _forget_scratch(scratch: str, own_scratch: bool) -> None:
    """Remove a worker's scratch directory once the worker has ended; never raises, whatever the worker left there.
    With ``own_scratch`` the worker's tmpfs is detached whole (two system calls, nothing walked: a directory 1,500
    levels deep made ``shutil.rmtree`` raise RecursionError here, which ended the zygote and the episodes of every
    other worker with it) and its empty mount point removed; otherwise the directory is walked without recursion
    (``mounts.remove_tree``)."""
    try:
        if own_scratch:
            mounts.unmount(scratch)
            try:
                os.rmdir(scratch)
                return
            except OSError:
                pass
        mounts.remove_tree(scratch)
    except Exception:  # noqa: BLE001 - a scratch left behind costs an inode of the zygote's tmpfs, not an episode
        pass


def _remove_scratch(scratch_base: str) -> None:
    """Remove the scratch directory (a parent killed with SIGKILL cannot), tmpfs detached first; never raises."""
    try:
        if os.path.basename(scratch_base).startswith(mounts.SCRATCH_PREFIX):
            os.chdir("/")
            mounts.unmount(scratch_base)
            mounts.remove_tree(scratch_base)
    except Exception:  # noqa: BLE001
        pass


if __name__ == "__main__":
    code = main(sys.argv[1:])
    # its workers are killed and its scratch is removed (main's finally); Python's own shutdown would then tear down
    # the modules of the emulator stack one by one (~0.1-0.2 s), and the command's exit waits for this process
    from pipeline.stopping import exit_now

    exit_now(code)
