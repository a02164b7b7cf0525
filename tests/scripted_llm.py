"""A scripted model behind a real HTTP endpoint on 127.0.0.1 that speaks each provider's own wire protocol.

No hosted LLM is reachable here, so the tests talk to this server through litellm exactly as codearcade
talks to a provider: real HTTP, and litellm's own adapter for the provider builds the request and parses the
reply. One server answers every protocol, chosen by the request's path:

- ``POST …/chat/completions``: OpenAI chat completions (``openai/NAME``, ``hosted_vllm/NAME``, ``mistral/NAME``);
- ``POST …/v1/messages``: Anthropic Messages (``anthropic/NAME``), with prompt caching: blocks marked
  ``cache_control`` are reported as ``cache_creation_input_tokens`` the first time and as
  ``cache_read_input_tokens`` after; a request that forces a tool (``tool_choice: {"type": "tool"}``, how litellm
  asks Anthropic for a reply schema) is answered with a ``tool_use`` block whose input is the scripted reply's
  JSON object (a reply that is not one becomes ``{"reasoning": text, "suggestion": {}}``, as a model held to the
  schema would say it);
- ``POST …/api/chat``: Ollama's chat API (``ollama_chat/NAME``; ``/api/show``, its model metadata, is answered
  and not logged);
- ``POST …/models/NAME:generateContent``: Gemini's generateContent (``gemini/NAME``).

It runs in its own process (codearcade forks episode workers; a server thread in the test process would be
forked along). The script is a JSON list consumed one entry per request (the last entry repeats):
- ``"text"`` or ``{"content": "text"}``: a normal reply (``"usage": {"input": n, "output": m}`` overrides the
  token counts, which are otherwise the words of the prompt and of the reply);
- ``{"status": 503}``: an HTTP error in the protocol's own error shape (``"times": n`` repeats it n times
  before moving on; 401 is an authentication error, 400 a bad request, 429 a rate limit; ``"message"`` replaces
  the error's text; ``"headers": {"retry-after": "2"}`` sends those response headers with it, a value
  ``{"date_in_s": 3}`` as the HTTP date 3 s after the answer is sent);
- ``{"sleep": seconds, "content": ...}``: reply late (to exercise time-outs);
- ``{"raw": "..."}``: a body sent as-is (latin-1 bytes; for broken replies); beside ``"status"``, that error's body
  instead of the protocol's error shape, as ``text/html`` (a proxy's error page);
- ``{"error_body": 529}``: HTTP 200 whose body is the protocol's error object for that status (a gateway that
  answers every request with 200);
- ``"finish": "length"`` beside ``content``: the reply stopped at the token limit, in the protocol's own words
  (OpenAI ``finish_reason: "length"``, Anthropic ``stop_reason: "max_tokens"``, Ollama ``done_reason: "length"``,
  Gemini ``finishReason: "MAX_TOKENS"``); any other value is sent as the stop reason as it is (Gemini's
  ``"SAFETY"``, ``"RECITATION"``); a Gemini reply with empty content has no ``content`` at all, as a blocked one;
- ``"stream_error": n`` beside ``content``: a stream that sends n pieces of text, then the protocol's error event
  (Anthropic's ``event: error`` with ``overloaded_error``; OpenAI's ``data: {"error": ...}``) and ends;
  ``"stream_cut": n``: a stream whose connection closes after n pieces of text (no stop reason, no ``[DONE]``);
  ``"stall": [n, s]``: a stream that waits s seconds after its first n events (a model generating slowly);
- ``"repeat": n`` beside ``content``: the content n times over (a huge reply from a small script); ``"gzip": true``:
  the body gzip-compressed (``Content-Encoding: gzip``) whatever the request accepts; ``"extra_dicts": n``: a field
  of n empty objects beside the reply (in a stream, beside its first event's fields); ``"empty_events": n``: n
  events of ``{}`` after a stream's first; ``"choices": n``: an OpenAI answer (each event of a stream) with its
  choice n times (``"tool_calls": n``: each event's text as n tool calls);
- ``{"echo_prompt": true}``: reply with a JSON suggestion-free text containing the prompt hash;
- ``{"pool": [...], "seed": s}``: reply with a seeded random choice from the pool (by request number), e.g.
  candidate policies of mixed quality (with ``"sleep"``: a model that takes that long per call);
- ``{"climb": [reply, ...], "marks": [text, ...]}``: a model that improves the code it is given, one rung at a
  time: the parent's rung is the last ``marks[i]`` found in the prompt's #Variables section (the code being improved;
  -1 when none is), and the reply is ``climb[rung + 1]`` (the last rung repeats). It answers a prompt one way: a
  stale prompt gets the reply it got before;
- ``"latency": [median_s, sigma, seed]`` beside any entry: reply after a seeded log-normal time (by request
  number): a provider's typical latency with a long tail.
A request with ``"stream": true`` gets the reply as server-sent events (OpenAI chat chunks, with a usage chunk
when ``stream_options.include_usage`` asks for it; Anthropic's message events, a tool call's input as
``input_json_delta`` pieces). Every request is appended to a JSONL log (protocol, path, the auth headers, the
body, the messages in one normalized form, and for Anthropic the kind of content block it is answered with), so
tests can read what the loop sent.

Each request also gets a line in a billing ledger (:meth:`ScriptedModel.billed`), what a provider would bill for
it: ``{"request": n, "billed": bool, "input": tokens, "output": tokens, "reported": bool}``. Every answer the model
produced is billed at the usage it has (the one an answer reports, whether or not it had text or stopped at the
token limit); a stream that broke midway (``stream_error``, ``stream_cut``) is billed too, at the usage the whole
answer would have reported, though the client never gets it (``reported``: false); an HTTP error and a 200 whose
body is an error object are not billed (0 tokens). The ledger is the oracle a test checks ``llm_calls`` and the
budgets against.
"""

from __future__ import annotations

import email.utils
import gzip
import hashlib
import json
import os
import random
import re
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

LOGGED_HEADERS = ("authorization", "x-api-key", "x-goog-api-key", "anthropic-version", "anthropic-beta")


class ScriptedModel:
    """Start with ``with ScriptedModel(script, tmp_path) as model:``; use ``model.model`` and ``model.api_base``.

    ``model``/``api_base`` give the OpenAI route; :meth:`route` gives (model, api_base) for another protocol.
    """

    model = "openai/scripted"

    def __init__(self, script: list, workdir: Path):
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.script_path = self.workdir / "script.json"
        self.log_path = self.workdir / "requests.jsonl"
        self.ledger_path = self.workdir / "billed.jsonl"  # beside the log: the server derives it the same way
        self.script_path.write_text(json.dumps(script))
        self.process: subprocess.Popen | None = None
        self.port = 0

    @property
    def api_base(self) -> str:
        return f"http://127.0.0.1:{self.port}/v1"

    def route(self, provider: str, name: str = "scripted") -> tuple[str, str]:
        """(``--model``, ``--api-base``) that reach this server through litellm's adapter for ``provider``."""
        root = f"http://127.0.0.1:{self.port}"
        bases = {"openai": root + "/v1", "hosted_vllm": root + "/v1", "mistral": root + "/v1",
                 "anthropic": root, "ollama_chat": root, "gemini": root + "/v1beta"}
        return f"{provider}/{name}", bases[provider]

    def start(self) -> "ScriptedModel":
        for _ in range(5):  # a port another process took between its choice and the bind: choose again
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                self.port = s.getsockname()[1]
            self.process = subprocess.Popen([sys.executable, __file__, str(self.script_path), str(self.log_path),
                                             str(self.port)], stderr=subprocess.PIPE)
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and self.process.poll() is None:
                try:
                    answer = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{self.port}/health",
                                                               timeout=1).read())
                except (OSError, ValueError):
                    time.sleep(0.05)
                    continue
                if answer.get("pid") == self.process.pid:
                    return self
                break  # another process's server on the port
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

    def raw_requests(self) -> list[dict]:
        """Every request as logged: protocol, path, headers, body, messages."""
        if not self.log_path.exists():
            return []
        return [json.loads(line) for line in self.log_path.read_text().splitlines() if line.strip()]

    def billed(self) -> list[dict]:
        """The billing ledger: a line per request, in the order they were answered (see the module docstring)."""
        if not self.ledger_path.exists():
            return []
        return [json.loads(line) for line in self.ledger_path.read_text().splitlines() if line.strip()]

    def requests(self) -> list[list[dict]]:
        """The messages of every request, normalized to ``[{"role", "content"}]`` with text content."""
        return [r["messages"] for r in self.raw_requests()]


def _text(content) -> str:
    """The text of a message content in any protocol's shape (a string, or a list of blocks or parts)."""
    if isinstance(content, str):
        return content
    if isinstance(content, list):
        return "".join(b.get("text", "") if isinstance(b, dict) else str(b) for b in content)
    return ""


def _normalize(protocol: str, body: dict) -> list[dict]:
    if protocol == "anthropic":
        out = []
        if body.get("system"):
            out.append({"role": "system", "content": _text(body["system"])})
        return out + [{"role": m["role"], "content": _text(m.get("content"))} for m in body.get("messages", [])]
    if protocol == "gemini":
        out = []
        system = body.get("system_instruction") or body.get("systemInstruction")
        if system:
            out.append({"role": "system", "content": _text(system.get("parts"))})
        return out + [{"role": "user" if c.get("role") == "user" else "assistant", "content": _text(c.get("parts"))}
                      for c in body.get("contents", [])]
    return [{"role": m["role"], "content": _text(m.get("content"))} for m in body.get("messages", [])]


def _rung(messages: list[dict], marks: list[str]) -> int:
    """The last of ``marks`` in the #Variables section (the code being improved) of the last user message; -1."""
    text = next((m["content"] for m in reversed(messages) if m["role"] == "user"), "")
    start = text.find("\n#Variables")
    end = text.find("\n#Constraints", start + 1)
    code = text[start:end if end > start else len(text)] if start >= 0 else text
    return max((i for i, mark in enumerate(marks) if mark in code), default=-1)


def _cached_prefix(protocol: str, body: dict) -> str:
    """The text of the blocks an Anthropic request marks for caching (and everything before them)."""
    if protocol != "anthropic":
        return ""
    blocks = []
    system = body.get("system")
    blocks += system if isinstance(system, list) else ([{"text": system}] if system else [])
    for m in body.get("messages", []):
        content = m.get("content")
        blocks += content if isinstance(content, list) else [{"text": content or ""}]
    last = max((i for i, b in enumerate(blocks) if isinstance(b, dict) and b.get("cache_control")), default=-1)
    return "".join(b.get("text", "") for b in blocks[: last + 1])


ERRORS = {
    400: ("invalid_request_error", "bad request"), 401: ("authentication_error", "invalid api key"),
    403: ("permission_error", "forbidden"), 404: ("not_found_error", "model not found"),
    429: ("rate_limit_error", "rate limited"), 500: ("api_error", "internal error"),
    503: ("overloaded_error", "overloaded"), 529: ("overloaded_error", "overloaded"),
}


def _error_body(protocol: str, status: int, text: str | None = None) -> dict:
    kind, default = ERRORS.get(status, ("api_error", "error"))
    message = f"scripted error {status}: {text or default}"
    if protocol == "anthropic":
        return {"type": "error", "error": {"type": kind, "message": message}}
    if protocol == "ollama":
        return {"error": message}
    if protocol == "gemini":
        return {"error": {"code": status, "message": message, "status": kind.upper()}}
    return {"error": {"message": message, "type": kind, "code": kind}}


def forced_tool(body: dict) -> str | None:
    """The tool an Anthropic request forces the model to call (litellm's way of asking for a reply schema)."""
    choice = body.get("tool_choice") or {}
    return choice.get("name") if choice.get("type") == "tool" else None


def _tool_input(content: str) -> dict:
    try:
        value = json.loads(content)
    except ValueError:
        value = None
    return value if isinstance(value, dict) else {"reasoning": content, "suggestion": {}}


TOKEN_LIMIT = {"openai": "length", "anthropic": "max_tokens", "ollama": "length", "gemini": "MAX_TOKENS"}
"""Each protocol's stop reason for a reply cut off at the token limit (``"finish": "length"``)."""
STOPPED = {"openai": "stop", "anthropic": "end_turn", "ollama": "stop", "gemini": "STOP"}


def _reply_body(protocol: str, body: dict, content: str, count: int, input_tokens: int, output_tokens: int,
                cache: dict, finish: str | None = None) -> dict:
    name = body.get("model", "scripted")
    stop = TOKEN_LIMIT[protocol] if finish == "length" else finish
    if protocol == "anthropic":
        prefix = _cached_prefix(protocol, body)
        created = read = 0
        if prefix:
            tokens = len(prefix.split())
            if hashlib.sha256(prefix.encode()).hexdigest() in cache:
                read = tokens
            else:
                created = tokens
                cache[hashlib.sha256(prefix.encode()).hexdigest()] = True
        tool = forced_tool(body)
        blocks = [{"type": "tool_use", "id": f"toolu_scripted_{count}", "name": tool, "input": _tool_input(content)}
                  if tool else {"type": "text", "text": content}]
        return {"id": f"msg_scripted_{count}", "type": "message", "role": "assistant", "model": name,
                "content": blocks, "stop_reason": stop or ("tool_use" if tool else "end_turn"), "stop_sequence": None,
                "usage": {"input_tokens": input_tokens - created - read, "output_tokens": output_tokens,
                          "cache_creation_input_tokens": created, "cache_read_input_tokens": read}}
    if protocol == "ollama":
        return {"model": name, "created_at": "2026-12-01T00:00:00Z",
                "message": {"role": "assistant", "content": content}, "done": True, "done_reason": stop or "stop",
                "total_duration": 1000, "prompt_eval_count": input_tokens, "eval_count": output_tokens}
    if protocol == "gemini":
        parts = {"content": {"parts": [{"text": content}], "role": "model"}} if content else {}
        return {"candidates": [{**parts, "finishReason": stop or "STOP", "index": 0}],
                "usageMetadata": {"promptTokenCount": input_tokens, "candidatesTokenCount": output_tokens,
                                  "totalTokenCount": input_tokens + output_tokens},
                "modelVersion": name}
    return {"id": f"chatcmpl-scripted-{count}", "object": "chat.completion", "created": 0, "model": name,
            "choices": [{"index": 0, "message": {"role": "assistant", "content": content},
                         "finish_reason": stop or "stop"}],
            "usage": {"prompt_tokens": input_tokens, "completion_tokens": output_tokens,
                      "total_tokens": input_tokens + output_tokens}}


def _pieces(text: str) -> list[str]:
    """The reply cut into word-sized pieces, as a model streams tokens."""
    return re.findall(r"\S+\s*|\s+", text) or [""]


def _sse_events(protocol: str, body: dict, request: dict, copies: int = 1,
                tool_calls: int = 0) -> list[tuple[str | None, str]]:
    """A finished reply as the server-sent events of a streamed one (OpenAI chat chunks or Anthropic events); a
    hostile endpoint's: each OpenAI chunk with its choice ``copies`` times, or its text as ``tool_calls`` calls."""
    if protocol == "anthropic":
        block = body["content"][0]
        start = {**body, "content": [], "stop_reason": None,
                 "usage": {**body["usage"], "output_tokens": 1}}
        if block["type"] == "tool_use":  # the tool's input arrives as pieces of its JSON
            opened = {**block, "input": {}}
            deltas = [{"type": "input_json_delta", "partial_json": p} for p in _pieces(json.dumps(block["input"]))]
        else:
            opened = {"type": "text", "text": ""}
            deltas = [{"type": "text_delta", "text": p} for p in _pieces(block["text"])]
        events = [("message_start", {"type": "message_start", "message": start}),
                  ("content_block_start", {"type": "content_block_start", "index": 0, "content_block": opened})]
        events += [("content_block_delta", {"type": "content_block_delta", "index": 0, "delta": d}) for d in deltas]
        events += [("content_block_stop", {"type": "content_block_stop", "index": 0}),
                   ("message_delta", {"type": "message_delta", "delta": {"stop_reason": body["stop_reason"]},
                                      "usage": {"output_tokens": body["usage"]["output_tokens"]}}),
                   ("message_stop", {"type": "message_stop"})]
        return [(name, json.dumps(data)) for name, data in events]
    if protocol != "openai":
        raise ValueError(f"the scripted server streams only OpenAI and Anthropic replies, not {protocol}")
    text = body["choices"][0]["message"]["content"]
    head = {k: body[k] for k in ("id", "created", "model")} | {"object": "chat.completion.chunk"}
    deltas = [{"role": "assistant", "content": p} if not tool_calls else
              {"role": "assistant", "tool_calls": [{"index": i, "function": {"arguments": p}}
                                                   for i in range(tool_calls)]}
              for p in _pieces(text)]
    chunks = [{**head, "choices": [{"index": 0, "delta": d, "finish_reason": None}] * copies} for d in deltas]
    stop = body["choices"][0]["finish_reason"]
    chunks.append({**head, "choices": [{"index": 0, "delta": {}, "finish_reason": stop}]})
    if (request.get("stream_options") or {}).get("include_usage"):
        chunks.append({**head, "choices": [], "usage": body["usage"]})
    return [(None, json.dumps(c)) for c in chunks] + [(None, "[DONE]")]


def _stream_error(protocol: str) -> tuple[str | None, str]:
    """The event a provider sends when it fails in the middle of a stream (Anthropic: overloaded)."""
    error = _error_body(protocol, 529, "overloaded in the middle of the stream")
    return ("error" if protocol == "anthropic" else None), json.dumps(error)


def _protocol(path: str) -> str:
    path = path.split("?", 1)[0]
    if path.endswith("/messages"):
        return "anthropic"
    if path.endswith("/api/chat"):
        return "ollama"
    if re.search(r":(stream)?[gG]enerateContent$", path):
        return "gemini"
    return "openai"


def _serve(script_path: str, log_path: str, port: int) -> None:
    script = json.loads(Path(script_path).read_text())
    state = {"index": 0, "repeats": 0, "count": 0}
    lock = threading.Lock()
    cache: dict = {}
    ledger_path = Path(log_path).with_name("billed.jsonl")

    def bill(count: int, input_tokens: int = 0, output_tokens: int = 0, reported: bool = True) -> None:
        """The ledger's line for request ``count``: what it is billed (nothing, without tokens)."""
        line = {"request": count, "billed": bool(input_tokens or output_tokens), "input": input_tokens,
                "output": output_tokens, "reported": reported}
        with lock, open(ledger_path, "a") as ledger:
            ledger.write(json.dumps(line) + "\n")

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
            # its pid: the test that started it knows the server that answers is its own (a port taken between
            # its choice and this server's bind would be answered by another)
            body = json.dumps({"status": "ok", "pid": os.getpid(),
                               "data": [{"id": "scripted", "object": "model"}]}).encode()
            self._send(200, body)

        def do_POST(self):
            length = int(self.headers.get("Content-Length", 0))
            request = json.loads(self.rfile.read(length) or b"{}")
            if self.path.endswith("/api/show"):  # Ollama's model metadata, which litellm asks for after a reply
                self._send(200, json.dumps({"template": "", "parameters": "", "details": {"family": "qwen2"},
                                            "model_info": {"qwen2.context_length": 32768}}).encode())
                return
            protocol = _protocol(self.path)
            messages = _normalize(protocol, request)
            headers = {k: self.headers[k] for k in LOGGED_HEADERS if self.headers.get(k) is not None}
            with open(log_path, "a") as log:
                # reply_blocks: the kind of content an Anthropic reply carries (a forced tool gets a tool_use)
                blocks = (["tool_use"] if forced_tool(request) else ["text"]) if protocol == "anthropic" else None
                log.write(json.dumps({"protocol": protocol, "path": self.path, "headers": headers, "body": request,
                                      "messages": messages, "reply_blocks": blocks, "received_at": time.time()}) + "\n")
            with lock:  # requests are served concurrently (an iteration's proposals are requested at once)
                entry = next_entry()
                state["count"] += 1
                count = state["count"]
            if isinstance(entry, str):
                entry = {"content": entry}
            if "pool" in entry:
                entry = {**entry, "content": random.Random(entry.get("seed", 0) * 100_003 + count).choice(entry["pool"])}
            if "climb" in entry:
                entry = {**entry, "content": entry["climb"][min(_rung(messages, entry["marks"]) + 1,
                                                                 len(entry["climb"]) - 1)]}
            if "sleep" in entry:
                time.sleep(entry["sleep"])
            if "latency" in entry:
                median, sigma, seed = entry["latency"]
                time.sleep(median * random.Random(seed * 7_919 + count).lognormvariate(0.0, sigma))
            if "status" in entry or "error_body" in entry or "raw" in entry:
                bill(count)  # an error, or a body that is no answer: nothing was generated
            if "status" in entry and "raw" in entry:  # a proxy's error page
                self._send(entry["status"], entry["raw"].encode("latin-1"), headers=entry.get("headers", {}),
                           content_type="text/html")
                return
            if "status" in entry:
                error = _error_body(protocol, entry["status"], entry.get("message"))
                self._send(entry["status"], json.dumps(error).encode(), headers=entry.get("headers", {}))
                return
            if "error_body" in entry:
                self._send(200, json.dumps(_error_body(protocol, entry["error_body"], entry.get("message"))).encode())
                return
            if "raw" in entry:
                self._send(200, entry["raw"].encode("latin-1"))
                return
            content = entry.get("content", "") * entry.get("repeat", 1)
            if entry.get("echo_prompt"):
                digest = hashlib.sha256(json.dumps(messages, sort_keys=True).encode()).hexdigest()
                content = f"prompt {digest}"
            usage = entry.get("usage", {})
            input_tokens = usage.get("input", sum(len(m["content"].split()) for m in messages))
            output_tokens = usage.get("output", len(content.split()))
            body = _reply_body(protocol, request, content, count, input_tokens, output_tokens, cache,
                               entry.get("finish"))
            broken = bool(request.get("stream")) and ("stream_error" in entry or "stream_cut" in entry
                                                      or "stall" in entry)
            bill(count, input_tokens, output_tokens, reported=not broken)
            if entry.get("extra_dicts"):  # a field no reply needs, costly to parse: [{}, {}, ...]
                body["x"] = [{}] * entry["extra_dicts"]
            if entry.get("choices") and not request.get("stream") and protocol == "openai":
                body["choices"] = body["choices"] * entry["choices"]  # the same choice n times, as one answer
            if request.get("stream"):
                extra = body.pop("x", None)
                events = _sse_events(protocol, body, request, entry.get("choices", 1),
                                     entry.get("tool_calls", 0))
                if extra is not None:  # beside the first event's fields: one event of n objects
                    name, data = events[0]
                    events[0] = (name, data[:-1] + ', "x": ' + json.dumps(extra, separators=(",", ":")) + "}")
                opened = 2 if protocol == "anthropic" else 0  # events before the first piece of text
                if "stream_error" in entry:
                    events = events[: opened + entry["stream_error"]] + [_stream_error(protocol)]
                elif "stream_cut" in entry:
                    events = events[: opened + entry["stream_cut"]]
                self._stream(events[:1] + [(None, "{}")] * entry.get("empty_events", 0) + events[1:],
                             entry.get("stall"))
                return
            self._send(200, json.dumps(body).encode(), gzipped=entry.get("gzip", False))

        def _stream(self, events: list[tuple[str | None, str]], stall: list | None = None):
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Connection", "close")
            self.end_headers()
            for sent, (event, data) in enumerate(events):
                if stall is not None and sent == stall[0]:
                    time.sleep(stall[1])
                self.wfile.write(((f"event: {event}\n" if event else "") + f"data: {data}\n\n").encode())
                self.wfile.flush()
            self.close_connection = True

        def _send(self, status: int, body: bytes, gzipped: bool = False, headers: dict | None = None,
                  content_type: str = "application/json"):
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            for name, value in (headers or {}).items():
                if isinstance(value, dict):  # an HTTP date relative to now, as Retry-After may be given
                    value = email.utils.formatdate(time.time() + value["date_in_s"], usegmt=True)
                self.send_header(name, value)
            if gzipped:  # whatever the request accepts, as a hostile endpoint would
                body = gzip.compress(body, 9)
                self.send_header("Content-Encoding", "gzip")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    ThreadingHTTPServer(("127.0.0.1", port), Handler).serve_forever()


if __name__ == "__main__":
    _serve(sys.argv[1], sys.argv[2], int(sys.argv[3]))
