"""The policy process's side of an episode: observations in, actions out, and nothing else within reach.

Policy code runs here, in a confined worker forked from the policy zygote (``pipeline/boundary/zygote.py``), a process that
never imported the emulator, OCAtari or gymnasium and cannot read them (``pipeline/boundary/confine.py``). The game host
(``pipeline/play/episodes.py``, ``pipeline/play/rollout.py``), a process where no policy code ever runs, holds the environment and drives this one over
a single socket, one round trip per step:

    host -> policy   J {"op": "start", policy_text, policy_name, seed, trace, trace_lines, call_time_limit_s, n_actions,
                        keep_printed}
    policy -> host   J {"kind": "ready"}  |  J {"kind": "failed", "end_reason": "policy_error", "error": ...}
    host -> policy   J {"op": "go", "cpu": N}       (the host's CPU: the pair shares one core, NOTES.md)
    host -> policy   O <marshal of the observation dict>          (once per step)
    policy -> host   a <8-byte action>  |  J {"kind": "failed", "end_reason": "policy_error"|"timeout", "error"}
    host -> policy   J {"op": "end", "more": bool}
    policy -> host   J {"kind": "done", "nodes": bool[, "printed", "printed_dropped"]}  [A <Arrow stream of the node rows>]

With ``"more": true`` (the next episode of a continued game follows: ``one_life="continue"``) the policy stays
loaded, its state and RNGs as they are, and the exchange goes on from ``go`` for the next episode, its node rows
recorded afresh (steps numbered from 0).

With ``keep_printed`` the policy's ``sys.stdout`` keeps what it prints (:class:`PrintedText`: the first
:data:`MAX_PRINTED_BYTES` bytes of each episode, and a count of the characters past them), sent with ``done``;
otherwise, and whatever it writes to its descriptors, its output goes to ``/dev/null``.

The host trusts nothing that comes back: an action is an int it checks against the game's actions, an error is
text it caps and cleans, the node rows are checked by the parent (``pipeline/play/episodes.py``). Observations are sent
with ``marshal`` because they come from the trusted host; nothing the policy sends is ever unmarshalled.
"""

from __future__ import annotations

import json
import marshal
import io
import math
import operator
import os
import random
import socket
import struct
import sys
import time
from typing import Any, Callable

import numpy as np
import numpy.random  # noqa: F401  (numpy loads it on first use: imported here, the zygote holds it for every worker)

from tracing.capture import NodeRecorder, failing_policy_line
from tracing.policy_file import PolicyLoadError, load_policy
from tracing.sandbox import CallTimer, PolicyTimeout

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


def describe_exception(exc: BaseException) -> str:
    """One line: the exception, and the innermost line of policy code it came from."""
    line, text = failing_policy_line(exc)
    where = f" at line {line}: `{text}`" if line and text else (f" at line {line}" if line else "")
    return f"{type(exc).__name__}: {exc}{where}"


class Channel:
    """Frames over one blocking stream socket (both ends of the host <-> policy connection use it)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buffer = bytearray()
        """Bytes read past the last frame returned (a frame begun, or the next one's start)."""
        self._chunk = bytearray(RECEIVE_CHUNK)
        self._chunk_view = memoryview(self._chunk)
        """Where each read lands: one buffer for the channel's life, not a new 64 KiB ``bytes`` per read."""
        self._timeout: float | None = -1.0
        """What the socket's timeout was last set to (-1: not set here)."""

    def _wait(self, timeout: float | None) -> None:
        """The socket's timeout for the next read (``settimeout`` costs a system call: only when it changes)."""
        if timeout != self._timeout:
            self.sock.settimeout(timeout)
            self._timeout = timeout

    def send(self, kind: bytes, payload: bytes) -> None:
        self.sock.sendall(HEADER.pack(kind, len(payload)) + payload)

    def send_json(self, obj: Any) -> None:
        self.send(b"J", json.dumps(obj, allow_nan=False, separators=(",", ":")).encode())

    def receive(self, limit: int, within: float | None = None) -> tuple[bytes, bytes]:
        """The next frame (kind, payload); EOFError when the other end is gone, ValueError for a frame over
        ``limit`` bytes. ``within``: seconds for the whole frame, header and payload (None: wait as long as it
        takes); past them ``TimeoutError``. It is the frame's deadline, not each read's: a policy process that
        trickles a frame a byte at a time held a host with a 1 s call limit for 34 s when each read had 2 s of its
        own (the episode then ended by the parent's kill, its steps lost)."""
        buffer = self.buffer
        self._wait(within)  # the first read may take it all (the same value every step: no system call)
        deadline = None if within is None else time.monotonic() + within
        if not buffer:  # the usual case, every step: nothing left over, and one read brings the whole frame
            read = self.sock.recv_into(self._chunk)
            if not read:
                raise EOFError
            if read >= HEADER.size:
                kind, size = HEADER.unpack_from(self._chunk)
                if size > limit:
                    raise ValueError(f"a frame of {size} bytes is over the limit of {limit}")
                if read == HEADER.size + size:
                    return kind, bytes(self._chunk_view[HEADER.size:read])
            buffer += self._chunk_view[:read]  # part of a frame, or more than one: the general path below
        while True:
            if len(buffer) >= HEADER.size:
                kind, size = HEADER.unpack_from(buffer)
                if size > limit:
                    raise ValueError(f"a frame of {size} bytes is over the limit of {limit}")
                end = HEADER.size + size
                if len(buffer) >= end:
                    payload = bytes(buffer[HEADER.size:end])
                    del buffer[:end]
                    return kind, payload
                if size > RECEIVE_CHUNK:
                    return kind, self._rest_of(size, deadline)
            if deadline is not None and buffer:  # a frame begun: the next read waits for what is left of it
                self._left(deadline)
            read = self.sock.recv_into(self._chunk)
            if not read:
                raise EOFError
            buffer += self._chunk_view[:read]

    def _left(self, deadline: float) -> None:
        """Wait for the next read only until ``deadline``; TimeoutError if it has passed."""
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the frame did not arrive whole in time")
        self._wait(left)

    def _rest_of(self, size: int, deadline: float | None = None) -> bytes:
        """The payload of a large frame (the node rows at the end of an episode) whose header and first bytes are
        in the buffer: the rest read in pieces of up to :data:`LARGE_PIECE` and joined once (growing the buffer
        piece by piece copied it over and over: 4 ms for 2 MB, against 0.4), all by ``deadline``."""
        buffer = self.buffer
        pieces = [bytes(buffer[HEADER.size:])]
        del buffer[:]
        have = len(pieces[0])
        while have < size:
            if deadline is not None:
                self._left(deadline)
            piece = self.sock.recv(min(size - have, LARGE_PIECE), socket.MSG_WAITALL)
            if not piece:
                raise EOFError
            pieces.append(piece)
            have += len(piece)
        return b"".join(pieces)


def policy_task(start: dict[str, Any], fd: int, _extra_fd: int | None) -> Callable[[int | None], None]:
    """The policy zygote's ``policy`` task, in the confined worker: ``start`` is the host's first message (read
    from ``fd``, the socket to the host, by the zygote): seed the RNGs and load the policy at once (while the
    host resets its environment), then serve the host's observations."""
    if start.get("op") != "start":
        raise ValueError("the host's first message is not a start")
    side = PolicySide(Channel(socket.socket(fileno=fd)), start)
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
            nodes = self.recorder.table() if self.recorder is not None else None
            channel.send_json({"kind": "done", "nodes": nodes is not None,
                               **(self.printed.take() if self.printed is not None else {})})
            if nodes is not None:
                from pipeline.boundary.wire import arrow_frame

                channel.sock.sendall(arrow_frame(nodes))
            if not more:
                return
            self.recorder = NodeRecorder(lines=self.lines) if self.trace else None
            more = self._play()

    def _play(self) -> bool:
        """One episode's exchange; whether the host asked for more (the next episode of the same game)."""
        channel, policy, recorder, n_actions = self.channel, self.policy, self.recorder, self.n_actions
        send_answer, answers = channel.sock.sendall, action_frames(n_actions)
        step, failed = -1, False
        with CallTimer() as timer, (recorder if recorder is not None else _nothing()):
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
                    action = timer.call(self.call_limit, policy, obs)
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
