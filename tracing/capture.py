"""Per-call node capture: one event for every call of a bundled policy method.

While a :class:`NodeRecorder` is active (``with recorder:``), each call of a bundled method records its
inputs (by parameter name), output, exception (type, message, failing policy line), duration, and the
earlier calls of the same step whose outputs it consumed (``parents``). Data flow is found by identity: an
argument that *is* the object an earlier call returned (or an element of a tuple/list argument that is)
makes that call a parent; when several earlier calls returned that same object (a method passing its input
through), the most recent one is the direct producer and is the one named. For values Python shares
(``None``, ``True``, small ints) this can name a call that merely returned an equal value.

With ``lines=True`` each call also records ``lines_run``: the lines of the method's source (1-based, the
``def`` line being 1) that ran during the call, sorted (``tracing/lines.py``); NULL when lines are not recorded, and
for a method longer than :data:`MAX_LINES_RUN` lines (its line numbers would not fit the ``int16`` of the wire and
of the store's ``SMALLINT``: the node table failed to encode and the episode lost its whole trace).

An exception is recorded by its type's name, its message and the failing policy line, each bounded
(:func:`exception_name`, :func:`exception_message`, :func:`failing_policy_line`), and whatever the exception's own
``__str__`` does (it is policy code: one that raises gives a placeholder message, the node row is kept).

Inputs that are the step's observation dict itself are stored as ``{"$ref": "obs"}``: the observation is
already in the ``steps`` table, and repeating it per call would triple the store. Values are stored as JSON
text: numpy values as numbers/lists, non-finite floats as the strings ``"NaN"``/``"Infinity"``, an int longer
than Python writes (4,300 digits) as ``"<int of n bits>"``, anything else as its ``repr`` with memory addresses
removed (prompts built from nodes must be deterministic). Writing a value can run the policy's own code (a
``__repr__``, a key's ``__str__``, a dict subclass's ``items``, a ``__class__`` property); where that raises, the
value is stored as a placeholder saying so and the call is recorded as it went: recording never ends an episode
that the same policy plays untraced (only its time limit, :class:`PolicyTimeout`, goes through). Each is
held to the bounds of ``tracing/bounded.py``: lists and objects nested deeper than 64 levels are cut (even where
the policy raised its recursion limit, which would let ``json.dumps`` go on until the process's stack overflows),
and a text over 20,000 characters becomes ``{"$truncated": n, "preview": ...}``.
"""

from __future__ import annotations

import json
import json.encoder
import linecache
import math
import re
import sys
import time
from functools import lru_cache
from typing import TYPE_CHECKING, Any

from tracing.bounded import MAX_CHARS, MAX_DEPTH, TOO_DEEP, deeper_than, truncated
from tracing.lines import LineCall
from tracing.sandbox import PolicyTimeout

if TYPE_CHECKING:  # pyarrow is imported where a table is made, numpy not at all (below): importing the `tracing`
    # package imports this module, and every command's parser reaches the package (its bounds, its policy files)
    import pyarrow as pa

ACTIVE: "NodeRecorder | None" = None
"""The recorder bundled methods report to; None when capture is off."""

_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
OBS_REF = {"$ref": "obs"}
OBS_REF_TEXT = '{"$ref":"obs"}'
"""``to_json(OBS_REF)``."""
_USUAL_RECURSION_LIMIT = sys.getrecursionlimit()
"""The recursion limit before any policy code ran (policy code can raise its own; see :func:`to_json`)."""

@lru_cache(maxsize=1)
def node_schema() -> "pa.Schema":
    """``NODE_SCHEMA``: the columns a recorder produces; the store adds ``episode_id`` and ``policy_version_id``."""
    import pyarrow as pa

    return pa.schema(
        [
            ("step", pa.int32()),
            ("call_index", pa.int16()),
            ("function", pa.string()),
            ("trainable", pa.bool_()),
            ("inputs", pa.string()),
            ("output", pa.string()),
            ("exc_type", pa.string()),
            ("exc_message", pa.string()),
            ("exc_line", pa.int32()),
            ("exc_source", pa.string()),
            ("duration_us", pa.int64()),
            ("parents", pa.list_(pa.int16())),
            ("lines_run", pa.list_(pa.int16())),
        ]
    )


def __getattr__(name: str) -> Any:
    if name == "NODE_SCHEMA":  # made when first asked for (its pyarrow with it): :func:`node_schema`
        return node_schema()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def is_policy_filename(filename: str) -> bool:
    """Policy code is compiled under file names starting with ``<policy`` (see ``tracing/policy_file.py``)."""
    return filename.startswith("<policy")


MAX_LINES_RUN = 2**15 - 1
"""The last line number ``lines_run`` holds (``int16`` on the wire, ``SMALLINT[]`` in the store): a method longer
than this records no lines (NULL, as when lines are not recorded)."""
MAX_CALLS_PER_STEP = 2**15
"""Calls of bundled methods one traced step records at most: ``call_index`` is ``int16`` on the wire and in the
store (0 to 32,767). A step past it is recorded no further, and the episode's node table is refused with
:data:`TOO_MANY_CALLS` (:meth:`NodeRecorder.table`): the index overflowed as the table was made, and the episode
said only ``trace missing: ... (ArrowInvalid: Value 32768 too large to fit in C integer type)``."""
TOO_MANY_CALLS = "call a helper that is not bundled in a loop, and bundle the method that runs the loop"
"""What to do about more calls of bundled methods a step than a trace records (a policy that calls a bundled
method per grid cell plays untraced, and forfeits its traced games)."""
MAX_MESSAGE_CHARS = 2_000
"""Characters of an exception's message a node keeps (:func:`exception_message`)."""
MAX_NAME_CHARS = 48
"""Characters of an exception type's name a node keeps: ``nodes.py`` allows ``exc_type`` 200 UTF-8 bytes, and a
character of a name is at most 4 of them (the cut mark 3 more)."""
MAX_SOURCE_CHARS = 500
"""Characters of the failing line's text kept (``exc_source``, and an episode's error): a policy line can be
100,000 characters long."""


_CUT_MARK_CHARS = 40
"""Room for the mark of a cut (``… [cut 99,000 characters]``) within its limit."""


def _cut(text: str, limit: int) -> str:
    """``text``, or its first characters and the mark of the cut: ``limit`` characters at most in all, so that a
    later cap of the same size (the store's, ``untrusted.MESSAGE_LIMIT``) does not cut it again."""
    if len(text) <= limit:
        return text
    keep = limit - _CUT_MARK_CHARS
    return f"{text[:keep]}… [cut {len(text) - keep:,} characters]"


def exception_name(exc: BaseException) -> str:
    """The name of ``exc``'s type, at most :data:`MAX_NAME_CHARS` characters (cut ending in ``…``)."""
    name = type(exc).__name__
    return name if len(name) <= MAX_NAME_CHARS else name[:MAX_NAME_CHARS] + "…"


def exception_message(exc: BaseException, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``str(exc)`` as plain text, at most ``limit`` characters (a cut marked); a placeholder when the exception's
    ``__str__`` (policy code) raises or returns no text. Raised inside the recorder's handler, that exception lost the
    node row, and the episode's error named it and its line in ``__str__`` instead of the policy's own exception."""
    try:
        said = str(exc)
    except (KeyboardInterrupt, PolicyTimeout):
        raise  # the call's time limit (or a stop) while __str__ ran: the episode's end, not a message
    except BaseException as failed:  # noqa: BLE001 - untrusted code: anything, SystemExit too
        return f"<message not shown: its __str__ raised {exception_name(failed)}>"
    return _cut(str.__str__(said), limit)  # a str subclass's own methods are policy code too


def failing_policy_line(exc: BaseException) -> tuple[int | None, str | None]:
    """The innermost line of policy code in ``exc``'s traceback: (line number, stripped text, at most
    :data:`MAX_SOURCE_CHARS` characters)."""
    line_no, text = None, None
    tb = exc.__traceback__
    while tb is not None:
        code = tb.tb_frame.f_code
        if is_policy_filename(code.co_filename):
            line_no = tb.tb_lineno
            text = linecache.getline(code.co_filename, tb.tb_lineno).strip() or None
        tb = tb.tb_next
    return line_no, None if text is None else _cut(text, MAX_SOURCE_CHARS)


def _jsonable(value: Any, depth: int = 0) -> Any:
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return value if _writable_int(value) else _int_mark(value)
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    numpy = sys.modules.get("numpy")  # no value is numpy's where numpy was never imported
    if numpy is not None and isinstance(value, numpy.generic):
        return _jsonable(value.item(), depth)
    if depth >= MAX_DEPTH:  # a list or object below the allowed nesting (scalars were answered above)
        return TOO_DEEP
    if isinstance(value, dict):
        return {str(k) if not isinstance(k, int) or _writable_int(k) else _int_mark(k): _jsonable(v, depth + 1)
                for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, depth + 1) for v in value]
    if isinstance(value, (set, frozenset)):
        return sorted((_jsonable(v, depth + 1) for v in value), key=repr)
    if numpy is not None and isinstance(value, numpy.ndarray):
        return _jsonable(value.tolist(), depth + 1) if value.size <= 1000 else f"<ndarray shape={value.shape}>"
    return _ADDRESS.sub("", repr(value))[:200]


def _writable_int(value: int) -> bool:
    """Whether ``value``'s decimal digits can be written: Python refuses an int of more than its limit of digits
    (``sys.get_int_max_str_digits``, 4,300), and a traced method that returned ``10**5000`` ended its episode in
    that ValueError, where the same policy untraced played on."""
    try:
        int.__repr__(value)
    except ValueError:
        return False
    return True


def _int_mark(value: int) -> str:
    """What stands for an int :func:`_writable_int` refuses."""
    return f"<int of {value.bit_length():,} bits>"


def _refuse(value: Any) -> Any:
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


class _Encoder:
    """``json.dumps(value, allow_nan=False, separators=(",", ":"))``, the very same C encoder, built once: ``dumps``
    builds a ``JSONEncoder`` and a C encoder on every call, which cost more than encoding a node's usual value."""

    def __init__(self) -> None:
        self.markers: dict[int, Any] = {}  # the encoder's circular-reference check: emptied after each value
        make = getattr(json.encoder, "c_make_encoder", None)
        self.encode = None if make is None else make(
            self.markers, _refuse, json.encoder.encode_basestring_ascii, None, ":", ",", False, False, False)

    def __call__(self, value: Any) -> str:
        if self.encode is None or self.markers:  # a dict subclass's items() encoding inside an encoding: its own
            return json.dumps(value, allow_nan=False, separators=(",", ":"))
        try:
            return "".join(self.encode(value, 0))
        except BaseException:
            self.markers.clear()  # the C encoder leaves the containers it was inside of marked when it raises
            raise


_encode = _Encoder()


def _finite_float_text(value: float) -> str:
    if value - value != 0.0:  # inf or nan: json.dumps refuses them with allow_nan=False (to_json's fallback)
        raise ValueError("not a finite float")
    return float.__repr__(value)


_SCALAR_TEXT = {
    type(None): lambda value: "null",
    bool: lambda value: "true" if value else "false",
    int: int.__repr__,
    float: _finite_float_text,
    str: json.encoder.encode_basestring_ascii,
}
"""The JSON text of a value of exactly these types, as ``json.dumps`` writes it (its C encoder calls the same
functions); ``ValueError`` where ``json.dumps`` raises too (a non-finite float, an int of more than 4,300 digits),
which sends the value down :func:`to_json`'s general path. Node values are mostly such scalars: this path costs a
dict lookup and a call, where ``json.dumps`` cost several microseconds."""


def _scalar_text(value: Any) -> str | None:
    """:data:`_SCALAR_TEXT` of ``value``, or None when it has none."""
    text_of = _SCALAR_TEXT.get(type(value))
    if text_of is None:
        return None
    try:
        return text_of(value)
    except ValueError:
        return None


def to_json(value: Any) -> str:
    """Deterministic JSON text for a node input or output (see the module docstring)."""
    text = _scalar_text(value)
    if text is not None:
        return text if len(text) <= MAX_CHARS else json.dumps(truncated(text))
    try:
        return _written(value)
    except (KeyboardInterrupt, PolicyTimeout):
        raise  # the call's time limit (or a stop) while the policy's code ran: the episode's end, not a value
    except BaseException as failed:  # noqa: BLE001 - untrusted code ran inside the value: anything, SystemExit too
        return json.dumps(f"<not shown: writing it raised {exception_name(failed)}>")


def _written(value: Any) -> str:
    """:func:`to_json` of a value that is not one of :data:`_SCALAR_TEXT`'s types."""
    nested = isinstance(value, (dict, list, tuple))
    if nested and sys.getrecursionlimit() > _USUAL_RECURSION_LIMIT and deeper_than(value, MAX_DEPTH):
        # the policy raised its recursion limit: json.dumps would follow a deep value until the stack overflows
        value = _jsonable(value)
    try:
        text = _encode(value)
    except (TypeError, ValueError, RecursionError):
        text = json.dumps(_jsonable(value), separators=(",", ":"))
    if nested and text.count("[") + text.count("{") > MAX_DEPTH and deeper_than(value, MAX_DEPTH):
        text = json.dumps(_jsonable(value), separators=(",", ":"))  # nested deeper than allowed: cut
    if len(text) > MAX_CHARS:
        text = json.dumps(truncated(text))
    return text


class NodeRecorder:
    """Collects node events for one episode, a tuple per node; ``table()`` returns them as Arrow.

    This runs around every bundled call of a traced episode, so its bookkeeping is kept to a few operations per
    call: a node's values are encoded once, when the call ends (:func:`to_json`; the usual ones, a dict of the
    observation and a few scalars, by :meth:`_encode_inputs`'s own path, to the same text), and its row is one
    tuple, turned into columns at the end. ``parents`` and ``lines_run`` are tuples, which the cyclic garbage
    collector stops tracking, so that a long episode's nodes do not make each of its collections slower."""

    def __init__(self, lines: bool = False) -> None:
        self.lines = lines
        """Record the lines each call ran (``lines_run``); costs a trace function call per line executed."""
        self._line_counts: dict[Any, int] = {}
        self._rows: list[tuple] = []
        """One tuple per node, in ``NODE_SCHEMA`` order."""
        self._keys: dict[Any, tuple[tuple[str, ...], tuple[str, ...]]] = {}
        """Per method: its parameter names (after ``self``) and each one's JSON text as a key (``"obs":``)."""
        self.step = -1
        self.obs: Any = None
        self._outputs: list[tuple[Any, int]] = []
        self._next_index = 0
        self._over: tuple[int, int] | None = None
        """The first step that called bundled methods more than :data:`MAX_CALLS_PER_STEP` times, and how often."""

    def __enter__(self) -> "NodeRecorder":
        global ACTIVE
        self._previous = ACTIVE
        ACTIVE = self
        return self

    def __exit__(self, *exc: object) -> None:
        global ACTIVE
        ACTIVE = self._previous

    def __len__(self) -> int:
        return len(self._rows)

    def begin_step(self, step: int, obs: Any) -> None:
        self._count_over()
        self.step = step
        self.obs = obs
        self._outputs.clear()
        self._next_index = 0

    def _names(self, fn: Any) -> tuple[tuple[str, ...], tuple[str, ...]]:
        keys = self._keys.get(fn)
        if keys is None:
            code = fn.__code__
            names = code.co_varnames[1 : code.co_argcount]  # skip self
            keys = self._keys[fn] = names, tuple(json.encoder.encode_basestring_ascii(n) + ":" for n in names)
        return keys

    def _encode_inputs(self, fn: Any, args: tuple, kwargs: dict) -> str:
        names, keys = self._names(fn)
        obs = self.obs
        if not kwargs and len(args) <= len(names):
            # the usual call, positional arguments that are the observation or scalars: their text put together
            # directly, as json.dumps of the dict below writes it
            parts = []
            for key, value in zip(keys, args):
                text = OBS_REF_TEXT if value is obs else _scalar_text(value)
                if text is None:
                    break
                parts.append(key + text)
            else:
                text = "{" + ",".join(parts) + "}"
                return text if len(text) <= MAX_CHARS else json.dumps(truncated(text))
        inputs: dict[str, Any] = {}
        for i, value in enumerate(args):
            key = names[i] if i < len(names) else f"arg{i}"
            inputs[key] = OBS_REF if value is obs else value
        for key, value in kwargs.items():
            inputs[key] = OBS_REF if value is obs else value
        return to_json(inputs)

    def _parents(self, args: tuple, kwargs: dict) -> tuple[int, ...]:
        outputs = self._outputs
        if not outputs:
            return ()
        values = list(args)
        if kwargs:
            values.extend(kwargs.values())
        try:
            for value in list(values):
                if isinstance(value, (tuple, list)) and len(value) <= 16:
                    values.extend(value)
        except (KeyboardInterrupt, PolicyTimeout):
            raise
        except BaseException:  # noqa: BLE001 - a subclass's own __len__ or __iter__ (policy code) raised: the
            pass  # elements found so far are searched; the call itself goes on as it would untraced
        parents = set()
        for value in values:
            # the most recent call that returned this very object is its direct producer
            for output, index in reversed(outputs):
                if value is output:
                    parents.add(index)
                    break
        return tuple(sorted(parents)) if parents else ()

    def call(self, parameter: Any, instance: Any, args: tuple, kwargs: dict) -> Any:
        """Run one bundled call and record it (exceptions are recorded, then re-raised)."""
        index = self._next_index
        self._next_index = index + 1
        if index >= MAX_CALLS_PER_STEP:  # past what a trace holds: played, not recorded (the table says so)
            return parameter.fn(instance, *args, **kwargs)
        fn = parameter.fn
        parents = self._parents(args, kwargs)
        inputs = self._encode_inputs(fn, args, kwargs)
        count = self._line_count(parameter) if self.lines else 0
        lines = self.lines and count <= MAX_LINES_RUN
        run = LineCall(fn, parameter.first_line, count) if lines else fn
        start = time.perf_counter_ns()
        try:
            output = run(instance, *args, **kwargs)
        except BaseException as exc:
            duration = (time.perf_counter_ns() - start) // 1000
            line, text = failing_policy_line(exc)
            self._rows.append((self.step, index, parameter.name, parameter.trainable, inputs, None, exception_name(exc),
                               exception_message(exc), line, text, duration, parents, run.lines() if lines else None))
            raise
        duration = (time.perf_counter_ns() - start) // 1000
        self._rows.append((self.step, index, parameter.name, parameter.trainable, inputs, to_json(output), None, None,
                           None, None, duration, parents, run.lines() if lines else None))
        self._outputs.append((output, index))
        return output

    def _line_count(self, parameter: Any) -> int:
        source = parameter.source
        count = self._line_counts.get(source)
        if count is None:
            count = self._line_counts[source] = source.count("\n")
        return count

    def _count_over(self) -> None:
        if self._over is None and self._next_index > MAX_CALLS_PER_STEP:
            self._over = self.step, self._next_index

    def table(self) -> "pa.Table":
        """The episode's node rows; ``ValueError`` naming the step when one made more calls than a trace holds."""
        self._count_over()
        if self._over is not None:
            step, calls = self._over
            raise ValueError(f"step {step} made {calls:,} calls of bundled methods; a traced step records at most "
                             f"{MAX_CALLS_PER_STEP:,}: {TOO_MANY_CALLS}")
        import pyarrow as pa

        schema = node_schema()
        columns = zip(*self._rows) if self._rows else [()] * len(schema)
        return pa.Table.from_arrays([pa.array(column, type=field.type) for column, field in zip(columns, schema)],
                                    schema=schema)
