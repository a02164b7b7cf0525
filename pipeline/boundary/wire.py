"""What crosses between the parent and its workers (game hosts, policy processes): plain data only, checked on arrival.

A message is a frame: one kind byte (``J`` JSON, ``A`` an Arrow IPC stream) and a 4-byte big-endian length,
then that many bytes. The parent sends one ``J`` frame (the task, e.g. an episode's spec as a JSON object of
primitives) and, to a staged worker, its go-ahead (:data:`GO`); the worker answers ``J`` frames
(``{"kind": "progress", ...}`` while it works, then ``{"kind": "result", ...}`` or ``{"kind": "error", ...}``)
and, after an episode's result, its steps (and nodes) as Arrow streams. Nothing is ever unpickled, imported or
executed by the receiver. (Between a host and its policy process the frames of ``pipeline/boundary/policy.py``
carry one observation out and one action back per step.)

This module owns the checks of every message: :class:`FrameReader` caps frame sizes, :func:`parse_message`
checks a message's kind and the fields of each kind (progress counts, error text),
:func:`parse_arrow` a table's schema, :func:`text_answer` the fields of a JSON task's result; anything else
raises :class:`BadMessage` (the parent then records the task as failed with that reason). The fields of a
task's own result are checked by the task: an episode's by ``pipeline/play/episodes.py``.
"""

from __future__ import annotations

import json
import os
import struct
from functools import lru_cache
from typing import Any

HEADER = struct.Struct(">cI")
GO = struct.Struct(">ch")
"""A staged worker's go-ahead: ``G`` and the CPU to run on (-1: anywhere)."""
NEXT = b"N"
"""Sent to a game host after its answer, the next task's second socket attached (SCM_RIGHTS), then the task as a
JSON frame (``pipeline/boundary/zygote.py``: ``Role.serves_many``). EOF instead: the host exits."""
MAX_JSON = 4 * 2**20
MAX_ARROW = 512 * 2**20
MAX_TEXT = 20_000
"""Longest error text kept from a worker."""

class BadMessage(Exception):
    """A worker sent something other than what the protocol allows; ``str()`` says what."""


def json_frame(obj: Any) -> bytes:
    data = json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()
    return HEADER.pack(b"J", len(data)) + data


def arrow_frame(table: Any) -> bytes:
    import pyarrow as pa

    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    data = sink.getvalue().to_pybytes()
    return HEADER.pack(b"A", len(data)) + data


def raw_arrow_frame(payload: bytes) -> bytes:
    """An Arrow frame around bytes that already are an Arrow IPC stream (relayed unread, checked by the receiver)."""
    return HEADER.pack(b"A", len(payload)) + payload


def write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def read_frame(fd: int, limit: int = MAX_JSON) -> tuple[bytes, bytes]:
    """One frame from a blocking fd: (kind, payload); EOFError at the end."""
    def exactly(n: int) -> bytes:
        chunks, left = [], n
        while left:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                raise EOFError
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)

    kind, size = HEADER.unpack(exactly(HEADER.size))
    if size > limit:
        raise BadMessage(f"a frame of {size} bytes is over the limit of {limit}")
    return kind, exactly(size)


class FrameReader:
    """Frames from bytes arriving in pieces (a non-blocking socket), sizes capped.

    The pieces of a frame are kept as they came and joined once it is whole: appending each piece to one buffer
    copied the whole buffer again every few pieces (4 ms for an episode's 2 MB of node rows, against 0.5)."""

    def __init__(self) -> None:
        self.pieces: list[bytes] = []
        self.held = 0
        """Bytes in ``pieces``."""
        self.needed = HEADER.size
        """Bytes to hold before the next frame (or its header) can be read."""

    def feed(self, data: bytes) -> list[tuple[bytes, bytes]]:
        if data:
            self.pieces.append(bytes(data))
            self.held += len(data)
        if self.held < self.needed:
            return []
        buffer = self.pieces[0] if len(self.pieces) == 1 else b"".join(self.pieces)
        frames, at, needed = [], 0, HEADER.size
        while len(buffer) - at >= HEADER.size:
            kind, size = HEADER.unpack_from(buffer, at)
            if kind not in (b"J", b"A"):
                raise BadMessage(f"unknown frame kind {kind!r}")
            if size > (MAX_JSON if kind == b"J" else MAX_ARROW):
                raise BadMessage(f"a {'JSON' if kind == b'J' else 'Arrow'} frame of {size} bytes is over the limit")
            end = at + HEADER.size + size
            if len(buffer) < end:
                needed = end - at
                break
            frames.append((kind, buffer[at + HEADER.size:end]))
            at = end
        rest = buffer[at:] if at else buffer
        self.pieces = [rest] if rest else []
        self.held, self.needed = len(rest), needed
        return frames


def parse_json(payload: bytes) -> dict[str, Any]:
    try:
        obj = json.loads(payload, parse_constant=lambda c: (_ for _ in ()).throw(BadMessage(f"JSON constant {c}")))
    except (ValueError, RecursionError) as exc:
        raise BadMessage(f"malformed JSON from the worker: {str(exc)[:200]}") from None
    if not isinstance(obj, dict) or not isinstance(obj.get("kind"), str):
        raise BadMessage("a worker message must be a JSON object with a 'kind'")
    return obj


MAX_BATCHES = 64
"""Record batches one Arrow stream may hold (a writer sends one per table; more only make readers copy)."""
MAX_BATCH_METADATA = 64 * 1024
"""Bytes of one record batch message's metadata (a table of the protocol's few columns needs about 1 KB)."""


def _flat_field(meta: bytes, table: int, index: int) -> int | None:
    """Where field ``index`` of the flatbuffer table at ``table`` lies in ``meta`` (None: absent); struct.error or
    IndexError for offsets outside ``meta``."""
    vtable = table - struct.unpack_from("<i", meta, table)[0]
    size = struct.unpack_from("<H", meta, vtable)[0]
    if 4 + 2 * index + 2 > size:
        return None
    offset = struct.unpack_from("<H", meta, vtable + 4 + 2 * index)[0]
    return table + offset if offset else None


def batch_header(meta: bytes) -> tuple[int, bool, int]:
    """(rows, compressed, bytes its buffers span in all) of a record batch message's metadata (the ``Message``
    flatbuffer of Arrow's ``Message.fbs``: its ``header``, a ``RecordBatch``, has ``length``, ``buffers`` and
    ``compression``), read before its body is decoded (reading the body of a compressed batch is what inflates:
    100 KB of zstd became three 1 GiB strings); BadMessage for
    metadata that is not one, or that carries key/value metadata (a vector of tables whose offsets may all point
    at one entry: read many times over, it costs what was never sent)."""
    try:
        root = struct.unpack_from("<I", meta, 0)[0]
        if _flat_field(meta, root, 4) is not None:  # Message.custom_metadata
            raise BadMessage("a record batch message with key/value metadata")
        header = _flat_field(meta, root, 2)  # Message.header
        if header is None:
            raise BadMessage("a record batch message without its header")
        batch = header + struct.unpack_from("<I", meta, header)[0]
        length = _flat_field(meta, batch, 0)  # RecordBatch.length
        rows = struct.unpack_from("<q", meta, length)[0] if length is not None else 0
        buffers = _flat_field(meta, batch, 2)  # RecordBatch.buffers: a vector of Buffer structs (offset, length)
        spanned = 0
        if buffers is not None:
            vector = buffers + struct.unpack_from("<I", meta, buffers)[0]
            count = struct.unpack_from("<I", meta, vector)[0]
            if vector + 4 + 16 * count > len(meta):
                raise BadMessage("a record batch message whose metadata is malformed")
            for i in range(count):
                offset, size = struct.unpack_from("<qq", meta, vector + 4 + 16 * i)
                if offset < 0 or size < 0:
                    raise BadMessage("a record batch buffer at a negative offset or of a negative size")
                spanned += size
        return rows, _flat_field(meta, batch, 3) is not None, spanned  # RecordBatch.compression
    except (struct.error, IndexError):
        raise BadMessage("a record batch message whose metadata is malformed") from None


@lru_cache(maxsize=16)
def schema_message(schema: Any) -> bytes:
    """The protocol's encapsulated schema message of ``schema``: the exact bytes a writer of this pyarrow begins an
    IPC stream with (both sides run the same environment)."""
    return schema.serialize().to_pybytes()


def parse_arrow(payload: bytes, schema: Any, max_rows: int | None = None) -> Any:
    """The table of an Arrow IPC stream, fully validated and of exactly ``schema``, each stage bounded by the bytes
    received before it runs:

    - the schema is agreed in advance: the stream must begin with :func:`schema_message`'s bytes, compared byte
      for byte before anything is decoded (no metadata, no dictionaries, no types the protocol does not name:
      a schema message is never parsed, so no offsets in it can be followed);
    - then each message's metadata is read before its body: only uncompressed record batches (no dictionaries,
      no compression, no key/value metadata, at most :data:`MAX_BATCH_METADATA` bytes), at most
      :data:`MAX_BATCHES` of them and ``max_rows`` rows in all, whose buffers span no more than the body they
      lie in (buffers that overlap would let one byte sent be read as many);
    - an uncompressed batch is read in place (its buffers are slices of ``payload``), so the table takes no more
      memory than the frame it came in."""
    import pyarrow as pa

    expected = schema_message(schema)
    if len(payload) < len(expected) or memoryview(payload)[:len(expected)] != expected:
        raise BadMessage("an Arrow table from the worker does not have the expected schema (compared byte for byte)")
    try:
        reader = pa.ipc.MessageReader.open_stream(pa.py_buffer(payload).slice(len(expected)))
        batches, rows = [], 0
        for message in reader:
            if message.type != "record batch":
                raise BadMessage(f"an Arrow {message.type} message in a table of plain columns")
            if len(batches) == MAX_BATCHES:
                raise BadMessage(f"an Arrow stream of more than {MAX_BATCHES} record batches")
            if message.metadata.size > MAX_BATCH_METADATA:
                raise BadMessage(f"a record batch message of {message.metadata.size:,} bytes of metadata")
            count, compressed, spanned = batch_header(message.metadata.to_pybytes())
            if compressed:
                raise BadMessage("a compressed Arrow record batch (refused unread: it could inflate to any size)")
            if spanned > message.body.size:
                raise BadMessage(f"record batch buffers spanning {spanned:,} bytes of a {message.body.size:,}-byte "
                                 "body")
            rows += count
            if count < 0 or (max_rows is not None and rows > max_rows):
                raise BadMessage(f"an Arrow stream of more than {max_rows:,} rows")
            batches.append(pa.ipc.read_record_batch(message, schema))
        table = pa.Table.from_batches(batches, schema)
        table.validate(full=True)
    except BadMessage:
        raise
    except Exception as exc:  # noqa: BLE001 - any malformed stream
        raise BadMessage(f"malformed Arrow stream from the worker: {type(exc).__name__}: {str(exc)[:200]}") from None
    return table


def parse_message(payload: bytes) -> dict[str, Any]:
    """A worker's JSON message, checked for its kind and that kind's fields: ``progress`` (``n``: an int >= 0),
    ``error`` (``error`` made text:
    stripped, capped, "(no reason given)" when it is none) or ``result`` (its fields are the task's to check);
    BadMessage for anything else."""
    msg = parse_json(payload)
    kind = msg["kind"]
    if kind == "progress":
        n = msg.get("n")
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise BadMessage("a progress count that is not a non-negative int")
    elif kind == "error":
        error = msg.get("error")
        msg["error"] = (error if isinstance(error, str) else "(no reason given)").strip()[:MAX_TEXT]
    elif kind != "result":
        raise BadMessage(f"unexpected message kind {kind[:30]!r}")
    return msg


def text_answer(msg: dict[str, Any]) -> dict[str, str | None]:
    """The fields of a JSON task's result message (all but ``kind``), each text (capped) or None; BadMessage if
    one is anything else."""
    fields = {k: v for k, v in msg.items() if k != "kind"}
    if any(v is not None and not isinstance(v, str) for v in fields.values()):
        raise BadMessage("an answer is not text")
    return {k: v if v is None else v[:MAX_TEXT] for k, v in fields.items()}
