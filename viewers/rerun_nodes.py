"""The per-call logging of an episode's recording: what the policy's trainable methods returned, raised and ran.

From a traced episode's node rows (one per call of a trainable method), :class:`NodeLogger` sends
``/policy/<function>`` (Scalars when the method's outputs are numbers, else a TextLog of the JSON output, one per
step), ``/policy/errors`` (exceptions of bundled calls), ``/game/policy/<name>`` (an output that is a screen
coordinate, named by the parameter that consumes it, drawn on the frame as a line) and ``/lines/<function>`` (the
method's source with ▶ on the lines that ran). Node rows are the policy process's data, possibly hostile: they are
read in slices of about :data:`NODE_SLICE_BYTES` (whole steps), so what the host holds is a constant multiple of
what it received, and every JSON value is decoded with its nesting bounded.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import rerun as rr

from tracing.bounded import load_json
from viewers.rerun_layout import SCREEN_H, SCREEN_W, framed_steps
from viewers.rerun_recording import entity
from viewers.safe_text import markdown_code_block, markdown_text


def _numeric(value: Any) -> float | None:
    """A node output as a number, or None when it is not one (bools are 0/1; JSON's non-finite strings too); an int
    past a float's range (``10**400``, which a method may return: float() raised OverflowError, the live recording
    was not made and ``view`` of the episode ended in a traceback) is not one: its function is shown as text."""
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)):
        try:
            return float(value)
        except OverflowError:
            return None
    if value in ("NaN", "Infinity", "-Infinity"):
        return float(value.replace("Infinity", "inf"))
    return None


NODE_SLICE_BYTES = 2**20
"""Bytes of node rows :meth:`EpisodeLogger.nodes` makes Python values of at a time (and of texts it sends at
once): the host's memory for a recording of node rows is a constant multiple of this and of what it sends."""


def node_slices(table: pa.Table, limit: int) -> Iterable[pa.Table]:
    """``table`` in consecutive slices of about ``limit`` bytes (its values and lines), each ending at the end of a
    step (a step's calls are read together: the last call's output, the lines of a step's calls joined)."""
    n = table.num_rows
    if n == 0:
        return
    size = np.full(n, 64, dtype=np.int64)
    for name in ("inputs", "output", "exc_message", "exc_source"):
        size += pc.binary_length(table.column(name)).fill_null(0).to_numpy()
    size += 2 * pc.list_value_length(table.column("lines_run")).fill_null(0).to_numpy() \
        + 2 * pc.list_value_length(table.column("parents")).fill_null(0).to_numpy()
    ends = np.cumsum(size)
    step = table.column("step").to_numpy()
    last_of_step = np.r_[step[1:] != step[:-1], True]  # rows after which another step begins
    start = 0
    while start < n:
        stop = max(start + 1, int(np.searchsorted(ends, (ends[start - 1] if start else 0) + limit, side="right")))
        later = np.flatnonzero(last_of_step[stop - 1:])  # the end of the step the slice ends in
        stop = stop + int(later[0]) if len(later) else n
        yield table.slice(start, stop - start)
        start = stop


def _spans(texts: Sequence[str], limit: int) -> Iterable[tuple[int, int]]:
    """(start, stop) of consecutive runs of ``texts`` of about ``limit`` characters each."""
    start, held = 0, 0
    for i, text in enumerate(texts):
        held += len(text)
        if held >= limit:
            yield start, i + 1
            start, held = i + 1, 0
    if start < len(texts):
        yield start, len(texts)


def _coordinate_axis(name: str) -> str | None:
    """``x``/``y`` when a value named ``name`` is a screen coordinate (``predicted_ball_y``, ``target_x``)."""
    lowered = name.lower()
    for axis in ("x", "y"):
        if lowered == axis or lowered.endswith("_" + axis):
            return axis
    return None


class NodeLogger:
    """Logs the node rows of one episode into ``rec`` (see the module docstring); the lines that ran need the
    policy's text first (:meth:`policy_text`)."""

    def __init__(self, rec: rr.RecordingStream, frames_every: int = 0):
        self.rec = rec
        self.frames_every = frames_every
        self.functions: list[str] = []
        """The methods whose outputs were logged, in order."""
        self.line_functions: list[str] = []
        """The methods whose lines that ran were logged, in order."""
        self.has_errors = False
        """Whether a bundled call's exception was logged."""
        self._overlays: dict[str, str] = {}
        self._text_functions: set[str] = set()
        self._policy_text: str | None = None
        self._method_sources: dict[str, list[str]] | None = None

    def policy_text(self, text: str) -> None:
        """The policy file played, whose methods' sources ``/lines/<function>`` shows."""
        self._policy_text = text
        self._method_sources = None

    def nodes(self, table: pa.Table | Mapping[str, Sequence]) -> None:
        """Outputs and exceptions of bundled calls (a ``nodes`` table: step, call_index, function, inputs,
        output, exc_type, exc_message, exc_line, exc_source, parents; ``inputs``/``output`` JSON text).

        A table is read in slices of about :data:`NODE_SLICE_BYTES` (whole steps), each made Python values and
        decoded on its own; only what is sent is kept between slices (per function and step, a number or the
        output's text; line sets as packed bytes), so what the host holds is a constant multiple of what it
        received, never ``to_pydict()`` of a whole column (64 MB of ``lines_run`` held 1.6 GB that way)."""
        parts = node_slices(table, NODE_SLICE_BYTES) if isinstance(table, pa.Table) else [dict(table)]
        per_function: dict[str, tuple[list[int], list[float | None], list[str]]] = {}
        errors: tuple[list[int], list[str]] = ([], [])
        names: dict[str, str] = {}
        lines: dict[str, list[tuple[int, bytes]]] = {}
        for part in parts:
            data = part.to_pydict() if isinstance(part, pa.Table) else part
            n = len(data.get("step", ()))
            if n == 0:
                continue
            steps, calls, functions = data["step"], data["call_index"], data["function"]
            outputs = [load_json(o) if o is not None else None for o in data["output"]]  # nesting bounded
            by_step_call = {(steps[i], calls[i]): i for i in range(n)}
            for fn, param in self._name_outputs(data, outputs, by_step_call).items():
                names.setdefault(fn, param)
            for i in range(n):
                fn = functions[i]
                if data["exc_type"][i] is not None:
                    line = f" at line {data['exc_line'][i]}: `{data['exc_source'][i]}`" if data["exc_line"][i] else ""
                    errors[0].append(steps[i])
                    errors[1].append(f"{fn}: {data['exc_type'][i]}: {data['exc_message'][i]}{line}")
                    continue
                s, numbers, texts = per_function.setdefault(fn, ([], [], []))
                value = outputs[i]
                if s and s[-1] == steps[i]:  # called again in the same step: the last call's output wins
                    numbers[-1], texts[-1] = _numeric(value), json.dumps(value)
                else:
                    s.append(steps[i])
                    numbers.append(_numeric(value))
                    texts.append(json.dumps(value))
            self._collect_lines(data, lines)
            del data, outputs, by_step_call
            self._send_errors(errors)  # a slice's at a time: a policy's caught exceptions may be most of its rows

        for fn, (s, numbers, texts) in per_function.items():
            if fn not in self.functions:
                self.functions.append(fn)
            numeric = all(x is not None or t == "null" for x, t in zip(numbers, texts))
            path = entity("policy", fn)
            if numeric and fn not in self._text_functions:
                keep = [k for k, x in enumerate(numbers) if x is not None]
                if keep:
                    self.rec.send_columns(path, indexes=[rr.TimeColumn("step", sequence=[s[k] for k in keep])],
                                          columns=rr.Scalars.columns(scalars=[numbers[k] for k in keep]))
                self._overlay(fn, names.get(fn, fn), s, numbers)
            else:
                self._text_functions.add(fn)
                for at, stop in _spans(texts, NODE_SLICE_BYTES):
                    self.rec.send_columns(path, indexes=[rr.TimeColumn("step", sequence=s[at:stop])],
                                          columns=rr.TextLog.columns(text=texts[at:stop],
                                                                     level=["INFO"] * (stop - at)))
        self._send_lines(lines)

    def _send_errors(self, errors: tuple[list[int], list[str]]) -> None:
        """Log the exceptions of ``errors`` (steps, texts) under ``/policy/errors`` in spans of at most
        :data:`NODE_SLICE_BYTES`, and empty it."""
        steps, texts = errors
        if steps:
            self.has_errors = True
            for at, stop in _spans(texts, NODE_SLICE_BYTES):
                self.rec.send_columns("/policy/errors", indexes=[rr.TimeColumn("step", sequence=steps[at:stop])],
                                      columns=rr.TextLog.columns(text=texts[at:stop], level=["ERROR"] * (stop - at)))
        steps.clear()
        texts.clear()

    def _collect_lines(self, data: Mapping[str, Sequence], per_function: dict[str, list[tuple[int, bytes]]]) -> None:
        """Add the lines that ran of each call in ``data`` (a slice of node rows) to ``per_function``: (step, the
        line numbers packed as int16 bytes), the lines of calls of one step joined."""
        if self._policy_text is None or not any(x is not None for x in data.get("lines_run") or ()):
            return
        sources = self._sources()
        for step, fn, ran in zip(data["step"], data["function"], data["lines_run"]):
            if ran is not None and fn in sources:
                calls = per_function.setdefault(fn, [])
                packed = np.asarray(ran, dtype=np.int16).tobytes()
                if calls and calls[-1][0] == step:  # called twice in a step: both calls' lines
                    both = np.union1d(np.frombuffer(calls[-1][1], np.int16), np.frombuffer(packed, np.int16))
                    calls[-1] = (step, both.astype(np.int16).tobytes())
                else:
                    calls.append((step, packed))

    def _sources(self) -> dict[str, list[str]]:
        """The policy's methods' source lines (from :meth:`code`'s text), read once."""
        if self._method_sources is None:
            from tracing.policy_file import PolicyLoadError, inspect_policy

            try:
                self._method_sources = {m.name: m.source.splitlines()
                                        for m in inspect_policy(self._policy_text).methods}
            except PolicyLoadError:
                self._method_sources = {}
        return self._method_sources

    def _send_lines(self, per_function: Mapping[str, list[tuple[int, bytes]]]) -> None:
        """``/lines/<function>``: the method's source marked with the lines that ran, one document per run of
        consecutive steps with the same lines (needs :meth:`code` first, for the sources), sent a few MB of
        documents at a time."""
        sources = self._sources() if per_function else {}
        for fn, calls in per_function.items():
            starts = [k for k in range(len(calls)) if k == 0 or calls[k][1] != calls[k - 1][1]]
            if fn not in self.line_functions:
                self.line_functions.append(fn)
            docs: list[str] = []
            at: list[int] = []
            held = 0
            for j, k in enumerate(starts):
                last = calls[(starts[j + 1] if j + 1 < len(starts) else len(calls)) - 1][0]
                first, ran = calls[k][0], set(np.frombuffer(calls[k][1], np.int16).tolist())
                span = f"step {first}" if first == last else f"steps {first}-{last}"
                body = "\n".join(f"{'▶' if i in ran else ' '} {i:>3}  {text}"
                                  for i, text in enumerate(sources[fn], start=1))
                docs.append(f"**{markdown_text(fn)}**: ▶ the lines that ran at {span}\n\n"
                            f"{markdown_code_block(body, 'python')}")
                at.append(first)
                held += len(docs[-1])
                if held >= NODE_SLICE_BYTES or j + 1 == len(starts):
                    self.rec.send_columns(entity("lines", fn), indexes=[rr.TimeColumn("step", sequence=at)],
                                          columns=rr.TextDocument.columns(text=docs,
                                                                          media_type=["text/markdown"] * len(docs)))
                    docs, at, held = [], [], 0

    def _name_outputs(self, data: Mapping[str, Sequence], outputs: list[Any],
                      by_step_call: Mapping[tuple[int, int], int]) -> dict[str, str]:
        """Per function, the parameter name its output is passed as (``predicted_ball_y``), where found."""
        names: dict[str, str] = {}
        for i, parents in enumerate(data["parents"]):
            if not parents or data["inputs"][i] is None:
                continue
            inputs = None
            for p in parents:
                j = by_step_call.get((data["step"][i], p))
                if j is None or data["function"][j] in names or outputs[j] is None:
                    continue
                if inputs is None:
                    inputs = load_json(data["inputs"][i])
                if not isinstance(inputs, dict):  # a marker (too deep, too long) or a store edited by hand
                    break
                for param, value in inputs.items():
                    if value == outputs[j] and not isinstance(value, dict):
                        names[data["function"][j]] = param
                        break
        return names

    def _overlay(self, fn: str, name: str, steps: list[int], values: list[float | None]) -> None:
        """Draw a coordinate-valued output on the frame: a horizontal line for y, a vertical one for x; on the
        frame's steps only, and nothing on a step whose value is None or not finite (not the last line drawn)."""
        axis = self._overlays.get(fn) or _coordinate_axis(name) or _coordinate_axis(fn)
        if axis is None or not any(x is not None for x in values):
            return
        self._overlays[fn] = axis
        framed = np.flatnonzero(framed_steps(np.asarray(steps, dtype=np.int64), self.frames_every))
        if not len(framed):
            return
        drawn = [k for k in framed if values[k] is not None and math.isfinite(values[k])]
        lengths = np.asarray([values[k] is not None and math.isfinite(values[k]) for k in framed], dtype=np.int64)
        steps = [steps[k] for k in framed]
        v = np.asarray([values[k] for k in drawn], dtype=np.float32)
        if axis == "y":
            strips = np.stack([np.column_stack((np.zeros_like(v), v)), np.column_stack((np.full_like(v, SCREEN_W), v))], 1)
        else:
            strips = np.stack([np.column_stack((v, np.zeros_like(v))), np.column_stack((v, np.full_like(v, SCREEN_H)))], 1)
        self.rec.send_columns(
            entity("game", "policy", name), indexes=[rr.TimeColumn("step", sequence=steps)],
            columns=rr.LineStrips2D.columns(strips=list(strips), labels=[name] * len(drawn),
                                            colors=[(255, 255, 0)] * len(drawn)).partition(lengths),
        )
