"""Where recordings go: viewer processes, the web viewer on 127.0.0.1, live targets, run-recording updates.

Nothing here imports Rerun. ``codearcade eval/optimize`` run this in the main process, which forks the episode
workers: the Rerun SDK starts Rust threads on import, so it must only ever be loaded in the workers (live
episode recordings) or in separate processes (the run recording, ``codearcade view``). Viewers and servers
are the ``rerun`` executable shipped in the rerun-sdk wheel, started as subprocesses:

- ``--rerun spawn`` / ``view --spawn``: the native viewer, its gRPC server bound to 127.0.0.1 (needs a display);
- ``view --serve-web``: ``rerun --serve-web --bind 127.0.0.1`` with no file, fed over gRPC by the SDK. It
  binds both the web page and the gRPC server to loopback and idles near 0% CPU (the SDK's ``serve_grpc`` +
  ``serve_web_viewer`` route binds 0.0.0.0; ``rerun --serve-web FILE.rrd`` keeps a core busy).
"""

from __future__ import annotations

import ctypes
import functools
import importlib.util
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, urlparse

LOOPBACK = "127.0.0.1"
DEFAULT_VIEWER_PORT = 9876
DEFAULT_WEB_PORT = 9090


class ViewerError(Exception):
    """A viewer or server that could not be started or reached; the message says what to do instead."""


def rerun_executable() -> str:
    """The ``rerun`` binary of the installed rerun-sdk (found without importing the SDK)."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.submodule_search_locations:
        for location in spec.submodule_search_locations:
            candidate = Path(location) / "rerun"
            if candidate.exists():
                return str(candidate)
    found = shutil.which("rerun")
    if found is None:
        raise ViewerError("the rerun executable was not found; reinstall rerun-sdk (scripts/setup.sh)")
    return found


def grpc_url(port: int, host: str = LOOPBACK) -> str:
    return f"rerun+http://{host}:{port}/proxy"


def web_viewer_url(web_port: int, grpc_port: int, host: str = LOOPBACK) -> str:
    """The page that opens the web viewer connected to the gRPC server (without ``?url=`` it shows only
    the welcome page)."""
    return f"http://{host}:{web_port}/?url={quote(grpc_url(grpc_port, host), safe='')}"


def port_open(port: int, host: str = LOOPBACK, timeout: float = 0.2) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def free_port(preferred: int | None = None) -> int:
    """``preferred`` if nothing listens on it on 127.0.0.1, else a free port chosen by the OS."""
    for port in ([preferred] if preferred else []) + [0]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((LOOPBACK, port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise ViewerError("no free TCP port on 127.0.0.1")


def _wait_for_port(process: subprocess.Popen, port: int, timeout_s: float, what: str) -> None:
    """Until ``process`` itself listens on 127.0.0.1:``port`` (another process listening there is not it: two
    ``view --serve-web`` started together chose the same free ports, and the one whose server lost the race
    went on to feed and show the other's)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise PortTaken(f"{what} exited with code {process.returncode} before listening on port {port}")
        if _listens(process.pid, port):
            return
        time.sleep(0.05)
    process.kill()
    raise ViewerError(f"{what} did not listen on 127.0.0.1:{port} within {timeout_s:g} s")


class PortTaken(ViewerError):
    """The server exited before listening: most often because another process took its port meanwhile."""


def _listens(pid: int, port: int) -> bool:
    """Whether process ``pid`` listens on TCP ``port`` of 127.0.0.1. On Linux its own sockets are matched against
    the kernel's table of listening sockets; elsewhere, whether anything answers there."""
    try:
        table = Path("/proc/net/tcp").read_text().splitlines()[1:]
    except OSError:  # no /proc: not Linux
        return port_open(port)
    try:
        sockets = {os.readlink(f"/proc/{pid}/fd/{fd}") for fd in os.listdir(f"/proc/{pid}/fd")}
    except OSError:  # it has just exited (the caller sees that next)
        return False
    for row in table:
        fields = row.split()  # sl local_address rem_address st tx:rx tr:when retrnsmt uid timeout inode ...
        address, state, inode = fields[1], fields[3], fields[9]
        if state == "0A" and int(address.rsplit(":", 1)[1], 16) == port and f"socket:[{inode}]" in sockets:
            return True
    return False


def _quiet_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("RUST_LOG", "warn")
    return env


@dataclass
class WebViewer:
    """A running ``rerun --serve-web`` bound to 127.0.0.1: its gRPC url to log to and the page to open."""

    process: subprocess.Popen
    grpc_port: int
    web_port: int

    @property
    def grpc_url(self) -> str:
        return grpc_url(self.grpc_port)

    @property
    def url(self) -> str:
        return web_viewer_url(self.web_port, self.grpc_port)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)

    def __enter__(self) -> "WebViewer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


_LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None
"""Opened here, not in a child between fork and exec, where opening a library may wait on a lock another thread held."""
PR_SET_PDEATHSIG = 1


def _ends_with(parent_pid: int) -> None:
    """In a served viewer's child, before it runs rerun: SIGTERM once the process that started it ends, however it
    ends (its own session keeps a terminal's Ctrl-C from it, so only this stops it: a ``view --serve-web`` killed
    with SIGKILL left its server behind, holding two ports). Gone already: end at once."""
    if _LIBC is not None:
        _LIBC.prctl(ctypes.c_int(PR_SET_PDEATHSIG), ctypes.c_ulong(signal.SIGTERM), ctypes.c_ulong(0),
                    ctypes.c_ulong(0), ctypes.c_ulong(0))
    if os.getppid() != parent_pid:
        os._exit(1)


def start_web_viewer(grpc_port: int | None = None, web_port: int | None = None,
                     server_memory_limit: str = "1GiB", timeout_s: float = 30.0) -> WebViewer:
    """Start the web viewer and its gRPC server on 127.0.0.1 (free ports near Rerun's defaults); it ends with this
    process at the latest (the thread that starts it: this one). A port another process took between the choice
    and the server's start (two views started at once) is chosen again, by the OS."""
    for attempt in range(_PORT_ATTEMPTS):
        preferred = attempt == 0
        try:
            return _start_web_viewer(grpc_port or free_port(DEFAULT_VIEWER_PORT if preferred else None),
                                     web_port or free_port(DEFAULT_WEB_PORT if preferred else None),
                                     server_memory_limit, timeout_s)
        except PortTaken:
            if (grpc_port and web_port) or attempt == _PORT_ATTEMPTS - 1:
                raise
    raise AssertionError("unreachable")


_PORT_ATTEMPTS = 4


def _start_web_viewer(grpc_port: int, web_port: int, server_memory_limit: str, timeout_s: float) -> WebViewer:
    process = subprocess.Popen(
        [rerun_executable(), "--serve-web", "--bind", LOOPBACK, "--port", str(grpc_port),
         "--web-viewer-port", str(web_port), "--server-memory-limit", server_memory_limit],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_quiet_env(),
        start_new_session=True, preexec_fn=functools.partial(_ends_with, os.getpid()),
    )
    viewer = WebViewer(process, grpc_port, web_port)
    try:
        _wait_for_port(process, grpc_port, timeout_s, "rerun --serve-web")
        _wait_for_port(process, web_port, timeout_s, "rerun --serve-web")
    except BaseException:
        viewer.stop()
        raise
    return viewer


def spawn_viewer(port: int = DEFAULT_VIEWER_PORT, timeout_s: float = 20.0) -> str:
    """The gRPC url of a native viewer on 127.0.0.1:``port``: the one already listening there, else a new one
    (detached: it outlives this process, as ``rr.spawn`` does)."""
    if port_open(port):
        return grpc_url(port)
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ViewerError("cannot spawn the Rerun viewer: no display (DISPLAY/WAYLAND_DISPLAY unset); save files "
                          "instead (--rerun DIR, or `codearcade view RUN --save F.rrd` / --serve-web)")
    process = subprocess.Popen(
        [rerun_executable(), "--bind", LOOPBACK, "--port", str(port), "--expect-data-soon"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_quiet_env(),
        start_new_session=True,
    )
    _wait_for_port(process, port, timeout_s, "the Rerun viewer")
    time.sleep(1.0)  # a viewer that cannot open its window exits right after binding
    if process.poll() is not None:
        raise ViewerError(f"the Rerun viewer exited (code {process.returncode}); is there a display? save files "
                          "instead (--rerun DIR)")
    return grpc_url(port)


def is_grpc_url(value: str) -> bool:
    return value.startswith(("rerun://", "rerun+http://", "rerun+https://"))


def resolve_live_target(value: str | None) -> str | None:
    """``--rerun`` of eval/optimize as an ``EpisodeSpec.rerun`` value: None (``off``), a gRPC url (``spawn``
    starts or reuses a viewer; a ``rerun+http://…/proxy`` url is taken as is), or an absolute directory
    (created) for ``DIR/<episode_id>.rrd`` files."""
    if value is None or value.strip().lower() in ("", "off", "none"):
        return None
    if value == "spawn":
        return spawn_viewer()
    if is_grpc_url(value):
        address = urlparse(value.replace("rerun+", "", 1).replace("rerun://", "http://", 1))
        if address.hostname in (LOOPBACK, "localhost") and address.port and not port_open(address.port):
            raise ViewerError(f"--rerun {value}: nothing listens there; start a viewer first (or use spawn or DIR)")
        return value
    if re.match(r"[A-Za-z][A-Za-z0-9+.-]*://", value):  # a URL of another kind: never a folder named "http:"
        raise ViewerError(f"--rerun {value}: a viewer's address starts rerun+http:// (e.g. "
                          f"rerun+http://127.0.0.1:9876/proxy); or give spawn, off or a directory for .rrd files")
    if value.strip().lower() == "spawn":  # "Spawn", " spawn": a word meant, not a directory
        raise ViewerError(f"--rerun {value!r}: did you mean spawn? (a directory of that name: ./{value.strip()})")
    path = Path(value).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise ViewerError(f"--rerun {value}: not a directory (give a directory for the .rrd files, spawn or off)")
    if not path.parent.is_dir():
        what = "is not a directory" if path.parent.exists() else "does not exist"
        raise ViewerError(f"--rerun {value}: {path.parent} {what}; give another path (a directory for the .rrd "
                          "files, spawn or off)")
    path.mkdir(exist_ok=True)
    return str(path)


def run_recording_path(target: str, run_id: str) -> str:
    """Where a run's recording goes in a ``--rerun DIR`` directory."""
    return os.path.join(target, f"{run_id}.rrd")


class RunRecordingUpdater:
    """Keeps an optimization run's recording current: after each iteration, a separate short-lived process
    (``codearcade view RUN --save DIR/RUN.rrd`` or ``--connect URL``) rebuilds it from the store. The
    process that forks the episode workers never loads Rerun itself."""

    def __init__(self, store_path: str | os.PathLike, target: str):
        self.store_path = str(Path(store_path).resolve())
        self.target = target
        self.process: subprocess.Popen | None = None
        self.pending: str | None = None

    def _command(self, run_id: str) -> list[str]:
        sink = (["--connect", self.target] if is_grpc_url(self.target)
                else ["--save", run_recording_path(self.target, run_id)])
        return [sys.executable, "-m", "pipeline.cli", "view", run_id, "--store", self.store_path, "--quiet", *sink]

    def update(self, run_id: str) -> None:
        """Rebuild ``run_id``'s recording now, or as soon as the previous rebuild has finished."""
        if self.process is not None and self.process.poll() is None:
            self.pending = run_id  # one rebuild at a time; the latest request wins
            return
        self.pending = None
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.process = subprocess.Popen(self._command(run_id), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                        env=env)

    def close(self, timeout_s: float = 120.0) -> None:
        """Wait for the running rebuild, then run the last pending one, so the file ends up complete."""
        for _ in range(2):
            if self.process is not None:
                try:
                    self.process.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait(5)
                self.process = None
            if self.pending is None:
                break
            self.update(self.pending)


