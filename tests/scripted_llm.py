"""A scripted model behind a real OpenAI-compatible HTTP endpoint on 127.0.0.1, for deterministic tests.

No hosted LLM is reachable here, so the tests talk to this server through litellm exactly as codearcade
talks to a provider: real HTTP, the chat-completions JSON shape, usage counts. It runs in its own process
(codearcade forks episode workers; a server thread in the test process would be forked along).

The script is a JSON list consumed one entry per request (the last entry repeats):
- ``"text"`` or ``{"content": "text"}``: a normal reply;
- ``{"status": 503}``: an HTTP error (``"times": n`` repeats it n times before moving on);
- ``{"sleep": seconds, "content": ...}``: reply late (to exercise time-outs);
- ``{"raw": "..."}``: a body sent as-is (latin-1 bytes; for broken replies);
- ``{"echo_prompt": true}``: reply with a JSON suggestion-free text containing the prompt hash.
Every request's messages are appended to a JSONL log, so tests can read the prompts the loop sent.
"""

from __future__ import annotations

import hashlib
import json
import socket
import subprocess
import sys
import time
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path


class ScriptedModel:
    """Start with ``with ScriptedModel(script, tmp_path) as model:``; use ``model.model`` and ``model.api_base``."""

    model = "openai/scripted"

    def __init__(self, script: list, workdir: Path):
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.script_path = self.workdir / "script.json"
        self.log_path = self.workdir / "requests.jsonl"
        self.script_path.write_text(json.dumps(script))
        self.process: subprocess.Popen | None = None
        self.port = 0

    @property
    def api_base(self) -> str:
        return f"http://127.0.0.1:{self.port}/v1"

    def start(self) -> "ScriptedModel":
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.process = subprocess.Popen([sys.executable, __file__, str(self.script_path), str(self.log_path),
                                         str(self.port)], stderr=subprocess.PIPE)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{self.port}/health", timeout=1).read()
                return self
            except OSError:
                time.sleep(0.05)
        self.stop()
        raise RuntimeError("the scripted model server did not start")

    def stop(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.wait(5)
            self.process = None

    def __enter__(self) -> "ScriptedModel":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def requests(self) -> list[list[dict]]:
        if not self.log_path.exists():
            return []
        return [json.loads(line) for line in self.log_path.read_text().splitlines() if line.strip()]


def _serve(script_path: str, log_path: str, port: int) -> None:
    script = json.loads(Path(script_path).read_text())
    state = {"index": 0, "repeats": 0, "count": 0}

    def next_entry():
        entry = script[min(state["index"], len(script) - 1)]
        if isinstance(entry, dict) and entry.get("times", 1) > 1:
            state["repeats"] += 1
            if state["repeats"] >= entry["times"]:
                state["index"] += 1
                state["repeats"] = 0
        else:
            state["index"] += 1
        return entry

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args):  # quiet
            pass

        def do_GET(self):
            body = json.dumps({"status": "ok", "data": [{"id": "scripted", "object": "model"}]}).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def do_POST(self):
            length = int(self.headers.get("Content-Length", 0))
            request = json.loads(self.rfile.read(length) or b"{}")
            messages = request.get("messages", [])
            with open(log_path, "a") as log:
                log.write(json.dumps(messages) + "\n")
            entry = next_entry()
            state["count"] += 1
            if isinstance(entry, str):
                entry = {"content": entry}
            if "sleep" in entry:
                time.sleep(entry["sleep"])
            if "status" in entry:
                body = json.dumps({"error": {"message": f"scripted error {entry['status']}", "type": "server_error"}})
                self._send(entry["status"], body.encode())
                return
            if "raw" in entry:
                self._send(200, entry["raw"].encode("latin-1"))
                return
            content = entry.get("content", "")
            if entry.get("echo_prompt"):
                digest = hashlib.sha256(json.dumps(messages, sort_keys=True).encode()).hexdigest()
                content = f"prompt {digest}"
            prompt_tokens = sum(len(m.get("content", "").split()) for m in messages)
            body = {
                "id": f"chatcmpl-scripted-{state['count']}", "object": "chat.completion", "created": 0,
                "model": "scripted",
                "choices": [{"index": 0, "message": {"role": "assistant", "content": content},
                             "finish_reason": "stop"}],
                "usage": {"prompt_tokens": prompt_tokens, "completion_tokens": len(content.split()),
                          "total_tokens": prompt_tokens + len(content.split())},
            }
            self._send(200, json.dumps(body).encode())

        def _send(self, status: int, body: bytes):
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    ThreadingHTTPServer(("127.0.0.1", port), Handler).serve_forever()


if __name__ == "__main__":
    _serve(sys.argv[1], sys.argv[2], int(sys.argv[3]))
