"""The policy process's side of an episode: observations in, actions out, and nothing else within reach.

Policy code runs here, in a confined worker forked from the policy zygote (``pipeline/boundary/zygote.py``), a
process that never imported the emulator, OCAtari or gymnasium and cannot read them
(``pipeline/boundary/confine.py``). The game host (``pipeline/play/episodes.py``, ``pipeline/play/rollout.py``), a
process where no policy code ever runs, holds the environment and drives this one, one round trip per step: over
the socket the pair was given until the go-ahead, which hands the policy process two pipes, and over them from
then on (:class:`Channel`):

    host -> policy   J {"op": "start", policy_text, policy_name, seed, trace, trace_lines, call_time_limit_s, n_actions,
                        keep_printed}
    policy -> host   J {"kind": "ready"}  |  J {"kind": "failed", "end_reason": "policy_error", "error": ...}
    host -> policy   J {"op": "go", "cpu": N}       (the host's CPU: the pair shares one core, NOTES.md; the first
                                                   go-ahead brings the pipes, passed beside it)
    host -> policy   O <marshal of the observation dict>          (once per step)
    policy -> host   a <8-byte action>  |  J {"kind": "failed", "end_reason": "policy_error"|"timeout", "error"}
    host -> policy   J {"op": "end", "more": bool}
    policy -> host   J {"kind": "done", "nodes": bool[, "no_nodes", "printed", "printed_dropped"]}
                     [A <Arrow stream of the node rows>]

With ``"more": true`` (the next episode of a continued game follows: ``one_life="continue"``) the policy stays
loaded, its state and RNGs as they are, and the exchange goes on from ``go`` for the next episode, its node rows
recorded afresh (steps numbered from 0). A traced episode whose node rows could not be made says why in ``no_nodes``
(``"nodes": false``): the host records that as the episode's error, as it does a process that ends before its rows
arrive (``pipeline/play/channels.py``): a traced episode never passes for one whose calls made no rows.

With ``keep_printed`` the policy's ``sys.stdout`` keeps what it prints (:class:`PrintedText`: the first
:data:`MAX_PRINTED_BYTES` bytes of each episode, and a count of the characters past them), sent with ``done``;
otherwise, and whatever it writes to its descriptors, its output goes to ``/dev/null``.

The host trusts nothing that comes back: an action is an int it checks against the game's actions, an error is
text it caps and cleans, the node rows are checked by the parent (``pipeline/play/episodes.py``). Observations are sent
with ``marshal`` because they come from the trusted host; nothing the policy sends is ever unmarshalled.
"""

from __future__ import annotations

import array
import io
import json
import marshal
import math
import operator
import os
import random
import select
import socket
import struct
import sys
import time
from typing import Any, Callable

import numpy as np
import numpy.random  # noqa: F401  (numpy loads it on first use: imported here, the zygote holds it for every worker)

from pipeline.boundary.wire import json_frame
from tracing.capture import NodeRecorder, exception_message, exception_name, failing_policy_line
from tracing.policy_file import PolicyLoadError, load_policy
from tracing.sandbox import EpisodeTimer, PolicyTimeout

ACTION = struct.Struct("<q")
"""The payload of an ``a`` frame: the action, as a signed 64-bit int (the host checks its range)."""
HEADER = struct.Struct(">cI")
"""A frame's kind byte and payload length (as ``pipeline/boundary/wire.py``'s frames)."""
RECEIVE_CHUNK = 64 * 1024
"""Bytes asked of the socket at a time: a buffer this size comes from the allocator's arena, where one of a
megabyte would be mapped and unmapped again on every step."""
LARGE_PIECE = 4 * 2**20
"""The most a large frame is read at once (the socket's ``recv`` allocates that much before it reads)."""
MAX_OBSERVATION = 16 * 2**20
MAX_ERROR_CHARS = 2_000
"""Characters of a failure's error text (what the store keeps of it: ``untrusted.MESSAGE_LIMIT``)."""
MAX_ANSWER = 32 * 1024
"""The largest frame the host reads from the policy process before the episode's end (ready, an action, a
failure): refused at its header, before it is read or decoded. A failure's error of :data:`MAX_ERROR_CHARS`
characters is at most 12 bytes a character as JSON (an astral character escaped as two ``\\uXXXX``)."""
MAX_PRINTED_BYTES = 4_096
"""UTF-8 bytes of what a policy prints that an episode keeps (``keep_printed``). Sent in the ``done`` frame, which
the host reads within :data:`MAX_ANSWER`: a byte is at most 6 bytes as JSON (a control character as ``\\u00XX``),
so 4 KiB of the worst text is 24 KiB."""
MAX_NO_NODES_CHARS = 300
"""Characters of ``no_nodes``, why a traced episode's node rows could not be made: 3.6 KB at most as JSON, beside
:data:`MAX_PRINTED_BYTES` in the ``done`` frame."""


class PrintedText(io.TextIOBase):
    """The ``sys.stdout`` of a policy process that keeps what the policy prints: the first ``limit`` UTF-8 bytes of
    an episode's output, and a count of the characters past them (never held: a policy printing 50 MB holds no more
    than its own strings)."""

    def __init__(self, limit: int = MAX_PRINTED_BYTES) -> None:
        super().__init__()
        self.limit = limit
        self.kept: list[str] = []
        self.held = 0
        self.dropped = 0

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        if not isinstance(text, str):
            raise TypeError(f"write() argument must be str, not {type(text).__name__}")
        room = self.limit - self.held if not self.dropped else 0  # once a character is dropped, keep no later one
        head = ""
        if room > 0:  # ``room`` characters are at least ``room`` bytes: cut there, on a character's boundary
            head = text[:room].encode("utf-8", "replace")[:room].decode("utf-8", "ignore")
            self.kept.append(head)
            self.held += len(head.encode("utf-8"))
        self.dropped += len(text) - len(head)
        return len(text)

    def take(self) -> dict[str, Any]:
        """What was printed since the last take, as the ``done`` frame's fields; the buffer starts afresh."""
        fields = {"printed": "".join(self.kept), "printed_dropped": self.dropped}
        self.kept, self.held, self.dropped = [], 0, 0
        return fields


PRINTED_TEXT_BYTES = MAX_PRINTED_BYTES + 128
"""UTF-8 bytes of an episode's printed text as the host passes it on: the kept bytes and the line that counts the
rest (:func:`printed_text`)."""


def printed_text(message: dict[str, Any]) -> str | None:
    """The host's reading of what a policy printed, from its ``done`` message (untrusted, already bounded by
    :data:`MAX_ANSWER`): the text cut to :data:`MAX_PRINTED_BYTES` UTF-8 bytes, and a line counting the characters
    that were not kept; None when the message holds no text."""
    text, dropped = message.get("printed"), message.get("printed_dropped")
    if not isinstance(text, str):
        return None
    text = text.encode("utf-8", "replace")[:MAX_PRINTED_BYTES].decode("utf-8", "ignore")
    if isinstance(dropped, int) and not isinstance(dropped, bool) and dropped > 0:
        text += f"\n… [{min(dropped, 10**15):,} more characters printed, not kept]"
    return text


def capped_error(text: str) -> str:
    """An error text cut to :data:`MAX_ERROR_CHARS` characters, the cut marked, so its failure frame fits
    :data:`MAX_ANSWER`."""
    if len(text) <= MAX_ERROR_CHARS:
        return text
    return f"{text[:MAX_ERROR_CHARS]}… [cut {len(text) - MAX_ERROR_CHARS:,} characters]"


def coerce_action(action: Any, n_actions: int) -> int:
    """The policy's return value as a legal action index, or ValueError saying why it is not one."""
    if isinstance(action, (bool, np.bool_)):
        raise ValueError(f"illegal action {action!r}: expected an int in 0..{n_actions - 1}, got a bool")
    try:
        index = operator.index(action)
    except TypeError:
        raise ValueError(
            f"illegal action {action!r}: expected an int in 0..{n_actions - 1}, got {type(action).__name__}"
        ) from None
    if not 0 <= index < n_actions:
        raise ValueError(f"illegal action {index}: legal actions are 0..{n_actions - 1}")
    return index


MAX_ERROR_MESSAGE_CHARS = 1_000
"""Characters of the exception's message in :func:`describe_exception`'s line: with the name and the line's text
(``capture.MAX_NAME_CHARS``, ``capture.MAX_SOURCE_CHARS``) within :data:`MAX_ERROR_CHARS`, so the location is
never what a cap cuts off."""


def describe_exception(exc: BaseException) -> str:
    """One line: the exception's name, its message and the innermost line of policy code it came from (``Name:
    message at line N: `text```, ``Name at line N`` where it says nothing), each part bounded: a 100,000-character
    message hid the location past the cap of the error; an exception whose ``__str__`` raises is still named, at
    its own line (``capture.exception_message``)."""
    line, text = failing_policy_line(exc)
    where = f" at line {line}: `{text}`" if line and text else (f" at line {line}" if line else "")
    name, said = exception_name(exc), exception_message(exc, MAX_ERROR_MESSAGE_CHARS)
    return f"{name}: {said}{where}" if said else f"{name}{where}"  # MemoryError() says ""


class Channel:
    """Frames between a game host and its policy process (both ends use it).

    The connection begins on the socket the pair was given (the policy's start, its ready or its failure). With the
    episode's go-ahead the host hands the policy process two pipes (:meth:`send_handing_over`, the pipes' ends passed
    with that frame), and every frame after it goes over them: a pipe's write and read cost about half of a Unix
    stream socket's here (a socket's buffers are allocated and charged to the memory cgroup for every message;
    a round trip between two processes on one CPU: ~5 µs against ~9, docs/benchmarks.md), and the exchange is one
    frame each way per step.

    A ``timed`` end (the host's) never blocks past a frame's deadline: its descriptors are non-blocking and it waits
    in ``poll``; the policy process's end blocks (its host ends the episode, or its parent kills it).
    """

    def __init__(self, sock: socket.socket, timed: bool = False, pipes_from_host: bool = False) -> None:
        self.sock: socket.socket | None = sock
        self.read_fd = self.write_fd = sock.fileno()
        self.timed = timed
        if timed:
            sock.setblocking(False)
        self.piped = False
        """Whether the frames go over the pipes (after the go-ahead) rather than the socket."""
        self._awaiting_pipes = pipes_from_host
        """The policy process's end, before the go-ahead: its reads take the pipes the host passes with it."""
        self.buffer = bytearray()
        """Bytes read past the last frame returned (a frame begun, or the next one's start)."""
        self._chunk = bytearray(RECEIVE_CHUNK)
        self._chunk_view = memoryview(self._chunk)
        """Where each read lands: one buffer for the channel's life, not a new 64 KiB ``bytes`` per read."""
        self._readable = select.poll()
        self._readable.register(self.read_fd, select.POLLIN)
        self._writable = select.poll()
        self._writable.register(self.write_fd, select.POLLOUT)

    def _use(self, read_fd: int, write_fd: int) -> None:
        """Go on over ``read_fd`` and ``write_fd`` (the pipes), the socket closed."""
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        self.read_fd, self.write_fd, self.piped = read_fd, write_fd, True
        if self.timed:
            os.set_blocking(read_fd, False)
            os.set_blocking(write_fd, False)
        self._readable = select.poll()
        self._readable.register(read_fd, select.POLLIN)
        self._writable = select.poll()
        self._writable.register(write_fd, select.POLLOUT)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        elif self.piped:
            for fd in (self.read_fd, self.write_fd):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self.piped = False
        self.read_fd = self.write_fd = -1

    @staticmethod
    def _wait(poller: select.poll, deadline: float | None) -> None:
        """Wait until ``poller``'s descriptor is ready, at most until ``deadline`` (``time.monotonic()``; None: as
        long as it takes, as for an infinite one); TimeoutError past it."""
        if deadline is None or deadline == math.inf:
            poller.poll()
            return
        left = deadline - time.monotonic()
        if left <= 0 or not poller.poll(math.ceil(left * 1000)):
            raise TimeoutError("the frame did not pass whole in time")

    def write_all(self, data: bytes, within: float | None = None) -> None:
        """Write ``data`` whole; a timed end waits at most ``within`` seconds for room (TimeoutError)."""
        try:
            written = os.write(self.write_fd, data)
        except BlockingIOError:
            written = 0
        if written == len(data):  # the usual case, every step: the pipe had room for the frame
            return
        view = memoryview(data)[written:]
        deadline = None if within is None else time.monotonic() + within
        while view:
            self._wait(self._writable, deadline)
            try:
                view = view[os.write(self.write_fd, view):]
            except BlockingIOError:
                pass

    def send(self, kind: bytes, payload: bytes, within: float | None = None) -> None:
        self.write_all(HEADER.pack(kind, len(payload)) + payload, within)

    def send_json(self, obj: Any, within: float | None = None) -> None:
        self.write_all(json_frame(obj), within)

    def send_handing_over(self, obj: Any, within: float) -> None:
        """The host's end: send ``obj`` (the go-ahead) on the socket with the policy process's ends of two new pipes,
        then go on over the pipes (see the class docstring)."""
        frame = json_frame(obj)
        to_policy_r, to_policy_w = os.pipe2(os.O_CLOEXEC)
        to_host_r, to_host_w = os.pipe2(os.O_CLOEXEC)
        try:
            self._wait(self._writable, time.monotonic() + within)
            if socket.send_fds(self.sock, [frame], [to_policy_r, to_host_w]) != len(frame):
                raise OSError("the go-ahead was not sent whole")
        except BaseException:
            for fd in (to_policy_w, to_host_r):
                os.close(fd)
            raise
        finally:
            os.close(to_policy_r)  # the policy process holds them now: when it ends, the host reads EOF
            os.close(to_host_w)
        self._use(to_host_r, to_policy_w)

    def receive(self, limit: int, within: float | None = None) -> tuple[bytes, bytes]:
        """The next frame (kind, payload); EOFError when the other end is gone, ValueError for a frame over
        ``limit`` bytes. ``within``: seconds for the whole frame, header and payload (None: wait as long as it
        takes); past them ``TimeoutError``. It is the frame's deadline, not each read's: a policy process that
        trickles a frame a byte at a time held a host with a 1 s call limit for 34 s when each read had 2 s of its
        own (the episode then ended by the parent's kill, its steps lost)."""
        if self._awaiting_pipes:
            return self._receive_taking_pipes(limit)
        buffer = self.buffer
        deadline = None if within is None else time.monotonic() + within
        if not buffer:  # the usual case, every step: nothing left over, and one read brings the whole frame
            if within is not None and within != math.inf and not self._readable.poll(math.ceil(within * 1000)):
                raise TimeoutError("the frame did not pass whole in time")
            try:
                read = os.readv(self.read_fd, [self._chunk])
            except BlockingIOError:  # a timed end with no deadline, or woken for nothing
                read = self._read(deadline)
            if not read:
                raise EOFError
            if read >= HEADER.size:
                kind, size = _header(self._chunk, limit)
                if read == HEADER.size + size:
                    return kind, bytes(self._chunk_view[HEADER.size:read])
            buffer += self._chunk_view[:read]  # part of a frame, or more than one: the general path below
        while True:
            if len(buffer) >= HEADER.size:
                kind, size = _header(buffer, limit)
                end = HEADER.size + size
                if len(buffer) >= end:
                    payload = bytes(buffer[HEADER.size:end])
                    del buffer[:end]
                    return kind, payload
                if size > RECEIVE_CHUNK:
                    return kind, self._rest_of(size, deadline)
            read = self._read(deadline)
            if not read:
                raise EOFError
            buffer += self._chunk_view[:read]

    def _read(self, deadline: float | None) -> int:
        """Read what has come (at most a chunk) into the chunk; 0 at the end of the stream."""
        if deadline is not None:
            self._wait(self._readable, deadline)
        while True:
            try:
                return os.readv(self.read_fd, [self._chunk])
            except BlockingIOError:  # a timed end with no deadline, or woken for nothing
                self._wait(self._readable, deadline)

    def _rest_of(self, size: int, deadline: float | None = None) -> bytes:
        """The payload of a large frame (the node rows at the end of an episode) whose header and first bytes are
        in the buffer: the rest read in pieces of up to :data:`LARGE_PIECE` and joined once (growing the buffer
        piece by piece copied it over and over: 4 ms for 2 MB, against 0.4), all by ``deadline``. A piece's
        memory is taken as its bytes arrive, never the whole frame's at its header's word."""
        buffer = self.buffer
        pieces = [bytes(buffer[HEADER.size:])]
        del buffer[:]
        have = len(pieces[0])
        while have < size:
            if deadline is not None:
                self._wait(self._readable, deadline)
            try:
                piece = os.read(self.read_fd, min(size - have, LARGE_PIECE))
            except BlockingIOError:
                self._wait(self._readable, deadline)
                continue
            if not piece:
                raise EOFError
            pieces.append(piece)
            have += len(piece)
        return b"".join(pieces)

    def _receive_taking_pipes(self, limit: int) -> tuple[bytes, bytes]:
        """The policy process's end before the go-ahead: the next frame (a go-ahead, or an end before any), read
        with the descriptors passed beside it; the pipes that come with the go-ahead carry every frame after it."""
        buffer, passed = self.buffer, []
        try:
            while True:
                if len(buffer) >= HEADER.size:
                    kind, size = _header(buffer, limit)
                    end = HEADER.size + size
                    if len(buffer) >= end:
                        break
                read, ancillary, flags, _ = self.sock.recvmsg_into([self._chunk], PASSED_PIPES_SPACE)
                passed += passed_descriptors(ancillary)
                if flags & socket.MSG_CTRUNC:
                    raise ValueError("descriptors passed with a frame were lost")
                if not read:
                    raise EOFError
                buffer += self._chunk_view[:read]
            payload = bytes(buffer[HEADER.size:end])
            del buffer[:end]
            if passed:
                if len(passed) != 2 or buffer:
                    raise ValueError("the go-ahead came with other than two pipes, or with more after it")
                self._awaiting_pipes = False
                self._use(*passed)
                passed = []
            return kind, payload
        finally:
            for fd in passed:
                os.close(fd)


def _header(data: bytes | bytearray, limit: int) -> tuple[bytes, int]:
    """The kind and payload size of the frame ``data`` begins with; ValueError for a payload over ``limit``."""
    kind, size = HEADER.unpack_from(data)
    if size > limit:
        raise ValueError(f"a frame of {size} bytes is over the limit of {limit}")
    return kind, size


PASSED_PIPES_SPACE = socket.CMSG_SPACE(2 * array.array("i").itemsize)
"""Room for the two descriptors of the go-ahead (one more would set ``MSG_CTRUNC``)."""


def passed_descriptors(ancillary: list[tuple[int, int, bytes]]) -> list[int]:
    """The descriptors an ``SCM_RIGHTS`` message brought (``recvmsg``'s ancillary data)."""
    fds = array.array("i")
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
            fds.frombytes(data[:len(data) - len(data) % fds.itemsize])
    return list(fds)


def policy_task(start: dict[str, Any], fd: int, _extra_fd: int | None) -> Callable[[int | None], None]:
    """The policy zygote's ``policy`` task, in the confined worker: ``start`` is the host's first message (read
    from ``fd``, the socket to the host, by the zygote): seed the RNGs and load the policy at once (while the
    host resets its environment), then serve the host's observations."""
    if start.get("op") != "start":
        raise ValueError("the host's first message is not a start")
    side = PolicySide(Channel(socket.socket(fileno=fd), pipes_from_host=True), start)
    return lambda cpu: side.serve()


class PolicySide:
    """One episode's policy, answering the host's observations (see the module docstring)."""

    def __init__(self, channel: Channel, start: dict[str, Any]) -> None:
        self.channel = channel
        self.n_actions = int(start["n_actions"])
        self.call_limit = float(start.get("call_time_limit_s") or 0) or math.inf
        self.trace, self.lines = bool(start.get("trace")), bool(start.get("trace_lines", True))
        self.recorder = NodeRecorder(lines=self.lines) if self.trace else None
        self.printed: PrintedText | None = None
        if start.get("keep_printed") is True:  # from before the policy loads: a print in its class body counts too
            sys.stdout = self.printed = PrintedText()
        seed = int(start.get("seed", 0))
        random.seed(seed)
        np.random.seed(seed % 2**32)
        self.error: str | None = None
        try:
            self.policy = load_policy(start["policy_text"], start.get("policy_name", "policy.py")).policy
        except PolicyLoadError as exc:
            self.policy, self.error = None, str(exc)

    def serve(self) -> None:
        """Answer until the host ends the episode, then send the node rows (and again for each next episode of a
        continued game)."""
        channel = self.channel
        more = False
        if self.policy is None:
            channel.send_json({"kind": "failed", "end_reason": "policy_error", "error": capped_error(self.error)})
        else:
            channel.send_json({"kind": "ready"})
            more = self._play()
        while True:
            nodes, why = self._node_frame()
            channel.send_json({"kind": "done", "nodes": nodes is not None, **({"no_nodes": why} if why else {}),
                               **(self.printed.take() if self.printed is not None else {})})
            if nodes is not None:
                channel.write_all(nodes)
            if not more:
                return
            self.recorder = NodeRecorder(lines=self.lines) if self.trace else None
            more = self._play()

    def _node_frame(self) -> tuple[bytes | None, str | None]:
        """The episode's node rows as a frame, or None and why they could not be made (a traced episode's host
        records that as the episode's error; this process dying here, the table unsent, gave it none at all)."""
        if self.recorder is None:
            return None, None
        from pipeline.boundary.wire import arrow_frame  # looked up at each end, as a policy may swap it (tests/faults)

        try:
            return arrow_frame(self.recorder.table()), None
        except Exception as exc:  # noqa: BLE001 - a value out of its column's range, memory: the episode says so
            return None, f"{exception_name(exc)}: {exception_message(exc, MAX_NO_NODES_CHARS)}"

    def _play(self) -> bool:
        """One episode's exchange; whether the host asked for more (the next episode of the same game)."""
        channel, policy, recorder, n_actions = self.channel, self.policy, self.recorder, self.n_actions
        send_answer, answers = channel.write_all, action_frames(n_actions)
        step, failed = -1, False
        with EpisodeTimer(self.call_limit) as timer, (recorder if recorder is not None else _nothing()):
            while True:
                kind, payload = channel.receive(MAX_OBSERVATION)
                if kind == b"J":
                    message = json.loads(payload)
                    if message.get("op") == "go":
                        _pin(message.get("cpu"))
                        continue
                    return message.get("more") is True and not failed  # "end"
                if kind != b"O" or failed:
                    raise ValueError("an observation after the policy failed, or a frame of an unknown kind")
                obs = marshal.loads(payload)
                step += 1
                if recorder is not None:
                    recorder.begin_step(step, obs)
                try:
                    action = timer.call(policy, obs)
                    send_answer(answers[coerce_action(action, n_actions)])
                    continue
                except PolicyTimeout as exc:
                    end_reason, error = "timeout", _describe(exc)
                except KeyboardInterrupt:
                    raise
                except BaseException as exc:  # noqa: BLE001 - untrusted code: anything, SystemExit too
                    end_reason, error = "policy_error", _describe(exc)
                failed = True
                channel.send_json({"kind": "failed", "end_reason": end_reason, "error": error})


def action_frames(n_actions: int) -> list[bytes]:
    """The ``a`` frame of each legal action, made once an episode instead of packed every step."""
    return [HEADER.pack(b"a", ACTION.size) + ACTION.pack(index) for index in range(n_actions)]


def _describe(exc: BaseException) -> str:
    """:func:`describe_exception` as plain, capped text, whatever the exception's ``__str__`` does (the host's
    deadline stops one that never returns)."""
    try:
        text = str(describe_exception(exc))
        return capped_error(text).encode("utf-8", "replace").decode("utf-8")
    except BaseException:  # noqa: BLE001 - a str subclass or __str__ that misbehaves
        return "the policy raised an exception that could not be described"


def _pin(cpu: Any) -> None:
    """Run on the host's CPU: a round trip between two processes on one core costs a few microseconds, across
    cores tens (NOTES.md)."""
    if isinstance(cpu, int) and not isinstance(cpu, bool):
        try:
            os.sched_setaffinity(0, {cpu})
        except OSError:
            pass


class _nothing:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None
