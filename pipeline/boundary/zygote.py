"""The zygote: a clean process that forks one confined worker per task (``python -m pipeline.boundary.zygote FD``).

The executor (``pipeline/boundary/workers.py``) starts it with a fresh interpreter, an environment reduced to an
allow-list (no API keys, no store path), its scratch directory as HOME and cwd, and one end of a Unix
``SOCK_SEQPACKET`` socket pair as its only inherited descriptor. It imports the environment stack once
(``pipeline.boundary.preload``), moves itself into an empty network namespace, mounts a small tmpfs over its
scratch directory in a mount namespace of its own (the workers' scratch directories), probes the features of
``pipeline/boundary/confine.py`` in a throwaway child, and says hello with what is missing. Then it serves:

- ``{"op": "prepare", "envs": [[game, sticky, noop_max], ...]}``: build those environments once (workers
  inherit them built);
- ``{"op": "run", "id", "task", "limits", "staged"}`` with a socket passed alongside (SCM_RIGHTS): fork a
  worker that reads its task as a JSON frame from that socket, confines itself (scratch directory,
  stdout/stderr to /dev/null, :func:`pipeline.boundary.confine.confine`), prepares it (an episode: policy loaded,
  environment reset), waits for a ``G`` byte if ``staged`` (the executor sets up the next worker while the
  current one plays), runs the task and writes its answer as frames (``pipeline/boundary/wire.py``); answered with
  ``{"kind": "started", "id", "pid"}``;
- ``{"op": "kill", "id"}``: SIGKILL that worker.

Every worker that ends is reported as ``{"kind": "exited", "id", "code"}`` (negative: killed by that signal)
and its scratch directory removed. When the parent goes away (EOF on the socket) the zygote kills its workers
and exits; workers die with the zygote (PDEATHSIG). Each worker is a fresh fork: no policy or module state
survives from one task to the next.
"""

from __future__ import annotations

import gc
import importlib
import json
import os
import selectors
import shutil
import signal
import socket
import sys
import traceback
from typing import Any, Callable

from pipeline.boundary import confine, wire

MAX_CONTROL = 64 * 1024


def _send(ctl: socket.socket, obj: dict[str, Any]) -> None:
    ctl.sendall(json.dumps(obj).encode())


# ------------------------------------------------------------------------------------------ worker tasks


TASKS: dict[str, tuple[str, bool]] = {
    "episode": ("pipeline.play.episodes:episode_task", True),
    "check": ("pipeline.play.validate:check_here", False),
    "vet": ("pipeline.play.validate:vet_and_check_here", False),
}
"""Per task name: the function that does it, by module path (the tasks live in ``pipeline/play``, above this
package: the boundary runs them without importing them), and whether it prepares itself: ``fn(item, fd)``
prepares in the confined worker (before a staged worker's go-ahead: an episode loads its policy and resets its
environment) and returns what runs the task and writes its answer on ``fd``; otherwise ``fn(item)`` returns the
text fields of one result message. Their modules are imported once, in the zygote (``preload``)."""


def _task(name: str, item: dict[str, Any], fd: int) -> Callable[[], None]:
    """What runs task ``name`` on ``item`` and writes its answer on ``fd`` (prepared already, if it prepares)."""
    path, prepares = TASKS[name]
    module, _, attr = path.partition(":")
    function = getattr(importlib.import_module(module), attr)  # preloaded: no file is read here
    if prepares:
        return function(item, fd)
    return lambda: wire.write_all(fd, wire.json_frame({"kind": "result", **function(item)}))


def _worker(fd: int, msg: dict[str, Any], zygote_pid: int, scratch_base: str, strict: bool) -> None:
    """In the forked worker: set up, confine, run the task; never returns."""
    code = 0
    try:
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):
            signal.signal(sig, signal.SIG_DFL)
        confine.die_with_parent(zygote_pid)
        os.closerange(3, fd)
        os.closerange(fd + 1, 1 << 30)  # close_range(2): cheap whatever the bound
        scratch = os.path.join(scratch_base, f"w{int(msg['id'])}")
        os.makedirs(scratch, exist_ok=True)
        os.chdir(scratch)
        os.environ["HOME"] = os.environ["TMPDIR"] = scratch
        devnull = os.open("/dev/null", os.O_RDWR)
        for target in (0, 1, 2):
            os.dup2(devnull, target)
        os.close(devnull)
        kind, payload = wire.read_frame(fd, limit=64 * 2**20)
        item = json.loads(payload)
        limits = confine.Limits(**msg["limits"])
        for path in limits.write_paths:
            os.makedirs(path, exist_ok=True)
        limits.write_paths = [scratch, *limits.write_paths]
        confine.confine(limits, strict=strict)
        run = _task(msg["task"], item, fd)  # confined already: preparing an episode loads policy code
        if msg.get("staged") and os.read(fd, 1) != b"G":
            return  # staged ahead of time (set up, confined, prepared while another task ran), then not needed
        run()
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


def _probe(scratch_base: str) -> list[str]:
    """Apply the full confinement in a throwaway child; the features it could not apply."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(r)
            scratch = os.path.join(scratch_base, "probe")
            os.makedirs(scratch, exist_ok=True)
            missing = confine.confine(confine.Limits(write_paths=[scratch], cpu_s=60), strict=False)
            os.write(w, json.dumps(missing).encode())
        finally:
            os._exit(0)
    os.close(w)
    data = b""
    while chunk := os.read(r, 65536):
        data += chunk
    os.close(r)
    os.waitpid(pid, 0)
    shutil.rmtree(os.path.join(scratch_base, "probe"), ignore_errors=True)
    try:
        return list(json.loads(data))
    except ValueError:
        return ["confinement probe (the probe process died)"]


def main(argv: list[str]) -> int:
    ctl = socket.socket(fileno=int(argv[0]))
    scratch_base = os.getcwd()
    # no PDEATHSIG here: it follows the parent's *thread* that started us; EOF on the socket is the signal
    from pipeline.boundary import preload

    preload.warm(sorted({path.partition(":")[0] for path, _ in TASKS.values()}))  # once, for every worker

    missing = []
    try:
        confine.enter_network_namespace()
    except OSError as exc:
        missing.append(f"network namespace ({exc})")
    try:
        confine.scratch_tmpfs(scratch_base)
    except OSError as exc:
        missing.append(f"scratch tmpfs ({exc})")
    missing += _probe(scratch_base)
    strict = not missing
    try:
        _send(ctl, {"kind": "hello", "pid": os.getpid(), "missing": missing})
    except OSError:  # the parent went away while we started
        _remove_scratch(scratch_base)
        return 0

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
                    while children:
                        pid, status = os.waitpid(-1, os.WNOHANG)
                        if pid == 0:
                            break
                        task_id, scratch = children.pop(pid, (None, None))
                        if task_id is None:
                            continue
                        by_id.pop(task_id, None)
                        shutil.rmtree(scratch, ignore_errors=True)
                        _send(ctl, {"kind": "exited", "id": task_id, "code": os.waitstatus_to_exitcode(status)})
                    continue
                data, fds, _flags, _addr = socket.recv_fds(ctl, MAX_CONTROL, 1)
                if not data:
                    return 0
                msg = json.loads(data)
                op = msg.get("op")
                if op == "run":
                    task_id = int(msg["id"])
                    pid = os.fork()
                    if pid == 0:
                        sel.close()
                        _worker(fds[0], msg, zygote_pid, scratch_base, strict)
                    os.close(fds[0])
                    children[pid] = (task_id, os.path.join(scratch_base, f"w{task_id}"))
                    by_id[task_id] = pid
                    _send(ctl, {"kind": "started", "id": task_id, "pid": pid})
                else:
                    for fd in fds:
                        os.close(fd)
                    if op == "kill" and int(msg["id"]) in by_id:
                        try:
                            os.kill(by_id[int(msg["id"])], signal.SIGKILL)
                        except ProcessLookupError:
                            pass
                    elif op == "prepare":
                        from games.envs import shared_env

                        for game, sticky, noop_max in msg["envs"]:
                            try:
                                shared_env(game, sticky=sticky, noop_max=noop_max)
                            except Exception:  # noqa: BLE001 - the worker meets the same error and reports it
                                pass
                        gc.freeze()
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


def _remove_scratch(scratch_base: str) -> None:
    """Remove the scratch directory (a parent killed with SIGKILL cannot), tmpfs detached first."""
    if os.path.basename(scratch_base).startswith("codearcade-sandbox-"):
        os.chdir("/")
        confine.unmount(scratch_base)
        shutil.rmtree(scratch_base, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
