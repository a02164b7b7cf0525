"""The node rows a policy process sends: read within bounds, then every field checked against its episode.

A traced episode's policy process sends its node rows (``tracing/capture.py``'s ``NODE_SCHEMA``) as one Arrow
stream at the end. The process runs policy code, which can reach every object of its own process (the recorder,
the channel, ``pipeline.boundary.wire``) and send anything in that frame: a zstd-compressed stream that inflates
a hundredfold, ten thousand rows for a five-step episode, steps and call indexes that never were, text that is
not JSON. So nothing in it is believed (DESIGN.md, "Bounded before parsed"):

- **bounded before parsed** (:func:`read_nodes`): the frame is at most :data:`MAX_NODE_FRAME` bytes (the host
  refuses a larger one at its header, ``pipeline/play/rollout.py``); the stream is read batch by batch, each
  batch's header first (``pipeline/boundary/wire.py``'s ``parse_arrow``): compressed batches and dictionaries are
  refused unread, rows capped (:func:`row_limits`), so the table is the frame's own bytes and no more;
- **every field checked** (:func:`check_nodes`), with Arrow/numpy kernels over whole columns (a traced episode has
  thousands of rows: no Python call per value in the usual case): each step is one the policy was asked about,
  the call indexes of a step are 0..n-1 once each, parents are earlier calls of the same step, functions are the
  policy's bundled methods (and ``trainable`` as the file says), durations fit in the episode, ``lines_run`` lie
  in the method's lines, texts are within their sizes, ``inputs`` and ``output`` are JSON that both Python and
  the store's JSON type accept, and a row has either an output or an exception.

Whatever breaks a rule raises :class:`MalformedTrace`, which the receiver (the parent, ``pipeline/play/
episodes.py``; the game host when it records the episode for Rerun) turns into the episode's recorded policy
error (``policy_error``, ``malformed trace at step 3: ...``), its node rows dropped: never an exception in a
trusted process, never a failed run, never a row in the store.
"""

from __future__ import annotations

import json
import re
from functools import lru_cache
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.boundary.wire import BadMessage, parse_arrow
from tracing.bounded import MAX_CHARS, MAX_DEPTH, deeper_than
from tracing.capture import MAX_CALLS_PER_STEP, TOO_MANY_CALLS

MAX_NODE_FRAME = 64 * 2**20
"""Bytes of one episode's node frame. An honest 4,000-step traced episode sends a few MB (a node's values are
mostly ``{"$ref": "obs"}`` and scalars); the frame is read whole, held twice while it is joined, so this also
bounds what a forged one costs the host and the parent."""
NODE_BYTES_BASE = 2**20
NODE_BYTES_PER_STEP = 32 * 1024
"""An episode's byte budget for its node rows: this base and this much a step the policy was asked about, at most
:data:`MAX_NODE_FRAME` (:func:`node_budget`). An honest traced step sends well under 1 KB (values are mostly
``{"$ref": "obs"}`` and scalars); a 4,000-step episode's budget is the whole frame."""
CALLS_PER_METHOD = 64
"""Calls of each bundled method one step may make (helpers called once per object of a frame stay under it)."""
MIN_CALLS_PER_STEP = 256
"""A step's node rows may be :data:`CALLS_PER_METHOD` x the policy's bundled methods, and never fewer than this
(nor more than ``call_index`` holds: ``tracing.capture.MAX_CALLS_PER_STEP``, reached at 512 methods)."""
MAX_NODE_ROWS = 2_000_000
"""Node rows of one episode, whatever its length."""
MAX_VALUE_BYTES = MAX_CHARS + 1024
"""UTF-8 bytes of one ``inputs`` or ``output`` text: ``to_json`` cuts a value at 20,000 characters of ASCII JSON
(non-ASCII text is escaped), so an honest value is that many bytes (and a parameter name's few more); counted in
bytes, a value of astral characters costs what it says (4 bytes a character: counted in characters, it was 4 x)."""
MAX_TEXT_BYTES = 16 * 1024
"""Bytes of ``exc_type``, ``exc_message``, ``exc_source`` (the recorder keeps 2,000 characters of a message)."""
DURATION_SLACK_US = 1_000_000
"""A node may last the episode's wall time and this much more (the two processes' clocks start apart)."""

_NUMBER = r"-?(?:0|[1-9][0-9]{0,99})(?:\.[0-9]+)?(?:[eE][+-]?[0-9]+)?"
"""A JSON number of at most 100 digits before its point: Python reads an integer only up to its limit of digits
(4,300), so a longer one is parsed like any other text (this shape once let a 5,000-digit integer through, a value
the store held and Python's ``json.loads`` refused)."""
_STRING = r'"(?:[^"\\\x00-\x1f]|\\["\\/bfnrt]|\\u(?:[0-9a-ce-fA-CE-F][0-9a-fA-F]{3}|[dD][0-7][0-9a-fA-F]{2}))*"'
_SCALAR = f"(?:{_NUMBER}|true|false|null|{_STRING})"
_FLAT = rf'(?:{_SCALAR}|\{{"\$ref":"obs"\}}|\[(?:{_SCALAR}(?:,{_SCALAR})*)?\])'
SIMPLE_JSON = rf"^(?:{_FLAT}|\{{(?:{_STRING}:{_FLAT}(?:,{_STRING}:{_FLAT})*)?\}})$"
"""JSON texts known valid by their shape alone (scalars, flat lists, objects of those; surrogate escapes left
out): the values of an honest episode are nearly all such, and a regular expression over the whole column
checks them at once. The rest are parsed one distinct value at a time (:func:`_invalid_json`)."""
_SURROGATE = re.compile(r"\\u[dD][89a-fA-F]")


class MalformedTrace(Exception):
    """Node rows that break a rule; ``str()`` is the episode's error (``malformed trace at step 3: ...``)."""

    def __init__(self, reason: str, step: int | None = None) -> None:
        where = "" if step is None else f" at step {step}"
        super().__init__(f"malformed trace{where}: {reason}")
        self.step = step


@lru_cache(maxsize=32)
def bundled_methods(policy_text: str, policy_name: str) -> dict[str, tuple[bool, int]]:
    """The policy's bundled methods as the file says (found without running it): name -> (trainable, lines)."""
    from tracing.policy_file import PolicyLoadError, inspect_policy

    try:
        methods = inspect_policy(policy_text, policy_name).methods
    except PolicyLoadError:
        return {}
    return {m.name: (m.trainable, m.source.count("\n")) for m in methods}


def node_budget(steps: int) -> int:
    """Bytes of node rows an episode of ``steps`` policy calls may send: on the wire, and so (each stage a
    constant multiple of it) in memory and in the store."""
    return min(MAX_NODE_FRAME, NODE_BYTES_BASE + NODE_BYTES_PER_STEP * max(0, steps))


def row_limits(methods: int, steps: int) -> tuple[int, int]:
    """(rows per step, rows per episode) allowed to a policy of ``methods`` bundled methods asked ``steps`` times."""
    per_step = min(MAX_CALLS_PER_STEP, max(MIN_CALLS_PER_STEP, CALLS_PER_METHOD * methods))
    return per_step, min(MAX_NODE_ROWS, per_step * steps)


def read_nodes(payload: bytes, spec: Any, steps: int, duration_s: float) -> pa.Table:
    """The checked node table of ``spec``'s episode from the Arrow stream its policy process sent, the policy asked
    for an action ``steps`` times in ``duration_s``; :class:`MalformedTrace` if anything is off."""
    from tracing.capture import NODE_SCHEMA

    if not spec.trace:  # refused unread
        raise MalformedTrace("node rows for an episode that is not traced")
    budget = node_budget(steps)
    if len(payload) > budget:
        raise MalformedTrace(f"a node frame of {len(payload):,} bytes, over the episode's budget of {budget:,} "
                             f"({NODE_BYTES_BASE:,} + {NODE_BYTES_PER_STEP:,} a step)")
    methods = bundled_methods(spec.policy_text, spec.policy_name)
    per_step, per_episode = row_limits(len(methods), steps)
    try:
        nodes = parse_arrow(payload, NODE_SCHEMA, max_rows=per_episode)
    except BadMessage as exc:
        more = (f" (a traced episode records at most {per_step:,} calls of bundled methods a step: {TOO_MANY_CALLS})"
                if "rows" in str(exc) else "")
        raise MalformedTrace(f"{exc}{more}") from None
    check_nodes(nodes, spec, steps, duration_s, methods)
    return nodes


def _first(mask: np.ndarray, step: np.ndarray | None) -> int | None:
    """The step of the first row where ``mask`` holds (None when no steps are known)."""
    row = int(np.flatnonzero(mask)[0])
    return None if step is None else int(step[row])


def _ints(nodes: pa.Table, name: str) -> np.ndarray:
    column = nodes.column(name)
    if column.null_count:
        raise MalformedTrace(f"{name} missing in a node row")
    return column.to_numpy()


def check_nodes(nodes: pa.Table, spec: Any, steps: int, duration_s: float,
                methods: dict[str, tuple[bool, int]] | None = None) -> None:
    """:class:`MalformedTrace` unless every field of every row of ``nodes`` is one an honest recorder sends for
    ``spec``'s episode (see the module docstring)."""
    if not spec.trace:
        raise MalformedTrace("node rows for an episode that is not traced")
    if methods is None:
        methods = bundled_methods(spec.policy_text, spec.policy_name)
    n = nodes.num_rows
    per_step, per_episode = row_limits(len(methods), steps)
    if n > per_episode:
        raise MalformedTrace(f"{n:,} node rows for {steps} steps (at most {per_episode:,})")
    if n == 0:
        return
    step = _ints(nodes, "step").astype(np.int64)
    if step.min() < 0 or step.max() >= steps:
        bad = (step < 0) | (step >= steps)
        raise MalformedTrace(f"a node row for step {int(step[np.flatnonzero(bad)[0]])} of an episode of {steps} "
                             "policy calls")
    counts = np.bincount(step, minlength=steps)
    if counts.max() > per_step:
        raise MalformedTrace(f"{int(counts.max()):,} calls of bundled methods in one step (at most {per_step:,}: "
                             f"{TOO_MANY_CALLS})", int(counts.argmax()))
    index = _ints(nodes, "call_index").astype(np.int64)
    order = np.lexsort((index, step))
    sorted_step = step[order]
    starts = np.flatnonzero(np.r_[True, sorted_step[1:] != sorted_step[:-1]])
    rank = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    wrong = index[order] != rank  # a step's call indexes, sorted, are 0, 1, 2, ... once each
    if wrong.any():
        raise MalformedTrace("call indexes that are not 0..n-1 once each", _first(wrong, sorted_step))
    _check_functions(nodes, methods, step)
    duration = _ints(nodes, "duration_us")
    longest = int(duration_s * 1e6) + DURATION_SLACK_US
    outside = (duration < 0) | (duration > longest)
    if outside.any():
        raise MalformedTrace(f"a call lasting {int(duration[outside][0])} us in an episode of {duration_s:.1f} s",
                             _first(outside, step))
    _check_parents(nodes, index, step)
    _check_texts(nodes, spec, step)
    _check_lines(nodes, spec, methods, step)


def _check_functions(nodes: pa.Table, methods: dict[str, tuple[bool, int]], step: np.ndarray) -> None:
    names = list(methods)
    at = pc.index_in(nodes.column("function"), value_set=pa.array(names, pa.string()))
    if at.null_count:
        row = int(pc.index(pc.is_null(at), True).as_py())
        raise MalformedTrace(f"a call of {str(nodes.column('function')[row].as_py())[:60]!r}, which is not a "
                             "bundled method of the policy", int(step[row]))
    expected = np.array([methods[name][0] for name in names], dtype=bool)[at.to_numpy()]
    differs = expected != _ints(nodes, "trainable").astype(bool)
    if differs.any():
        raise MalformedTrace("a call whose trainable flag is not its method's", _first(differs, step))


def _check_parents(nodes: pa.Table, index: np.ndarray, step: np.ndarray) -> None:
    """Parents are earlier calls of the same step, listed once each in rising order (as the recorder writes them)."""
    parents = nodes.column("parents").combine_chunks()
    if parents.null_count:
        raise MalformedTrace("parents missing", _first(parents.is_null().to_numpy(zero_copy_only=False), step))
    # a call has at most as many parents as calls before it (they are distinct and earlier): checked per row
    # before a value is read, so what follows costs a constant multiple of honest rows, not of the bytes sent
    many = np.asarray(pc.list_value_length(parents), dtype=np.int64) > index
    if many.any():
        raise MalformedTrace("a parent that is not an earlier call of the same step", _first(many, step))
    values = pc.list_flatten(parents)
    if not len(values):
        return
    if values.null_count:
        raise MalformedTrace("a parent that is missing")
    owner = pc.list_parent_indices(parents).to_numpy()
    value = values.to_numpy()  # int16, as sent: compared at its own width
    bad = (value < 0) | (value >= index[owner])
    rising = np.r_[True, owner[1:] != owner[:-1]] | np.r_[True, value[1:] > value[:-1]]
    bad |= ~rising
    if bad.any():
        raise MalformedTrace("a parent that is not an earlier call of the same step", int(step[owner[bad][0]]))


def _check_texts(nodes: pa.Table, spec: Any, step: np.ndarray) -> None:
    """Text sizes, exception lines, JSON of ``inputs`` and ``output``, and an output or an exception per row."""
    for name, limit in (("exc_type", 200), ("exc_message", MAX_TEXT_BYTES), ("exc_source", MAX_TEXT_BYTES),
                        ("inputs", MAX_VALUE_BYTES), ("output", MAX_VALUE_BYTES)):
        long = pc.fill_null(pc.greater(pc.binary_length(nodes.column(name)), limit), False)
        if pc.any(long).as_py():
            raise MalformedTrace(f"a node's {name} of more than {limit:,} bytes",
                                 _first(long.to_numpy(zero_copy_only=False), step))
    if nodes.column("inputs").null_count:
        raise MalformedTrace("a node without its inputs",
                             _first(nodes.column("inputs").is_null().to_numpy(zero_copy_only=False), step))
    raised = nodes.column("exc_type").is_valid().to_numpy(zero_copy_only=False)
    returned = nodes.column("output").is_valid().to_numpy(zero_copy_only=False)
    if (raised == returned).any():
        raise MalformedTrace("a node with both an output and an exception, or neither", _first(raised == returned,
                                                                                               step))
    line = nodes.column("exc_line")
    if line.null_count < len(line):
        lines = spec.policy_text.count("\n") + 1
        outside = pc.fill_null(pc.or_(pc.less(line, 1), pc.greater(line, lines)), False)
        if pc.any(outside).as_py():
            raise MalformedTrace(f"an exception line outside the policy's {lines} lines",
                                 _first(outside.to_numpy(zero_copy_only=False), step))
    for name in ("inputs", "output"):
        bad = _invalid_json(nodes.column(name))
        if bad is not None:
            raise MalformedTrace(f"a node's {name} {bad[1]}", int(step[bad[0]]))


def _invalid_json(column: pa.ChunkedArray) -> tuple[int, str] | None:
    """The first row of a string column whose text is not JSON that Python (without NaN or Infinity) and the
    store's JSON type both accept (a lone surrogate escape the store refuses), or that is nested deeper than
    ``MAX_DEPTH`` (the recorder cuts an honest value there), and why; or None. Texts of :data:`SIMPLE_JSON`'s
    shape pass at once; the others are parsed once per distinct text."""
    simple = pc.fill_null(pc.match_substring_regex(column, SIMPLE_JSON), True)
    if pc.all(simple).as_py():
        return None
    others = pc.filter(column, pc.invert(simple))
    for text in pc.unique(others).to_pylist():
        why = _not_json(text)
        if why is not None:
            return int(pc.index(column, text).as_py()), why
    return None


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"JSON constant {name}")


def _not_json(text: str) -> str | None:
    """Why ``text`` is not a JSON value the store may hold, or None."""
    try:
        value = json.loads(text, parse_constant=_refuse_constant)
    except RecursionError:
        return f"is nested deeper than {MAX_DEPTH} levels"
    except ValueError:
        return "is not JSON"
    if (text.count("[") + text.count("{") > MAX_DEPTH) and deeper_than(value, MAX_DEPTH):
        return f"is nested deeper than {MAX_DEPTH} levels"
    if _SURROGATE.search(text):  # the store's JSON refuses a lone surrogate escape that Python accepts
        try:
            json.dumps(value, ensure_ascii=False).encode("utf-8")
        except UnicodeEncodeError:
            return "is not JSON (a lone surrogate)"
    return None


def _check_lines(nodes: pa.Table, spec: Any, methods: dict[str, tuple[bool, int]], step: np.ndarray) -> None:
    """``lines_run``: NULL (lines not recorded), or strictly increasing line numbers inside the source of the
    node's method (what an honest recorder sends), and only when the episode records lines."""
    lines = nodes.column("lines_run").combine_chunks()
    if lines.null_count == len(lines):
        return
    if not spec.trace_lines:
        raise MalformedTrace("lines_run for an episode played without line recording",
                             _first(lines.is_valid().to_numpy(zero_copy_only=False), step))
    functions = nodes.column("function").combine_chunks()
    for name in pc.unique(pc.filter(functions, pc.is_valid(lines))).to_pylist():
        count = methods[name][1]
        chosen = pc.filter(lines, pc.equal(functions, name))
        # a call runs each of its method's lines at most once, in order: more lines than the method has are
        # refused per row, before the values are read
        per_call = np.asarray(pc.list_value_length(chosen).fill_null(0), dtype=np.int64)
        if per_call.size and per_call.max() > count:
            raise MalformedTrace(f"lines_run of {name} outside its {count} lines")
        flat = pc.list_flatten(chosen)
        if flat.null_count:
            raise MalformedTrace(f"lines_run of {name} with a missing line")
        if not len(flat):
            continue
        low, high = pc.min_max(flat).values()  # at the wire's width (int16): nothing is widened
        if low.as_py() < 1 or high.as_py() > count:
            raise MalformedTrace(f"lines_run of {name} outside its {count} lines")
        values = flat.to_numpy()  # int16, zero-copy
        rising = values[1:] > values[:-1]
        starts = per_call.cumsum()[:-1]
        rising[starts[(starts > 0) & (starts < values.size)] - 1] = True  # a new call may start lower
        if not rising.all():
            raise MalformedTrace(f"lines_run of {name} not strictly increasing")
