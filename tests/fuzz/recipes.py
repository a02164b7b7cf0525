"""What the fuzzers send: a recipe (a small JSON-able dict that Hypothesis draws, and that the saved corpus keeps)
and the bytes it makes.

A recipe names a shape and its sizes; :func:`build` turns it into the bytes a compromised policy process could
send: an Arrow stream of node rows (honest-shaped tables with hostile values, schemas with metadata or fields
whose flatbuffer offsets all point at one entry, wide schemas, every Arrow type in place of a column,
dictionaries, compression, many batches, flipped bytes) or a failure frame's JSON. Big inputs are built with
numpy and repetition, so that an example costs milliseconds to make whatever it costs the decoder.

The recipes are built by this checkout and decoded by the tree under test (``CODEARCADE_FUZZ_TREE``, an older
commit's worktree: tests/fuzz/server.py), so the same inputs can be sent to the code before a fix.
"""

from __future__ import annotations

import json
import struct
import textwrap

import numpy as np
import pyarrow as pa
from hypothesis import strategies as st

from pipeline.boundary.wire import _flat_field
from tests.conftest import random_policy
from tracing.capture import NODE_SCHEMA

LONG_METHOD_LINES = 3_000
"""Lines of the fuzz policy's long bundled method: ``lines_run`` may hold that many lines a call."""
POLICY = random_policy("pong", "self.helper(obs)") + textwrap.indent(textwrap.dedent("""
    @trace.bundle()
    def helper(self, obs):
        return 0

    @trace.bundle(trainable=True)
    def long(self, obs):
    """), "    ") + "".join(f"        x{i} = {i}\n" for i in range(LONG_METHOD_LINES)) + "        return 0\n"
"""The policy every fuzzed episode claims to play: three bundled methods, one of them long."""
FUNCTIONS = {"act": (True, 2), "helper": (False, 2), "long": (True, LONG_METHOD_LINES + 2)}
"""Its bundled methods as the file says: name -> (trainable, lines) (as ``nodes.bundled_methods`` finds them)."""

# ----------------------------------------------------------------------------------------------- values

VALUE_KINDS = ("plain", "ascii", "astral", "one_emoji", "objects", "huge_number", "deep", "not_json", "escapes",
               "random_astral", "random_ascii")
RANDOM_KINDS = ("random_astral", "random_ascii")
RANDOM_BYTES = 32 * 2**20
"""Values that differ from row to row (random characters: the store cannot compress them away)."""


def random_strings(n: int, size: int, astral: bool, seed: int = 0) -> pa.Array:
    """``n`` JSON strings of ``size`` random characters each (emoji, 4 UTF-8 bytes each; or ASCII letters), built
    as one buffer."""
    size = max(1, min(size, RANDOM_BYTES // (4 * max(1, n))))  # at most RANDOM_BYTES: made quickly
    rng = np.random.default_rng(seed)
    if astral:
        cp = rng.integers(0x1F300, 0x1FAFF, size=(n, size), dtype=np.uint32)
        chars = np.stack([0xF0 | (cp >> 18), 0x80 | ((cp >> 12) & 0x3F), 0x80 | ((cp >> 6) & 0x3F),
                          0x80 | (cp & 0x3F)], axis=-1).astype(np.uint8).reshape(n, size * 4)
    else:
        chars = rng.integers(ord("a"), ord("z") + 1, size=(n, size), dtype=np.uint8)
    quote = np.full((n, 1), ord('"'), dtype=np.uint8)
    data = np.concatenate([quote, chars, quote], axis=1)
    width = data.shape[1]
    offsets = np.arange(0, (n + 1) * width, width, dtype=np.int32)
    return pa.StringArray.from_buffers(n, pa.py_buffer(offsets.tobytes()), pa.py_buffer(data.tobytes()))


def value_text(kind: str, size: int) -> str:
    """A node value of ``kind`` about ``size`` characters long."""
    if kind == "plain":
        return "0"
    if kind == "ascii":
        return json.dumps("a" * size)
    if kind == "astral":
        return json.dumps("\U0001F600" * size, ensure_ascii=False)
    if kind == "one_emoji":
        return json.dumps("\U0001F600" + "b" * size, ensure_ascii=False)
    if kind == "objects":
        return "[" + ",".join(["{}"] * max(1, size // 3)) + "]"
    if kind == "huge_number":
        return "1" + "0" * max(1, size)
    if kind == "deep":
        depth = min(size, 50)
        return "[" * depth + "]" * depth
    if kind == "not_json":
        return "{" * max(1, size)
    if kind == "escapes":
        return json.dumps("\x01" * size)
    raise ValueError(kind)


# ----------------------------------------------------------------------------------------------- tables


def node_table(steps: int, rows_per_step: int, value_kind: str, value_size: int, lines: int,
               lines_valid: bool = True, function: str = "long") -> pa.Table:
    """An honest-shaped node table: ``rows_per_step`` calls of ``function`` at each of ``steps`` steps (call
    indexes 0..n-1, no parents, a plain output), the output of every row a ``value_kind`` value, ``lines`` lines
    run per call (strictly increasing within the method when ``lines_valid``)."""
    n = steps * rows_per_step
    step = np.repeat(np.arange(steps, dtype=np.int32), rows_per_step)
    call = np.tile(np.arange(rows_per_step, dtype=np.int16), steps)
    value = None if value_kind in RANDOM_KINDS else value_text(value_kind, value_size)
    trainable, method_lines = FUNCTIONS.get(function, (True, 2))  # "nope": not a bundled method
    if lines:
        per_call = np.arange(1, lines + 1, dtype=np.int16) if lines_valid else \
            np.full(lines, method_lines + 5, dtype=np.int16)
        if lines_valid and lines > method_lines:
            per_call = (np.arange(lines, dtype=np.int64) % method_lines + 1).astype(np.int16)
        flat = np.tile(per_call, n)
        offsets = np.arange(0, (n + 1) * lines, lines, dtype=np.int32)
        lines_run = pa.ListArray.from_arrays(pa.array(offsets), pa.array(flat, pa.int16()))
    else:
        lines_run = pa.nulls(n, pa.list_(pa.int16()))
    columns = {
        "step": pa.array(step), "call_index": pa.array(call),
        "function": pa.array([function] * n, pa.string()),
        "trainable": pa.array([trainable] * n, pa.bool_()),
        "inputs": pa.array(['{"$ref":"obs"}'] * n, pa.string()),
        "output": random_strings(n, value_size, value_kind == "random_astral") if value_kind in RANDOM_KINDS
        else pa.array([value] * n, pa.string()),
        "exc_type": pa.nulls(n, pa.string()), "exc_message": pa.nulls(n, pa.string()),
        "exc_line": pa.nulls(n, pa.int32()), "exc_source": pa.nulls(n, pa.string()),
        "duration_us": pa.array(np.full(n, 5, dtype=np.int64)),
        "parents": pa.array([[]] * n, pa.list_(pa.int16())),
        "lines_run": lines_run,
    }
    return pa.table([columns[f.name] for f in NODE_SCHEMA], schema=NODE_SCHEMA)


def stream(table: pa.Table, schema: pa.Schema | None = None, batches: int = 1, compression: str | None = None,
           ) -> bytes:
    """``table`` as an Arrow IPC stream (under ``schema``'s metadata when given), in ``batches`` record batches."""
    sink = pa.BufferOutputStream()
    options = pa.ipc.IpcWriteOptions(compression=compression)
    with pa.ipc.new_stream(sink, schema or table.schema, options=options) as writer:
        n = table.num_rows
        if batches <= 1 or n == 0:
            writer.write_table(table)
        else:
            size = max(1, -(-n // batches))
            for at in range(0, n, size):
                writer.write_table(table.slice(at, size))
            for _ in range(batches - -(-n // size)):
                writer.write_table(table.slice(0, 0))
    return sink.getvalue().to_pybytes()


SMALL = None


def small_table() -> pa.Table:
    """One honest row at step 0."""
    global SMALL
    if SMALL is None:
        SMALL = node_table(1, 1, "plain", 0, 0, function="act")
    return SMALL


# ------------------------------------------------------------------------------ flatbuffer offsets, shared


def _share_vector(message: bytes, path: tuple[int, ...]) -> bytes:  # walks offsets as the receiver would
    """An encapsulated schema message whose vector at ``path`` (field indexes from the Message's root table; the
    last names a vector of tables) has every slot pointing at its first element: one entry, read many times."""
    meta_len = struct.unpack_from("<i", message, 4)[0]
    meta = bytearray(message[8:8 + meta_len])
    table = struct.unpack_from("<I", meta, 0)[0]
    for index in path[:-1]:
        at = _flat_field(bytes(meta), table, index)
        table = at + struct.unpack_from("<I", meta, at)[0]
    at = _flat_field(bytes(meta), table, path[-1])
    vector = at + struct.unpack_from("<I", meta, at)[0]
    count = struct.unpack_from("<I", meta, vector)[0]
    first = vector + 4 + struct.unpack_from("<I", meta, vector + 4)[0]
    for i in range(1, count):
        slot = vector + 4 + 4 * i
        struct.pack_into("<I", meta, slot, first - slot)
    return message[:8] + bytes(meta) + message[8 + meta_len:]


def _schema_message(schema: pa.Schema) -> bytes:
    return schema.serialize().to_pybytes()


def _batches_of(table: pa.Table) -> bytes:
    """The record batch messages (and end of stream) of ``table``'s stream, without its schema message."""
    whole = stream(table)
    return whole[len(_schema_message(table.schema)):]


def shared_metadata(entries: int, value_bytes: int, shared: bool) -> bytes:
    """A node stream whose schema carries ``entries`` key/value pairs, the first ``value_bytes`` long; ``shared``:
    every slot of the vector points at that first one."""
    metadata = {b"k0": b"v" * value_bytes}
    metadata.update({f"k{i}".encode(): b"" for i in range(1, entries)})
    message = _schema_message(NODE_SCHEMA.with_metadata(metadata))
    if shared and entries > 1:
        message = _share_vector(message, (2, 2))  # Message.header -> Schema.custom_metadata
    return message + _batches_of(small_table())


def shared_fields(count: int, name_bytes: int, shared: bool) -> bytes:
    """A stream whose schema has ``count`` fields, the first named with ``name_bytes`` bytes; ``shared``: every
    slot of the fields vector points at the first field."""
    fields = [pa.field("f" * max(1, name_bytes), pa.int8())] + [pa.field(f"f{i}", pa.int8()) for i in range(1, count)]
    message = _schema_message(pa.schema(fields))
    if shared and count > 1:
        message = _share_vector(message, (2, 1))  # Message.header -> Schema.fields
    return message + _batches_of(small_table())


# ---------------------------------------------------------------------------------------------- types

ARROW_TYPES = {
    "null": pa.null(), "bool": pa.bool_(), "int8": pa.int8(), "uint64": pa.uint64(), "int64": pa.int64(),
    "float16": pa.float16(), "float64": pa.float64(), "decimal128": pa.decimal128(38, 4),
    "decimal256": pa.decimal256(76, 10), "date32": pa.date32(), "timestamp": pa.timestamp("ns", "UTC"),
    "duration": pa.duration("s"), "interval": pa.month_day_nano_interval(), "binary": pa.binary(),
    "large_string": pa.large_string(), "large_binary": pa.large_binary(), "string_view": pa.string_view(),
    "binary_view": pa.binary_view(), "fixed_binary": pa.binary(1024), "list_string": pa.list_(pa.string()),
    "large_list": pa.large_list(pa.int16()), "list_view": pa.list_view(pa.int16()),
    "fixed_list": pa.list_(pa.int16(), 4096), "struct": pa.struct([("a", pa.string()), ("b", pa.int64())]),
    "map": pa.map_(pa.string(), pa.string()), "dense_union": pa.dense_union([pa.field("a", pa.string())]),
    "sparse_union": pa.sparse_union([pa.field("a", pa.int64())]),
    "dictionary": pa.dictionary(pa.int32(), pa.string()), "run_end": pa.run_end_encoded(pa.int32(), pa.string()),
}


def other_type(column: str, type_name: str, rows: int, width: int) -> bytes:
    """A stream of ``rows`` rows whose ``column`` is of ``type_name``, filled with values about ``width`` wide
    (or nulls where a value cannot be made)."""
    kind = ARROW_TYPES[type_name]
    base = node_table(1, max(1, min(rows, 255)), "plain", 0, 0, function="act")
    n = base.num_rows
    try:
        if type_name in ("large_string", "string_view", "run_end", "dictionary", "list_string"):
            text = pa.array(["s" * width] * n, pa.string())
            value = pa.array([["s" * width]] * n) if type_name == "list_string" else text.cast(kind)
        elif type_name in ("binary", "large_binary", "binary_view"):
            value = pa.array([b"b" * width] * n, kind)
        elif type_name == "fixed_binary":
            value = pa.array([b"b" * 1024] * n, kind)
        else:
            value = pa.nulls(n, kind)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
        value = pa.nulls(n, kind)
    index = NODE_SCHEMA.get_field_index(column)
    table = base.set_column(index, pa.field(column, kind), value)
    return stream(table)


def wide_schema(count: int, type_names: list[str]) -> bytes:
    """A stream whose schema has ``count`` fields cycling through ``type_names`` (no rows)."""
    fields = [pa.field(f"c{i}", ARROW_TYPES[type_names[i % len(type_names)]]) for i in range(count)]
    schema = pa.schema(fields)
    return _schema_message(schema) + b"\xff\xff\xff\xff\x00\x00\x00\x00"


# ----------------------------------------------------------------------------------------------- build


def build(recipe: dict) -> bytes:
    """The bytes of ``recipe`` (see the strategies below)."""
    kind = recipe["kind"]
    if kind == "table":
        table = node_table(recipe["steps"], recipe["rows_per_step"], recipe["value_kind"], recipe["value_size"],
                           recipe["lines"], recipe.get("lines_valid", True), recipe.get("function", "long"))
        return stream(table, batches=recipe.get("batches", 1))
    if kind == "metadata":
        return shared_metadata(recipe["entries"], recipe["value_bytes"], recipe["shared"])
    if kind == "fields":
        return shared_fields(recipe["count"], recipe["name_bytes"], recipe["shared"])
    if kind == "type":
        return other_type(recipe["column"], recipe["type"], recipe["rows"], recipe["width"])
    if kind == "wide":
        return wide_schema(recipe["count"], recipe["types"])
    if kind == "compressed":
        table = node_table(1, 4, "ascii", recipe["value_size"], 0, function="act")
        return stream(table, compression="zstd")
    if kind == "flip":
        data = bytearray(stream(node_table(2, 3, "ascii", 40, 3, function="act")))
        for at, value in recipe["flips"]:
            data[int(at * (len(data) - 1))] = value
        return bytes(data)
    if kind == "failure":
        return failure_frame(recipe["shape"], recipe["size"])
    raise ValueError(kind)


def failure_frame(shape: str, size: int) -> bytes:
    """A policy process's failure message (JSON, at most the host's 32 KB answer) of ``shape``."""
    if shape == "honest":
        text = {"kind": "failed", "end_reason": "policy_error", "error": "x" * size}
    elif shape == "astral":
        text = {"kind": "failed", "end_reason": "policy_error", "error": "\U0001F600" * size}
    elif shape == "escaped_astral":
        return json.dumps({"kind": "failed", "end_reason": "timeout", "error": "\U0001F600" * size}).encode()[:32768]
    elif shape == "deep":
        return (b"[" * size + b"]" * size)[:32768]
    elif shape == "huge_number":
        return b'{"kind":"failed","end_reason":"policy_error","error":' + b"9" * min(size, 32000) + b"}"
    elif shape == "wrong_type":
        text = {"kind": "failed", "end_reason": "policy_error", "error": [["x"] * 10] * (size // 60 + 1)}
    else:  # bytes that are not JSON
        return bytes(range(256)) * (size // 256 + 1)
    return json.dumps(text, ensure_ascii=False).encode()[:32768]


# ------------------------------------------------------------------------------------------- strategies

MB = 2**20


def table_recipes() -> st.SearchStrategy[dict]:
    return st.fixed_dictionaries({
        "kind": st.just("table"),
        # sizes drawn mostly large: the oracle looks for a cost out of proportion, which small inputs hide
        "steps": st.sampled_from([1, 5, 16, 16]),
        "rows_per_step": st.sampled_from([1, 100, 256, 256]),
        "value_kind": st.sampled_from(VALUE_KINDS),
        "value_size": st.sampled_from([10, 1_000, 5_000, 16_000, 20_000]),
        "lines": st.sampled_from([0, 1, 600, LONG_METHOD_LINES, LONG_METHOD_LINES, LONG_METHOD_LINES]),
        "lines_valid": st.sampled_from([True, True, True, False]),
        "function": st.sampled_from(["long", "long", "long", "act", "nope"]),
        "batches": st.sampled_from([1, 1, 1, 2, 64, 65]),
    })


def arrow_recipes() -> st.SearchStrategy[dict]:
    """Every shape of node stream (structurally valid and invalid)."""
    return st.one_of(
        table_recipes(), table_recipes(), table_recipes(),  # a third of the draws: the shapes that pass the checks
        st.fixed_dictionaries({"kind": st.just("metadata"), "entries": st.integers(1, 3_000),
                               "value_bytes": st.sampled_from([0, 1_000, 100_000, 1 * MB]),
                               "shared": st.booleans()}),
        st.fixed_dictionaries({"kind": st.just("fields"), "count": st.integers(1, 20_000),
                               "name_bytes": st.sampled_from([1, 1_000, 100_000]), "shared": st.booleans()}),
        st.fixed_dictionaries({"kind": st.just("type"), "column": st.sampled_from(NODE_SCHEMA.names),
                               "type": st.sampled_from(sorted(ARROW_TYPES)), "rows": st.integers(1, 255),
                               "width": st.sampled_from([1, 100, 10_000])}),
        st.fixed_dictionaries({"kind": st.just("wide"), "count": st.integers(1, 50_000),
                               "types": st.lists(st.sampled_from(sorted(ARROW_TYPES)), min_size=1, max_size=4)}),
        st.fixed_dictionaries({"kind": st.just("compressed"), "value_size": st.sampled_from([10, 1 * MB, 8 * MB])}),
        st.fixed_dictionaries({"kind": st.just("flip"), "flips": st.lists(
            st.tuples(st.floats(0, 1), st.integers(0, 255)), min_size=1, max_size=8)}),
    )


def failure_recipes() -> st.SearchStrategy[dict]:
    return st.fixed_dictionaries({
        "kind": st.just("failure"),
        "shape": st.sampled_from(["honest", "astral", "escaped_astral", "deep", "huge_number", "wrong_type",
                                  "bytes"]),
        "size": st.integers(0, 40_000),
    })
