"""What crosses the boundary between a policy worker and the parent: plain data only, checked on arrival.

A message is a frame: one kind byte (``J`` JSON, ``A`` an Arrow IPC stream) and a 4-byte big-endian length,
then that many bytes. The parent sends one ``J`` frame (the task, e.g. an :class:`EpisodeSpec` as a JSON
object of primitives); the worker answers ``J`` frames (``{"kind": "progress", "n": ...}``, then
``{"kind": "result", ...}`` or ``{"kind": "error", ...}``) and, after an episode's result, its steps (and nodes)
as Arrow streams. Nothing is ever unpickled, imported or executed by the receiver. :class:`FrameReader` caps
frame sizes; :func:`episode_from_worker` checks every field of an episode against what the parent asked for
and the Arrow schemas that ``pipeline/play/rollout.py`` produces, and raises :class:`BadMessage` otherwise (the
executor then records the episode as ``crashed`` with that reason).
"""

from __future__ import annotations

import json
import math
import os
import struct
from dataclasses import asdict, fields
from datetime import datetime
from typing import Any

HEADER = struct.Struct(">cI")
MAX_JSON = 4 * 2**20
MAX_ARROW = 512 * 2**20
MAX_TEXT = 20_000
"""Longest error text kept from a worker."""
END_REASONS = frozenset({"terminated", "truncated", "policy_error", "timeout"})


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
    """Frames from bytes arriving in pieces (a non-blocking socket), sizes capped."""

    def __init__(self) -> None:
        self.buffer = bytearray()

    def feed(self, data: bytes) -> list[tuple[bytes, bytes]]:
        self.buffer += data
        frames = []
        while len(self.buffer) >= HEADER.size:
            kind, size = HEADER.unpack_from(self.buffer)
            if kind not in (b"J", b"A"):
                raise BadMessage(f"unknown frame kind {kind!r}")
            if size > (MAX_JSON if kind == b"J" else MAX_ARROW):
                raise BadMessage(f"a {'JSON' if kind == b'J' else 'Arrow'} frame of {size} bytes is over the limit")
            if len(self.buffer) < HEADER.size + size:
                break
            frames.append((kind, bytes(self.buffer[HEADER.size:HEADER.size + size])))
            del self.buffer[:HEADER.size + size]
        return frames


def parse_json(payload: bytes) -> dict[str, Any]:
    try:
        obj = json.loads(payload, parse_constant=lambda c: (_ for _ in ()).throw(BadMessage(f"JSON constant {c}")))
    except (ValueError, RecursionError) as exc:
        raise BadMessage(f"malformed JSON from the worker: {str(exc)[:200]}") from None
    if not isinstance(obj, dict) or not isinstance(obj.get("kind"), str):
        raise BadMessage("a worker message must be a JSON object with a 'kind'")
    return obj


def parse_arrow(payload: bytes, schema: Any) -> Any:
    """The table of an Arrow IPC stream, fully validated and of exactly ``schema``."""
    import pyarrow as pa

    try:
        table = pa.ipc.open_stream(pa.py_buffer(payload)).read_all()
        table.validate(full=True)
    except Exception as exc:  # noqa: BLE001 - any malformed stream
        raise BadMessage(f"malformed Arrow stream from the worker: {type(exc).__name__}: {str(exc)[:200]}") from None
    if not table.schema.equals(schema, check_metadata=False):
        raise BadMessage("an Arrow table from the worker does not have the expected schema")
    return table


# ------------------------------------------------------------------------------------------------ episodes


def spec_to_json(spec: Any) -> dict[str, Any]:
    data = asdict(spec)
    for key, value in data.items():
        if not (value is None or isinstance(value, (str, int, float, bool))):
            raise TypeError(f"EpisodeSpec.{key} is not a primitive")
    return data


def spec_from_json(data: dict[str, Any]) -> Any:
    from pipeline.play.rollout import EpisodeSpec

    names = {f.name for f in fields(EpisodeSpec)}
    return EpisodeSpec(**{k: v for k, v in data.items() if k in names})


MEASURED = ("game", "started_at", "duration_s", "env_s", "policy_s", "length", "lives_lost", "end_reason", "error",
            "return")


def episode_to_json(episode: dict[str, Any]) -> dict[str, Any]:
    row = {k: episode[k] for k in MEASURED + ("episode_id",)}
    if isinstance(row["started_at"], datetime):
        row["started_at"] = row["started_at"].isoformat()
    if isinstance(row["error"], str):
        row["error"] = row["error"][:MAX_TEXT]
    return row


def _number(row: dict, key: str, nullable: bool = False) -> float | None:
    value = row.get(key)
    if value is None and nullable:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BadMessage(f"episode field {key} is not a finite number: {str(value)[:50]}")
    return float(value)


def _int(row: dict, key: str, low: int, high: int) -> int:
    value = row.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise BadMessage(f"episode field {key} is not an int in {low}..{high}: {str(value)[:50]}")
    return value


def check_lines_run(spec: Any, nodes: Any) -> None:
    """BadMessage unless every ``lines_run`` of ``nodes`` is NULL (lines not recorded) or strictly increasing
    line numbers inside the source of the node's method in ``spec.policy_text`` (what an honest worker sends)."""
    import numpy as np
    import pyarrow.compute as pc

    lines = nodes.column("lines_run").combine_chunks()
    if lines.null_count == len(lines):
        return
    if not spec.trace_lines:
        raise BadMessage("lines_run for an episode played without line recording")
    from tracing.policy_file import PolicyLoadError, inspect_policy

    try:
        methods = {m.name: m.source.count("\n") for m in inspect_policy(spec.policy_text, spec.policy_name).methods}
    except PolicyLoadError:
        raise BadMessage("lines_run for a policy that does not load") from None
    functions = nodes.column("function").combine_chunks()
    for name in pc.unique(pc.filter(functions, pc.is_valid(lines))).to_pylist():
        if name not in methods:
            raise BadMessage(f"lines_run for {str(name)[:60]!r}, which is not a bundled method of the policy")
        chosen = pc.filter(lines, pc.equal(functions, name))
        values = np.asarray(pc.list_flatten(chosen), dtype=np.int64)
        if values.size and (values.min() < 1 or values.max() > methods[name]):
            raise BadMessage(f"lines_run of {name} outside its {methods[name]} lines")
        starts = np.asarray(pc.list_value_length(chosen).fill_null(0), dtype=np.int64).cumsum()[:-1]
        rising = np.diff(values) > 0
        rising[starts[(starts > 0) & (starts < values.size)] - 1] = True  # a new call may start lower
        if not rising.all():
            raise BadMessage(f"lines_run of {name} not strictly increasing")


def episode_from_worker(spec: Any, row: Any, steps: Any, nodes: Any) -> Any:
    """The :class:`EpisodeOutcome` of ``spec`` from what its worker sent, every value checked; BadMessage if
    anything is off. Fields the parent knows (ids, seed, settings) come from ``spec``, never from the worker."""
    from games import get_game
    from pipeline.play.rollout import EpisodeOutcome, _episode_row

    if not isinstance(row, dict):
        raise BadMessage("the episode row is not an object")
    if row.get("episode_id") != spec.episode_id:
        raise BadMessage(f"the worker answered for episode {str(row.get('episode_id'))[:60]!r}, "
                         f"not {spec.episode_id!r}")
    game = get_game(spec.game).name
    if row.get("game") != game:
        raise BadMessage(f"the episode's game is {str(row.get('game'))[:30]!r}, not {game!r}")
    end_reason = row.get("end_reason")
    if end_reason not in END_REASONS:
        raise BadMessage(f"unknown end reason {str(end_reason)[:30]!r}")
    error = row.get("error")
    if error is not None and not isinstance(error, str):
        raise BadMessage("the episode's error is not text")
    try:
        started_at = datetime.fromisoformat(row["started_at"]) if row.get("started_at") is not None else None
    except (TypeError, ValueError):
        raise BadMessage("started_at is not an ISO timestamp") from None
    length = _int(row, "length", 0, spec.max_steps)
    measured = dict(
        game=game, started_at=started_at, duration_s=_number(row, "duration_s"),
        env_s=_number(row, "env_s", nullable=True), policy_s=_number(row, "policy_s", nullable=True),
        length=length, lives_lost=_int(row, "lives_lost", 0, 2**31 - 1), end_reason=end_reason,
        error=error[:MAX_TEXT] if error else error,
    )
    failed_step = end_reason in ("policy_error", "timeout")  # the step the policy failed on is stored too
    if steps.num_rows not in ((length, length + 1) if failed_step else (length,)) or steps.num_rows > spec.max_steps:
        raise BadMessage(f"{steps.num_rows} step rows for an episode of length {length}")
    if steps.num_rows and steps.column("step").to_pylist() != list(range(steps.num_rows)):
        raise BadMessage("the step rows are not numbered 0, 1, 2, ...")
    if nodes is not None and not spec.trace:
        raise BadMessage("nodes for an untraced episode")
    if nodes is not None:
        check_lines_run(spec, nodes)
    episode = _episode_row(spec, score=_number(row, "return"), **measured)
    return EpisodeOutcome(episode, steps, nodes)
