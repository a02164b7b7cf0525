"""``codearcade serve``'s MCP transport: the protocol's operations as MCP tools, with the official SDK (``mcp``).

The tools are the HTTP operations (``http.py``) under the same names and arguments: ``task``, ``submit``,
``feedback``, ``budget``, ``sql``, ``finalize``. Each returns the operation's JSON object as structured content;
a refused request (it costs nothing) is a tool error whose text says why. Operations run in a worker thread, so
a submission that plays for a while does not stall the transport. Transports: stdio (what Claude Code and Codex
CLI start: ``codearcade serve --mcp``) and streamable HTTP on 127.0.0.1 (``--mcp-port``). Over stdio, what the agent
writes is bounded before the SDK reads it (:func:`bound_stdin_lines`), so are the requests it holds unanswered
(:data:`MAX_PENDING_REQUESTS`), and a request the SDK cannot read is answered (:func:`serve_stdio`). Over
``--mcp-port``, so are the bodies held at once, in bytes, until each request is answered (:data:`MAX_HELD_BYTES`).
"""

from __future__ import annotations

import os
import re
import select
import threading
from typing import Any, Callable

import anyio
from mcp.server.mcpserver import MCPServer
from mcp.server.mcpserver.exceptions import ToolError

from pipeline.serve.protocol import RequestError, ServeRun, failed_request

INSTRUCTIONS = """A rollout server for one codearcade run. Call `task` first: it gives the game, the starting policy \
(a Python class whose trainable methods you improve), the budget and the rules. `submit` a whole policy file (its \
text, or `path`: a file of your workspace) with the training instances to play it on; every episode costs one of \
the budget. `feedback` shows a submission's episodes, errors, what your policy printed and the steps that \
mattered; `sql` queries your own training play (tables submissions, episodes, steps, nodes). The run is scored at \
the end on hidden games."""


def build_server(run: ServeRun) -> MCPServer:
    """The MCP server of ``run``: one tool per operation."""
    server = MCPServer("codearcade", instructions=INSTRUCTIONS, log_level="WARNING")

    async def call(operation: str, **arguments: Any) -> dict[str, Any]:
        arguments = {k: v for k, v in arguments.items() if v is not None}
        try:
            return await anyio.to_thread.run_sync(lambda: getattr(run, operation)(**arguments))
        except RequestError as exc:
            raise ToolError(str(exc)) from None
        except Exception as exc:  # noqa: BLE001 - the server goes on; the agent learns the request failed
            if run.stopping.is_set():  # what the server's own stop broke under the request: no fault
                raise ToolError("the server is stopping: nothing of this request was kept") from None
            # said here, made safe for the terminal (the SDK's own traceback printed an agent's escape bytes raw)
            raise ToolError(failed_request(exc)) from None

    @server.tool()
    async def task() -> dict[str, Any]:
        """The game's facts, the starting policy and its trainable methods, the budget and the rules."""
        return await call("task")

    @server.tool()
    async def submit(instances: list[int], policy: str | None = None, path: str | None = None,
                     parent: int | None = None) -> dict[str, Any]:
        """Play a whole policy file (``policy``: its text, or ``path``: a file of the workspace) on the training
        instances ``instances`` (ids); ``parent``: the submission it improves (default: the newest). Each
        episode costs one of the budget. Returns the episodes' returns, ends and errors, and the score."""
        return await call("submit", policy=policy, instances=instances, parent=parent, path=path)

    @server.tool()
    async def feedback(submission: int, instance: int | None = None, steps: int = 40) -> dict[str, Any]:
        """A submission's summary, its feedback text, and ``steps`` steps of one of its episodes (``instance``;
        default the first) with every call of a trainable method, the steps before lost points first."""
        return await call("feedback", submission=submission, instance=instance, steps=steps)

    @server.tool()
    async def budget() -> dict[str, Any]:
        """The episode budget: total, spent, playing now, remaining."""
        return await call("budget")

    @server.tool()
    async def sql(query: str) -> dict[str, Any]:
        """Read-only SQL (DuckDB) over your own training play: tables submissions, episodes, steps, nodes."""
        return await call("sql", query=query)

    @server.tool()
    async def finalize() -> dict[str, Any]:
        """End the run: every submission is scored on the hidden validation games, the best on held-out ones."""
        return await call("finalize")

    return server


MAX_MESSAGE_BYTES = 4 * 2**20
"""The longest line (one JSON-RPC message) read from the agent over stdio: a policy file's 200,000 characters,
each escaped as JSON may (``\\uXXXX``), and the rest of its request. The MCP SDK reads a line whole, however long:
600 MB without a newline took ``serve`` to 2.5 GB."""
TOO_LONG = '"a message longer than the server reads"'
"""The line that stands for one past :data:`MAX_MESSAGE_BYTES` (dropped as it arrived)."""
TOO_MANY_VALUES = '"a message of more values than the server parses"'
"""The line that stands for one of more values than ``messages.MAX_MESSAGE_VALUES``."""
TOO_LONG_A_NUMBER = '"a message with a number longer than the server parses"'
"""The line that stands for one with a number of more characters than ``messages.MAX_NUMBER_CHARS``."""
_BLANK = re.compile(rb"[ \t\r\n]*")
"""What may come before a message on its line, blank lines included: JSON's whitespace."""


def bound_stdin_lines(limit: int = MAX_MESSAGE_BYTES) -> tuple[int, Callable[[], None]]:
    """A pipe fed by a thread that copies the agent's lines to it, each at most ``limit`` bytes and
    ``messages.MAX_MESSAGE_VALUES`` values: a longer one is dropped as it arrives (never held), one of more values
    (or with a number longer than ``messages.MAX_NUMBER_CHARS``) once it has arrived, each replaced by a line that
    says so (:data:`TOO_LONG`, :data:`TOO_MANY_VALUES`, :data:`TOO_LONG_A_NUMBER`), which
    the server answers (:func:`unreadable_answer`). Blank lines, and the whitespace before a message, are skipped
    as they arrive (one match however many): the SDK took each blank line for a message, ~300 us of server CPU a
    byte (1 MiB of newlines: 293 s). Each chunk read is split in place and its lines written on at once (a chunk of
    newlines was copied once a line). Returns the pipe's end to read (:func:`serve_stdio`) and ``stop``; fd 0 is
    the null device from now on, so that nothing else reads the agent's messages. At the agent's EOF, the pipe ends
    too.

    ``stop``: the pipe ends now, as at the agent's EOF. A server stopped by Ctrl-C or SIGTERM while the agent kept
    stdin open (an agent stops its server with SIGTERM, or a person presses Ctrl-C) marked its run stopped and never
    exited: the SDK's reader thread (not a daemon) waited on this pipe for good, and the interpreter's exit waited
    on it; a second Ctrl-C did not end it either."""
    from pipeline.serve.messages import MAX_MESSAGE_VALUES, json_long_number, json_values

    source = os.dup(0)
    read_end, write_end = os.pipe()
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    stop_read, stop_write = os.pipe()

    def relay() -> None:
        line, dropping = bytearray(), False
        waiting = select.poll()
        waiting.register(source, select.POLLIN)
        waiting.register(stop_read, select.POLLIN)
        try:
            while stop_read not in {fd for fd, _ in waiting.poll()} and (chunk := os.read(source, 65536)):
                passed, at, view = bytearray(), 0, memoryview(chunk)  # passed: the chunk's lines, written at once
                while at < len(chunk):
                    if not line and not dropping:  # a line's start: blank lines and leading whitespace, skipped in
                        at = _BLANK.match(chunk, at).end()  # one match, are no message (the SDK took each for one)
                        if at == len(chunk):
                            break
                    end = chunk.find(b"\n", at)
                    stop = len(chunk) if end < 0 else end + 1
                    if not dropping:
                        line += view[at:stop]
                        if len(line) > limit:  # past the limit: let it go, and the rest of it as it comes
                            line.clear()
                            dropping = True
                    if end >= 0:
                        if dropping:
                            passed += TOO_LONG.encode() + b"\n"
                        elif json_values(line) > MAX_MESSAGE_VALUES:  # counted in place: bytes(line) would copy it
                            passed += TOO_MANY_VALUES.encode() + b"\n"
                        elif json_long_number(line):  # its parse would cost more than its bytes (an int's digits)
                            passed += TOO_LONG_A_NUMBER.encode() + b"\n"
                        else:
                            passed += line
                        line.clear()
                        dropping = False
                    at = stop
                view.release()
                if passed:
                    os.write(write_end, passed)
        except OSError:  # the SDK's end was closed: it is done reading
            pass
        finally:
            os.close(write_end)
            os.close(source)
            os.close(stop_read)

    def stop() -> None:
        try:
            os.write(stop_write, b"x")
        except OSError:  # the relay ended already (the agent's EOF): the pipe has ended
            pass

    thread = threading.Thread(target=relay, name="codearcade-mcp-stdin", daemon=True)
    thread.start()
    return read_end, stop


MAX_PENDING_REQUESTS = 16
"""Requests read from the agent over stdio and not answered yet: with that many, the server reads no more of stdin
until one is answered (or settles unanswered: cancelled), so the pipe fills and the agent's writes wait. Each holds
its message (at most :data:`MAX_MESSAGE_BYTES`) while it waits for its turn. The SDK read on and started every
request as it came: 2,000 refused submissions of 190 KB written at once, their answers unread, grew the server's
peak by 317 MB (now ~15 MB). An agent runs a few calls at once; more wait their turn in the pipe."""


def serve_stdio(server: MCPServer, lines: int, limit: int = MAX_PENDING_REQUESTS) -> None:
    """Serve ``server`` over the agent's lines (``lines``: the pipe :func:`bound_stdin_lines` feeds) and stdout until
    the agent closes stdin, as the SDK's ``run("stdio")`` does (its transport, ``mcp.server.stdio``, and its server),
    with a stage between the two: at most ``limit`` requests are held unanswered (:data:`MAX_PENDING_REQUESTS`),
    and every request the transport could not take as one is answered (:func:`unreadable_answer`). The SDK
    dropped such a request with no answer, and the agent waited for good: a lone surrogate (``"\\ud800"``, which
    Python's JSON reads and the SDK's does not) in any argument or in the id, an id that is neither a string nor an
    integer (``5.5``, ``null``: the SDK took the request for a notification), a line nested too deep to parse."""
    anyio.run(_serve_stdio, server, lines, limit)


class _Lines:
    """The agent's lines as the SDK's transport reads them (``async for``), each also kept in :attr:`read` until the
    stage takes it: the transport makes exactly one item of each line, in order, and the stage needs the line
    itself where the item lost what it said (a request's id that the SDK's models drop).

    The pipe is read in blocks, a worker thread's call for each, and its lines handed out from them: read a line
    at a time (``anyio.wrap_file(...).readline()``), each line cost a worker thread's round trip, ~120 us of the
    ~290 us of server CPU a line took, so 64 KiB of ``{}`` lines took 6.3 s. Held here at most: one block's lines
    and one line being read (at most ``MAX_MESSAGE_BYTES``, :func:`bound_stdin_lines`). Read as the SDK's text
    stream reads them: UTF-8 (what is not, replaced) and universal newlines (``\\r\\n`` and ``\\r`` end a line
    too)."""

    BLOCK = 65536

    def __init__(self, fd: int) -> None:
        import codecs
        import collections
        import io

        self.file = os.fdopen(fd, "rb", buffering=0)  # closed with this object, as the SDK's text stream was
        self.text = io.IncrementalNewlineDecoder(codecs.getincrementaldecoder("utf-8")("replace"), translate=True)
        self.lines: collections.deque[str] = collections.deque()  # whole lines of the blocks read, not handed out
        self.partial: list[str] = []  # the line being read: its pieces so far
        self.ended = False
        self.read: collections.deque[str] = collections.deque()

    def __aiter__(self) -> "_Lines":
        return self

    async def __anext__(self) -> str:
        while not self.lines and not self.ended:
            block = await anyio.to_thread.run_sync(self.file.read, self.BLOCK)  # what the pipe holds, up to it
            self.ended = not block
            self._split(self.text.decode(block, final=self.ended))
        if not self.lines:
            raise StopAsyncIteration
        line = self.lines.popleft()
        self.read.append(line)
        return line

    def _split(self, text: str) -> None:
        at = 0
        while (end := text.find("\n", at)) >= 0:
            self.partial.append(text[at:end + 1])
            self.lines.append("".join(self.partial))
            self.partial.clear()
            at = end + 1
        if at < len(text):
            self.partial.append(text[at:])
        if self.ended and self.partial:  # the last line, without its newline: a line still
            self.lines.append("".join(self.partial))
            self.partial.clear()


async def _serve_stdio(server: MCPServer, fd: int, limit: int) -> None:
    from functools import partial

    from mcp.server.stdio import stdio_server
    from mcp.shared.message import ServerMessageMetadata, SessionMessage
    from mcp_types import JSONRPCError, JSONRPCNotification, JSONRPCRequest, JSONRPCResponse

    slots = anyio.Semaphore(limit)
    unanswered: dict[int | str, int] = {}  # the id of each request read and not answered: how many (ids may repeat)

    async def settled(request_id: int | str) -> None:
        if unanswered.get(request_id, 0) > 0:
            unanswered[request_id] -= 1
            if not unanswered[request_id]:
                del unanswered[request_id]
            slots.release()

    lines = _Lines(fd)
    async with stdio_server(stdin=lines) as (wire_in, wire_out):  # type: ignore[arg-type] - it iterates its lines
        to_server, server_in = anyio.create_memory_object_stream[SessionMessage | Exception](0)
        server_out, from_server = anyio.create_memory_object_stream[SessionMessage](0)

        async def inbound() -> None:
            async with to_server:
                while True:
                    await slots.acquire()  # before the next line is read: past the limit, stdin waits, not memory
                    try:
                        item = await wire_in.receive()
                    except (anyio.EndOfStream, anyio.ClosedResourceError):
                        return
                    line = lines.read.popleft() if lines.read else ""
                    if isinstance(item, SessionMessage) and isinstance(item.message, JSONRPCRequest):
                        request_id = item.message.id
                        unanswered[request_id] = unanswered.get(request_id, 0) + 1
                        # a request the agent cancels settles with no answer: the SDK says so through this hook
                        await to_server.send(SessionMessage(item.message, metadata=ServerMessageMetadata(
                            on_request_unanswered=partial(settled, request_id))))
                        continue
                    slots.release()  # a notification, a response, a line the SDK could not read: passed on now
                    if isinstance(item, SessionMessage) and not isinstance(item.message, JSONRPCNotification):
                        await to_server.send(item)  # a response to the server's own request
                    elif (answer := unreadable_answer(getattr(item, "message", item), line)) is not None:
                        await wire_out.send(SessionMessage(answer))
                    else:  # a notification, or what names nothing to answer: the SDK sets it aside
                        await to_server.send(item)

        async def outbound() -> None:
            async with wire_out:
                async for item in from_server:
                    await wire_out.send(item)
                    if isinstance(item.message, JSONRPCResponse | JSONRPCError) and item.message.id is not None:
                        await settled(item.message.id)  # handed to the writer: the request holds nothing more

        async with anyio.create_task_group() as tg:
            tg.start_soon(inbound)
            tg.start_soon(outbound)
            lowlevel = server._lowlevel_server  # what run("stdio") serves (mcp==2.3.0 has no public name for it)
            await lowlevel.run(server_in, server_out, lowlevel.create_initialization_options())


def unreadable_answer(item: Any, line: str) -> Any:
    """The JSON-RPC error answering ``line``, a request the SDK's transport could not take as one (``item``: the
    ``ValidationError`` it raised, or the notification it took the request for), or None where nothing waits for an
    answer (a notification, a response, a blank line). Its id is the request's where the request has one the
    answer can name (an integer or a string of valid Unicode); else JSON-RPC's ``null``, as JSON-RPC answers a
    request whose id cannot be read (a line that is not JSON, one the server would not parse, an id of ``5.5``,
    ``null``, ``true`` or with a lone surrogate)."""
    import json

    from mcp_types import INVALID_REQUEST, PARSE_ERROR, ErrorData, JSONRPCError, JSONRPCNotification
    from pydantic import ValidationError

    def answer(request_id: int | str | None, code: int, why: str) -> JSONRPCError:
        return JSONRPCError(jsonrpc="2.0", id=request_id, error=ErrorData(code=code,
                                                                           message=f"{why}; nothing was done"))

    if line.strip() in (TOO_LONG, TOO_MANY_VALUES, TOO_LONG_A_NUMBER):  # what bound_stdin_lines made of a message
        from pipeline.serve.messages import MAX_MESSAGE_VALUES, MAX_NUMBER_CHARS  # it let go

        return answer(None, INVALID_REQUEST, f"{json.loads(line)} (at most {MAX_MESSAGE_BYTES:,} bytes, "
                                             f"{MAX_MESSAGE_VALUES:,} values and numbers of {MAX_NUMBER_CHARS} "
                                             f"characters a message)")
    if not line.strip():
        return None
    try:  # Python's JSON reads what the SDK's refuses (a lone surrogate): enough to find the id
        message = json.loads(line)
    except (ValueError, RecursionError):  # not JSON, or nested deeper than Python's parser goes
        return answer(None, PARSE_ERROR, "the message is not JSON the server reads")
    if not isinstance(message, dict) or "method" not in message or "id" not in message:
        return None  # a response, a notification, or no message: nothing waits for an answer
    problems = item.errors(include_url=False) if isinstance(item, ValidationError) else []
    if problems and problems[0]["type"] == "json_invalid":
        code, why = PARSE_ERROR, f"the message is not JSON the server reads ({problems[0]['msg'][:200]})"
        try:
            json.dumps(message, ensure_ascii=False).encode("utf-8")
        except UnicodeEncodeError:
            why = "the message is not valid Unicode: a string in it holds a lone surrogate (such as \\ud800)"
    elif isinstance(item, ValidationError):  # JSON, not a JSON-RPC request
        shown = [f"{'.'.join(map(str, p['loc'][1:]))}: {p['msg']}" for p in problems if p["loc"][:1] == (
            "JSONRPCRequest",)]
        code, why = INVALID_REQUEST, f"the message is not a JSON-RPC request ({'; '.join(shown)[:300]})"
    elif isinstance(item, JSONRPCNotification):  # a request whose id the SDK's models dropped
        code, why = INVALID_REQUEST, "a request's id is a string or an integer (never null)"
    else:
        return None
    request_id = message["id"]
    if isinstance(request_id, bool) or not isinstance(request_id, int | str):
        request_id = None
    elif isinstance(request_id, str):
        try:
            request_id.encode("utf-8")
        except UnicodeEncodeError:  # its id itself holds a lone surrogate: no answer can name it
            request_id, why = None, "the message is not valid Unicode: its id holds a lone surrogate"
    return answer(request_id, code, why)


MAX_SESSIONS = 16
"""MCP sessions open at once over ``--mcp-port`` (an agent uses one; the SDK's default of 10,000, each ~37 KB, let
a client hold the port against every other for its 30-minute idle timeout)."""
SESSION_IDLE_TIMEOUT_S = 600.0
"""Seconds an MCP session may go unused before it is closed."""


def serve_streamable_http(server: MCPServer, port: int, listening: Callable[[int], None]) -> None:
    """Serve ``server`` over streamable HTTP on 127.0.0.1:``port`` (0: a free one) until Ctrl-C, as the SDK's own
    ``run("streamable-http")`` does, but on a socket bound here, so that ``listening`` gets the port really served
    (given 0, the SDK's server printed port 0) before the first request can come, and within the HTTP transport's
    bounds (``http.py``: connections at once, a whole request within its time), which uvicorn's defaults lack:
    1,100 connections that sent nothing were held for good, and the server died out of file descriptors."""
    import socket

    import uvicorn

    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port))
    sock.listen(128)  # connections made once the URL is said wait in the backlog, not refused, until uvicorn runs
    app = _values_bound(server.streamable_http_app(host="127.0.0.1", max_sessions=MAX_SESSIONS,
                                                   session_idle_timeout=SESSION_IDLE_TIMEOUT_S))
    listening(sock.getsockname()[1])
    uvicorn.Server(uvicorn.Config(app, http=_bounded_h11(), log_level=server.settings.log_level.lower(),
                                  timeout_keep_alive=5)).run(sockets=[sock])


MAX_OPENING_BYTES = 64 * 1024
"""The longest body of a request over ``--mcp-port`` that names no session (an ``initialize``, ~300 bytes: the
SDK refuses any other without a session): each session kept ~2 x its opening body, so 16 sessions opened with 4 MB
of a string in their params held the server at +128 MB for their idle timeout."""
MAX_HELD_BYTES = 32 * 2**20
"""Bytes of request bodies over ``--mcp-port`` held at once: each request holds its body's length (its
``Content-Length``; one sent without, the most it may be) from before its body is read until its answer is sent,
even where its client went away meanwhile (the SDK runs a request on without its client, holding its message). One
that would pass it is answered 503 at once, nothing of its body kept. A body the SDK holds costs ~2-4 x its bytes:
32 connections each sending 4 MiB to a slow tool grew the server by 558 MB, and 80 such requests whose clients hung
up as they were sent by 630 MB (linear: the connection bound let them go); now under ~150 MB. An honest request is
at most a policy's ~2.4 MB of JSON, and an agent runs a few at once."""


def _values_bound(app: Any) -> Any:
    """``app`` (the SDK's ASGI app) with each request's body read first, at most :data:`MAX_MESSAGE_BYTES`
    (:data:`MAX_OPENING_BYTES` for one that opens a session; 413 past it, as the SDK's own limit answers) and
    ``messages.MAX_MESSAGE_VALUES`` values and numbers of ``messages.MAX_NUMBER_CHARS`` characters (400 with a
    JSON-RPC error past them), then handed on whole. The SDK parses a body into Python objects whatever it holds,
    and keeps an ``initialize`` request's params with its session: 16 sessions opened with 3.5 MB of
    ``[{},{},...]`` in their params held the server at 1.57 GB (from 214 MB) for their idle timeout. The bodies
    held at once are at most :data:`MAX_HELD_BYTES` (503 past it), each held until its request is answered, its
    client there or not."""
    import json

    from pipeline.serve.messages import MAX_MESSAGE_VALUES, MAX_NUMBER_CHARS, json_long_number, json_values

    held = 0  # bytes of the bodies of the requests read or being read and not answered yet (one event loop)

    async def refuse(receive: Any, send: Any, status: int, why: str, more: bool) -> None:
        read = 0
        while more and read <= MAX_MESSAGE_BYTES:  # read on (to its end, or the SDK's limit), none of it kept,
            message = await receive()  # so that the client reads the answer
            if message["type"] != "http.request":  # the client went away: nothing to answer
                return
            read += len(message.get("body", b""))
            more = message.get("more_body", False)
        body = json.dumps({"jsonrpc": "2.0", "id": None, "error": {"code": -32600, "message": why}}).encode()
        await send({"type": "http.response.start", "status": status, "headers": [
            (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
            (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

    async def handed_on(scope: Any, receive: Any, send: Any, limit: int, too_long: str) -> None:
        # its body read whole, then handed to the app, which returns once the request is answered: a client
        # that goes away is not told to it (the SDK's answer stopped waiting while the request ran on, holding
        # its message, no longer counted), and the answer is sent to nobody
        parts, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] != "http.request":  # the client went away: nothing to answer
                return
            size += len(message.get("body", b""))
            more = message.get("more_body", False)
            if size > limit:  # sent without a length, and longer than it may be: none of it kept
                parts.clear()
                await refuse(receive, send, 413, too_long, more)
                return
            parts.append(message.get("body", b""))
        body = b"".join(parts)
        del parts
        if json_values(body) > MAX_MESSAGE_VALUES:
            await refuse(receive, send, 400, f"a message of more values than the server parses (at most "
                                             f"{MAX_MESSAGE_VALUES:,}); nothing was done", False)
            return
        if json_long_number(body):
            await refuse(receive, send, 400, f"a message with a number longer than the server parses (at most "
                                             f"{MAX_NUMBER_CHARS} characters); nothing was done", False)
            return
        handed = False

        async def replay() -> Any:
            nonlocal handed, body
            if not handed:
                handed, whole, body = True, body, b""
                return {"type": "http.request", "body": whole, "more_body": False}
            message = await receive()  # after the body, what the app waits for is the client's going away
            if message["type"] == "http.disconnect":
                await anyio.sleep_forever()  # ended by the app once the request is answered (into the void)
            return message

        await app(scope, replay, send)

    async def bounded(scope: Any, receive: Any, send: Any) -> None:
        nonlocal held
        if scope["type"] != "http" or scope.get("method") != "POST":
            await app(scope, receive, send)
            return
        headers = dict(scope.get("headers", ()))
        opening = b"mcp-session-id" not in headers
        limit = MAX_OPENING_BYTES if opening else MAX_MESSAGE_BYTES
        declared = headers.get(b"content-length", b"").strip()
        size = int(declared) if declared.isdigit() else None  # h11 refused a malformed one before the app
        too_long = (f"a message of more than {limit:,} bytes{' before a session is open' if opening else ''}; "
                    f"nothing was done")
        if size is not None and size > limit:
            await refuse(receive, send, 413, too_long, True)
            return
        taken = limit if size is None else size  # what this request may hold, taken before a byte of it is read
        if held + taken > MAX_HELD_BYTES:
            await refuse(receive, send, 503, f"the server holds {held:,} bytes of requests not answered yet (at "
                                             f"most {MAX_HELD_BYTES:,}): ask again when one is answered; nothing "
                                             f"was done", True)
            return
        held += taken
        try:
            await handed_on(scope, receive, send, limit, too_long)
        finally:
            held -= taken

    return bounded


def _bounded_h11() -> type:
    """uvicorn's HTTP/1.1 protocol with the bounds of ``http.py``: past ``MAX_CONNECTIONS`` a connection is closed
    as it opens; a connection that has not sent a whole request ``REQUEST_TIMEOUT_S`` after it opened (or after its
    last answer) is closed, unless an answer is under way (an event stream may run for long)."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    from pipeline.serve.http import MAX_CONNECTIONS, REQUEST_TIMEOUT_S

    class BoundedH11(H11Protocol):
        _deadline: Any = None

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            if len(self.connections) > MAX_CONNECTIONS:
                transport.close()
                return
            self._deadline = self.loop.call_later(REQUEST_TIMEOUT_S, self._past_deadline)

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self._deadline is not None:
                self._deadline.cancel()
            self._deadline = self.loop.call_later(REQUEST_TIMEOUT_S, self._past_deadline)

        def connection_lost(self, exc) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
            super().connection_lost(exc)

        def _past_deadline(self) -> None:
            waiting = self.cycle is None or self.cycle.response_complete or self.cycle.more_body
            if waiting and not self.transport.is_closing():
                self.transport.close()

    return BoundedH11
