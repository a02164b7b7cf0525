"""``codearcade serve``'s plain HTTP+JSON transport (the standard library's threading server, on 127.0.0.1).

Every operation is ``POST /<operation>`` with a JSON object of its arguments (``GET`` works for the two that only
read: ``/task`` and ``/budget``): ``/task``, ``/submit`` (``instances``, and ``policy``: the file's text, or
``path``: a file of the workspace; optional ``parent``), ``/feedback`` (``submission``,
optional ``instance``, ``steps``), ``/budget``, ``/sql`` (``query``), ``/finalize``. The answer is a JSON object;
a refused request (it costs nothing) is status 400 with ``{"error": ...}``. Requests are served concurrently:
the budget is exact however many arrive at once (``protocol.ServeRun``).

A web page the person visits can send requests to 127.0.0.1 too. So a request naming another host (``Host``: a
DNS-rebound name) or coming from a page (an ``Origin`` that is not this server) is refused, 403, and ``GET``, which
an ``<img>`` on any page sends, acts on nothing: a reviewer's ``GET /finalize`` with a foreign ``Referer``
finalized the run. At most :data:`MAX_CONNECTIONS` connections are served at once (each may hold a body of
:data:`MAX_BODY`; 2,000 held open took the server from 177 MB to 3.7 GB), the next answered 503 at once; a
request must arrive whole within :data:`REQUEST_TIMEOUT_S` (a byte every 10 s held one for 70 s); whatever a
failed request prints on the server's terminal is made safe for it first (an agent's text in a traceback set the
window title and cleared the screen). A body's values are counted before it is parsed
(``messages.MAX_MESSAGE_VALUES``): 32 concurrent bodies of 1 MB of ``[{},{},...]`` grew the server by 437 MB; so is
its longest number (``messages.MAX_NUMBER_CHARS``).
"""

from __future__ import annotations

import html
import io
import json
import math
import socket
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from pipeline.serve.messages import MAX_MESSAGE_VALUES, MAX_NUMBER_CHARS, json_long_number, json_values
from pipeline.serve.protocol import RequestError, ServeRun, failed_request
from viewers.safe_text import print_failure

MAX_BODY = 1_000_000
"""Bytes of a request body read at most (a policy file is at most 200,000 characters)."""

OPERATIONS = {
    "task": ((), ()),
    "budget": ((), ()),
    "submit": (("instances",), ("policy", "path", "parent")),
    "feedback": (("submission",), ("instance", "steps")),
    "sql": (("query",), ()),
    "finalize": ((), ()),
}
"""Each operation's required and optional arguments; the same names as the MCP tools' (``tools.py``)."""


def call(run: ServeRun, operation: str, arguments: dict[str, Any]) -> dict[str, Any]:
    """Run one operation with its arguments, checked against :data:`OPERATIONS` (RequestError: refused)."""
    if operation not in OPERATIONS:
        raise RequestError(f"no operation {operation!r}; there are {', '.join(OPERATIONS)}")
    if not isinstance(arguments, dict):
        raise RequestError("the body must be a JSON object of the operation's arguments")
    required, optional = OPERATIONS[operation]
    missing = [name for name in required if name not in arguments]
    unknown = [name for name in arguments if name not in required + optional]
    if missing or unknown:
        raise RequestError(f"{operation}: " + "; ".join(
            ([f"missing {', '.join(missing)}"] if missing else []) + ([f"unknown {', '.join(unknown)}"] if unknown
                                                                      else [])))
    return getattr(run, operation)(**arguments)


REQUEST_TIMEOUT_S = 30.0
"""Seconds a connection may keep the server waiting for a whole request (its line, headers and body, however
they trickle in; an idle keep-alive connection), after which it is closed; a submission that plays for minutes
is not waiting."""
MAX_CONNECTIONS = 32
"""Connections served at once; one past them is answered 503 and closed."""
READ_ONLY = ("task", "budget")
"""The operations ``GET`` may run: the ones that change nothing."""


class _DeadlineReader(io.RawIOBase):
    """A connection's bytes, read within the deadline its handler sets for the whole request (``socket``'s own
    timeout is per read: a byte every 29 s never passed it)."""

    def __init__(self, sock: socket.socket, handler: "_Handler"):
        self.sock, self.handler = sock, handler

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        left = self.handler.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the request did not arrive whole in time")
        self.sock.settimeout(left)
        return self.sock.recv_into(buffer)


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"
    timeout = REQUEST_TIMEOUT_S

    deadline = math.inf
    """When the request being read must have arrived whole (``time.monotonic()``)."""

    def setup(self) -> None:
        super().setup()
        self.rfile.close()  # the socket's own file, in place of which the request is read within its deadline
        self.rfile = io.BufferedReader(_DeadlineReader(self.connection, self), io.DEFAULT_BUFFER_SIZE)

    def handle_one_request(self) -> None:
        self.deadline = time.monotonic() + self.timeout  # for this request (and the wait for it)
        super().handle_one_request()

    def log_message(self, format: str, *args: Any) -> None:
        pass  # the store records what matters; stderr stays for the server's own lines

    def _foreign(self) -> str | None:
        """Why this request is not the agent's own (a page's, or a rebound name's), or None."""
        port = self.server.server_address[1]
        here = {f"{name}:{port}" for name in ("127.0.0.1", "localhost", "[::1]")} | {"127.0.0.1", "localhost", "[::1]"}
        for name in ("Host", "Origin"):  # two: the check below read the first, a server behind it may read the other
            if len(self.headers.get_all(name) or ()) > 1:
                return f"a request with one {name} header at most"
        host = self.headers.get("Host")
        if host is not None and host.strip().lower() not in here:
            return f"this server answers requests to 127.0.0.1:{port}, not to {host.strip()[:80]!r}"
        origin = self.headers.get("Origin")
        if origin is not None and origin.strip().lower() not in {f"http://{name}" for name in here}:
            return "this server answers its agent, not a web page (a request with a foreign Origin)"
        return None

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """The standard library's own refusals (a request line it cannot parse, a method without a handler, a
        header too long) as every other answer: ``{"error": ...}`` in JSON, not an HTML page."""
        short, _ = self.responses.get(code, ("error", ""))
        if getattr(self, "request_version", "HTTP/0.9") == "HTTP/0.9":  # a request line it could not read: the
            self.request_version = self.protocol_version  # answer still gets its status line and headers
        self._send(code, {"error": html.unescape(message or short)}, close=True)

    def do_GET(self) -> None:
        operation = self.path.strip("/").split("?")[0]
        if operation in OPERATIONS and operation not in READ_ONLY:
            self._send(405, {"error": f"{operation} acts: POST it (GET runs only {' and '.join(READ_ONLY)})"})
            return
        self._answer({})

    def do_POST(self) -> None:
        if self.headers.get("Transfer-Encoding") is not None:  # chunked: the body would be taken for empty
            self._send(411, {"error": "send the body with a Content-Length (not Transfer-Encoding)"}, close=True)
            return
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if length < 0:  # read() of a negative length would wait for the client to close
            self._send(400, {"error": "Content-Length: a number of bytes"}, close=True)
            return
        if length > MAX_BODY:
            self._send(413, {"error": f"the body is {length:,} bytes; at most {MAX_BODY:,}"}, close=True)
            return
        body = self.rfile.read(length) if length else b"{}"
        if json_values(body) > MAX_MESSAGE_VALUES:  # a Python object a value: counted before they are made
            self._send(400, {"error": f"the body holds more than {MAX_MESSAGE_VALUES:,} values; nothing was done"})
            return
        if json_long_number(body):  # its parse would cost more than its bytes (an int's digits)
            self._send(400, {"error": f"the body holds a number of more than {MAX_NUMBER_CHARS} characters; nothing "
                                      f"was done"})
            return
        try:
            arguments = json.loads(body or b"{}")
        except (ValueError, UnicodeDecodeError, RecursionError):  # nested deeper than Python's parser goes
            self._send(400, {"error": "the body is not JSON (or is nested too deep)"})
            return
        self._answer(arguments)

    def _answer(self, arguments: Any) -> None:
        operation = self.path.strip("/").split("?")[0]
        refused = self._foreign()
        if refused is not None:
            self._send(403, {"error": refused}, close=True)
            return
        try:
            self._send(200, call(self.server.run, operation, arguments))
        except RequestError as exc:
            self._send(400 if operation in OPERATIONS else 404, {"error": str(exc)})
        except Exception as exc:  # noqa: BLE001 - the server goes on; the agent learns the request failed
            if self.server.run.stopping.is_set():  # what the server's own stop broke under a request: no fault
                self._send(503, {"error": "the server is stopping"})
                return
            self._send(500, {"error": failed_request(exc)})

    def _send(self, status: int, payload: dict[str, Any], close: bool = False) -> None:
        data = json.dumps(payload, default=str).encode()
        try:
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            if close:
                self.send_header("Connection", "close")
                self.close_connection = True
            self.end_headers()
            self.wfile.write(data)
        except (BrokenPipeError, ConnectionResetError):  # the client hung up before its answer: nothing to say
            self.close_connection = True


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 128
    """Connections the kernel holds until they are accepted (socketserver's default is 5): an agent may send many
    requests at once, and on a busy machine the accepting thread lags; past the queue a connection was reset
    (one of 24 concurrent requests in a CI run of tests/test_serve.py)."""

    def __init__(self, run: ServeRun, port: int):
        self.run = run
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        super().__init__(("127.0.0.1", port), _Handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        """A thread for the connection while one of :data:`MAX_CONNECTIONS` is free; else 503 at once."""
        if not self.slots.acquire(blocking=False):
            try:
                request.settimeout(1.0)
                body = json.dumps({"error": f"the server serves {MAX_CONNECTIONS} connections at once; try again"})
                request.sendall(f"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                                f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n{body}".encode())
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A client that hung up mid-request is its own business (socketserver printed a traceback for it); any
        other failure is printed safe for the terminal."""
        if isinstance(sys.exc_info()[1], ConnectionError):
            return
        print_failure("codearcade serve: a request failed:")


def start_http(run: ServeRun, port: int = 0) -> tuple[ThreadingHTTPServer, threading.Thread]:
    """Serve ``run`` on 127.0.0.1:``port`` (0: any free port; ``server.server_address`` says which) in a thread."""
    server = _Server(run, port)
    thread = threading.Thread(target=server.serve_forever, name="codearcade-serve-http", daemon=True)
    thread.start()
    return server, thread
