"""One Rerun recording per episode: the entity layout, columnar loggers and the blueprint.

The same code logs an episode live, from inside the worker process that plays it (``viewers/rerun_live.py``),
and rebuilt from the store afterwards (``viewers/rerun_replay.py``); both feed it the same columns, so the
two recordings hold the same data. Everything is sent with ``send_columns`` in chunks of many steps, so
logging costs a few microseconds per step rather than one ~100 µs ``log`` call per entity per step.

Recording: application id ``codearcade``, recording id = the episode id (``{run_id}.{iteration}.{kind}.{index}``),
so a rebuilt recording replaces a live one in the viewer. Timeline ``step`` (sequence): the agent step.

Entity layout::

    /game                        AnnotationContext (static): one class per object category -> label, colour
    /game/frame                  EncodedImage (PNG), every K-th step, when frames were taken (optional)
    /game/frame_step             Points2D with a label, on the frame's steps: "frame of step N", so a scrubbed
                                 view says which step the picture (and everything drawn on it) is from
    /game/objects/<Category>     Boxes2D, ONE entity per category (Player, Ball, Enemy, Alien, Shield, Bullet,
                                 Satellite; Breakout brick rows RB OB YB GB AB BB), labels = the observation
                                 keys (Alien3, Ball, RB); an empty row where the category is absent. Drawn over
                                 the frame, so logged on the frame's steps only (every step when there are no
                                 frames): boxes and picture shown together are always of the same step
    /game/policy/<name>          LineStrips2D / Points2D: numeric outputs of bundled methods that are screen
                                 coordinates, named by the parameter that consumes them (predicted_ball_y is a
                                 horizontal line on the frame, target_x a vertical one); on the frame's steps
                                 only, like the boxes  [traced episodes]
    /objects                     AnnotationContext (static), as /game
    /objects/<Category>          Boxes2D of every step (the same boxes, no frame under them)
    /series/action               Scalars (step-wise), one value per step the policy acted
    /series/reward               Scalars, one value per step
    /series/score                Scalars, cumulative reward
    /series/lives                Scalars, lives when the observation was taken
    /policy/<function>           Scalars when the method's outputs are numbers (bools as 0/1), else TextLog of
                                 the JSON output, one per step  [traced episodes]
    /policy/errors               TextLog (ERROR): exceptions of bundled calls and the episode's end error
    /code                        TextDocument (markdown, static): the policy file played
    /lines/<function>            TextDocument (markdown): the method's source with ▶ on the lines that ran at the
                                 step (``nodes.lines_run``), logged at each step where they change (latest-at
                                 shows the right one at every step), its header naming the steps it covers
                                 [traced episodes]
    properties                   ``episode``: run_id, iteration, kind, index, episode_id, game, seed,
                                 policy_version_id, return, length, lives_lost, end_reason, error, max_steps,
                                 sticky, noop_max, traced, frames_every

Frames are taken on the steps that are multiples of K (``frames_every``), by the live recorder and the rebuilt
one alike; the logger draws the boxes and overlays of ``/game`` on those steps only. Rerun shows the latest value
at or before the time cursor, so had the boxes been logged every step, a scrubbed view would show the frame of
step 4 under the boxes of step 7 (a fast paddle well off its box).

Blueprint: the 2D view has origin ``/game`` so it draws the frame, the boxes and the policy overlay together
(the default layout would draw only the frame), with a second tab showing the boxes of every step
(``/objects``); time-series views for score, reward/lives, action and the policy outputs beside it; the code
as a text document.

Every function takes an explicit ``recording`` (a ``rr.RecordingStream``) and falls back to the ambient one
(``rr.init`` / ``with rec:``), as Rerun's own functions do.
"""

from __future__ import annotations

import json
import math
import zlib
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import rerun as rr
import rerun.blueprint as rrb

from games import GAMES
from tracing.bounded import load_json
from viewers.safe_text import markdown_code_block, markdown_text

APPLICATION_ID = "codearcade"
SCREEN_W, SCREEN_H = 160, 210
FRAME_LABEL_AT = (80.0, 4.0)
"""Where the "frame of step N" label is pinned: its text is centred on this point, so the top middle of the
screen keeps it whole in a narrow view (and clear of Pong's score digits)."""


def _game_colours() -> dict[str, tuple[int, int, int]]:
    colours: dict[str, tuple[int, int, int]] = {}
    for game in GAMES.values():  # each game module names its categories' colours
        for category, colour in game.colours.items():
            colours.setdefault(category, tuple(colour))
    return colours


CATEGORY_COLORS: dict[str, tuple[int, int, int]] = _game_colours()
"""Box colours of the curated games' categories (``Game.colours``; others get a colour from their name)."""
_KNOWN_CATEGORIES = tuple(CATEGORY_COLORS)

STEP_SERIES = ("action", "reward", "score", "lives")


def resolve_recording(recording: rr.RecordingStream | None) -> rr.RecordingStream:
    """``recording``, or the ambient (thread-local or global) one; error if there is none."""
    if recording is not None:
        return recording
    ambient = rr.get_data_recording()
    if ambient is None:
        raise RuntimeError("no Rerun recording: pass recording=... or call rr.init()/use `with rec:` first")
    return ambient


def new_recording(recording_id: str, name: str | None = None) -> rr.RecordingStream:
    """A recording stream of application ``codearcade`` with a deterministic id (not made the default)."""
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    rec.set_log_time_enabled(False)  # only our own timelines: a rebuilt recording holds the same data as a live one
    rec.set_log_tick_enabled(False)
    rec.send_recording_name(name or recording_id)
    return rec


def class_id(category: str) -> int:
    """Stable class id of an object category (known ones first, others from a hash of the name)."""
    if category in _KNOWN_CATEGORIES:
        return 1 + _KNOWN_CATEGORIES.index(category)
    return 100 + zlib.crc32(category.encode()) % 60000


def category_color(category: str) -> tuple[int, int, int]:
    if category in CATEGORY_COLORS:
        return CATEGORY_COLORS[category]
    h = zlib.crc32(category.encode())
    return (80 + h % 176, 80 + (h >> 8) % 176, 80 + (h >> 16) % 176)


def entity(*parts: str) -> str:
    """An entity path from parts that may hold any characters (method names, categories)."""
    return "/" + "/".join(rr.escape_entity_path_part(p) for p in parts)


@dataclass
class StepColumns:
    """A run of consecutive steps as columns: the input of :meth:`EpisodeLogger.steps`.

    ``action`` and ``lives`` hold NaN where the store has NULL (a step the policy failed on). Objects are
    flattened: object ``j`` belongs to row ``obj_row[j]``, has observation key ``key[j]`` and category
    ``categories[category_code[j]]``.
    """

    step: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    score: np.ndarray
    lives: np.ndarray
    obj_row: np.ndarray
    key: pa.Array
    category_code: np.ndarray
    categories: list[str]
    x: np.ndarray
    y: np.ndarray
    w: np.ndarray
    h: np.ndarray

    def __len__(self) -> int:
        return len(self.step)

    @classmethod
    def from_arrays(cls, step, action, reward, score, lives, obj_row, key: pa.Array, category: pa.Array,
                    x, y, w, h) -> "StepColumns":
        encoded = pc.dictionary_encode(category)
        if isinstance(encoded, pa.ChunkedArray):
            encoded = encoded.combine_chunks()

        def f64(values) -> np.ndarray:
            if isinstance(values, (pa.Array, pa.ChunkedArray)):
                return values.to_numpy(zero_copy_only=False).astype(np.float64)  # NULL -> NaN
            return np.asarray(values, dtype=np.float64)

        return cls(
            step=np.asarray(step, dtype=np.int64), action=f64(action), reward=f64(reward), score=f64(score),
            lives=f64(lives), obj_row=np.asarray(obj_row, dtype=np.int64),
            key=key.cast(pa.utf8()) if key.type != pa.utf8() else key,
            category_code=encoded.indices.to_numpy(zero_copy_only=False).astype(np.int32),
            categories=encoded.dictionary.to_pylist(),
            x=f64(x), y=f64(y), w=f64(w), h=f64(h),
        )

    @classmethod
    def from_table(cls, table: pa.Table) -> "StepColumns":
        """From a table with the ``steps`` columns ``step, action, reward, score, lives, objects``
        (a store query or ``StepLog.table()``)."""
        objects = table.column("objects").combine_chunks() if table.num_rows else pa.array(
            [], type=table.schema.field("objects").type)
        flat = pc.list_flatten(objects)
        parents = pc.list_parent_indices(objects)

        def field(name: str) -> pa.Array:
            return flat.field(name) if isinstance(flat, pa.StructArray) else pc.struct_field(flat, name)

        return cls.from_arrays(
            table.column("step").to_numpy(), table.column("action"), table.column("reward"),
            table.column("score"), table.column("lives"), parents.to_numpy(zero_copy_only=False),
            field("key"), field("category"), field("x"), field("y"), field("w"), field("h"),
        )


def _numeric(value: Any) -> float | None:
    """A node output as a number, or None when it is not one (bools are 0/1; JSON's non-finite strings too)."""
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)):
        return float(value)
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


class EpisodeLogger:
    """Logs one episode into a recording, in chunks of steps (see the module docstring for the layout).

    Stateful across chunks: it remembers which object categories it has drawn, so that a category that
    vanishes gets empty rows (its boxes disappear) rather than staying on screen.
    """

    def __init__(self, recording: rr.RecordingStream | None = None, traced: bool = False, frames_every: int = 0):
        self.rec = resolve_recording(recording)
        self.traced = traced
        self.frames_every = max(0, int(frames_every or 0))
        """K: frames are taken on the multiples of K (0: no frames), and ``/game`` is drawn on those steps only."""
        self._categories: dict[str, int] = {}
        self._overlays: dict[str, str] = {}
        self._functions: list[str] = []
        self._text_functions: set[str] = set()
        self._has_errors = False
        self._has_frames = False
        self._static_sent = False
        self._policy_text: str | None = None
        self._line_functions: list[str] = []
        self._method_sources: dict[str, list[str]] | None = None

    # -- static parts ------------------------------------------------------------------------------------

    def _send_static(self) -> None:
        if not self._static_sent:
            self._static_sent = True
            for name in STEP_SERIES:
                self.rec.log(f"/series/{name}", rr.SeriesLines(names=name, interpolation_mode="StepAfter"
                                                               if name in ("action", "lives") else None), static=True)

    def _annotate(self, categories: Iterable[str]) -> None:
        new = [c for c in categories if c not in self._categories]
        if not new:
            return
        for c in new:
            self._categories[c] = class_id(c)
        context = rr.AnnotationContext([
            rr.ClassDescription(info=rr.AnnotationInfo(id=cid, label=c, color=category_color(c)))
            for c, cid in sorted(self._categories.items(), key=lambda kv: kv[1])
        ])
        for root in ("/game", "/objects"):
            self.rec.log(root, context, static=True)

    def _on_frame_steps(self, steps: np.ndarray) -> np.ndarray:
        """Mask of ``steps`` that have a frame (all of them when there are no frames)."""
        if not self.frames_every:
            return np.ones(len(steps), dtype=bool)
        return np.asarray(steps) % self.frames_every == 0

    def code(self, policy_text: str) -> None:
        """The policy file, as a markdown text document at ``/code``."""
        self._policy_text = policy_text
        self._method_sources = None
        self.rec.log("/code", rr.TextDocument(markdown_code_block(policy_text, "python"), media_type="text/markdown"),
                     static=True)

    def properties(self, episode: Mapping[str, Any], frames_every: int = 0) -> None:
        """The episode's row (run, iteration, version, seed, return, end reason, ...) as recording properties."""
        keys = ("run_id", "iteration", "kind", "episode_index", "episode_id", "game", "seed", "policy_version_id",
                "return", "length", "lives_lost", "end_reason", "error", "max_steps", "sticky", "noop_max", "traced")
        values = {k: episode.get(k) for k in keys if episode.get(k) is not None}
        values["frames_every"] = frames_every
        self.rec.send_property("episode", rr.AnyValues(**{k: _property_value(v) for k, v in values.items()}))
        if episode.get("error"):
            self._has_errors = True
            last = int(episode.get("length") or 0)
            self.rec.set_time("step", sequence=last)
            self.rec.log("/policy/errors", rr.TextLog(f"episode ended ({episode.get('end_reason')}): "
                                                      f"{episode['error']}", level=rr.TextLogLevel.ERROR))
            self.rec.reset_time()

    # -- per-step data -----------------------------------------------------------------------------------

    def steps(self, cols: StepColumns) -> None:
        """Series and object boxes of a chunk of consecutive steps."""
        n = len(cols)
        if n == 0:
            return
        self._send_static()
        t = rr.TimeColumn("step", sequence=cols.step)
        send = self.rec.send_columns
        for name in ("reward", "score"):
            send(f"/series/{name}", indexes=[t], columns=rr.Scalars.columns(scalars=getattr(cols, name)))
        for name in ("action", "lives"):
            values = getattr(cols, name)
            ok = ~np.isnan(values)
            if ok.any():
                send(f"/series/{name}", indexes=[rr.TimeColumn("step", sequence=cols.step[ok])],
                     columns=rr.Scalars.columns(scalars=values[ok]))

        present = cols.categories
        self._annotate(sorted(present))
        framed = self._on_frame_steps(cols.step)  # rows whose boxes are also drawn over their frame
        all_framed = bool(framed.all())
        framed_t = t if all_framed else rr.TimeColumn("step", sequence=cols.step[framed])
        row_to_framed = np.cumsum(framed) - 1  # a framed row's position among the framed rows
        cx = cols.x + cols.w / 2.0
        cy = cols.y + cols.h / 2.0
        for category in sorted(self._categories):
            if category in present:
                where = np.flatnonzero(cols.category_code == present.index(category))
                boxes = self._boxes(cols, where, cx, cy, category)
                columns = boxes.partition(np.bincount(cols.obj_row[where], minlength=n))
                if all_framed:
                    over_frame = columns
                else:  # the same boxes, those of the framed rows (taken from the built arrays: half the cost)
                    on_frame = np.flatnonzero(framed[cols.obj_row[where]])
                    lengths = np.bincount(row_to_framed[cols.obj_row[where[on_frame]]], minlength=int(framed.sum()))
                    over_frame = rr.ComponentColumnList([
                        rr.ComponentColumn(c.descriptor, _Rows(c.component_batch, on_frame), lengths=lengths)
                        for c in boxes])
            else:  # drawn in an earlier chunk, absent in this one: empty rows clear it
                columns = _no_boxes(n)
                over_frame = columns if all_framed else _no_boxes(int(framed.sum()))
            send(entity("objects", category), indexes=[t], columns=columns)
            if framed.any():
                send(entity("game", "objects", category), indexes=[framed_t], columns=over_frame)

    def _boxes(self, cols: StepColumns, where: np.ndarray, cx: np.ndarray, cy: np.ndarray, category: str):
        """Box columns of the objects ``where`` (not yet partitioned into steps)."""
        return rr.Boxes2D.columns(
            centers=np.column_stack((cx[where], cy[where])),
            half_sizes=np.column_stack((cols.w[where] / 2.0, cols.h[where] / 2.0)),
            labels=cols.key.take(pa.array(where, type=pa.int64())),
            class_ids=np.full(len(where), self._categories[category], dtype=np.uint16),
        )

    def frames(self, steps: Sequence[int], pngs: Sequence[bytes]) -> None:
        """PNG frames taken at ``steps``."""
        if not len(steps):
            return
        self._has_frames = True
        at = np.asarray(steps, dtype=np.int64)
        t = rr.TimeColumn("step", sequence=at)
        self.rec.send_columns("/game/frame", indexes=[t],
                              columns=rr.EncodedImage.columns(blob=list(pngs), media_type=["image/png"] * len(pngs)))
        # the picture's own step, written on it: scrubbing between frames shows the last frame, and says so
        self.rec.send_columns("/game/frame_step", indexes=[t], columns=rr.Points2D.columns(
            positions=np.tile(FRAME_LABEL_AT, (len(at), 1)), labels=[f"frame of step {s}" for s in at.tolist()],
            radii=np.full(len(at), 0.5, dtype=np.float32), colors=np.tile((0, 0, 0), (len(at), 1)),
            show_labels=np.ones(len(at), dtype=bool)))

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

        for fn, (s, numbers, texts) in per_function.items():
            if fn not in self._functions:
                self._functions.append(fn)
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
        if errors[0]:
            self._has_errors = True
            self.rec.send_columns("/policy/errors", indexes=[rr.TimeColumn("step", sequence=errors[0])],
                                  columns=rr.TextLog.columns(text=errors[1], level=["ERROR"] * len(errors[1])))

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
            if fn not in self._line_functions:
                self._line_functions.append(fn)
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
        framed = np.flatnonzero(self._on_frame_steps(np.asarray(steps, dtype=np.int64)))
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

    # -- layout ------------------------------------------------------------------------------------------

    def blueprint(self) -> rrb.Blueprint:
        """The layout for what has been logged so far (call after the data)."""
        return episode_blueprint(traced=self.traced or bool(self._functions), errors=self._has_errors,
                                 line_functions=self._line_functions)

    def send_blueprint(self) -> None:
        self.rec.send_blueprint(self.blueprint())


def episode_blueprint(traced: bool = False, errors: bool = False, line_functions: Sequence[str] = ()) -> rrb.Blueprint:
    """Game view (frame + boxes + policy overlay) beside score/reward/action series, policy outputs (traced
    episodes) and the code; a log of policy outputs and errors under the game view when there can be any; the
    lines that ran of each method in ``line_functions`` above the code."""
    left: list[Any] = [rrb.Tabs(game_view("/game", "game"), objects_view("/objects"))]
    if traced or errors:
        left.append(rrb.TextLogView(origin="/policy", name="policy log"))
    series: list[Any] = [
        rrb.TimeSeriesView(origin="/series", contents=["/series/score"], name="score"),
        rrb.TimeSeriesView(origin="/series", contents=["/series/reward", "/series/lives"], name="reward, lives"),
        rrb.TimeSeriesView(origin="/series", contents=["/series/action"], name="action"),
    ]
    if traced:
        series.append(rrb.TimeSeriesView(origin="/policy", name="policy outputs"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(*left, row_shares=[3, 1][: len(left)]),
            rrb.Vertical(*series),
            rrb.Vertical(*[rrb.TextDocumentView(origin=entity("lines", fn), name=f"lines run: {fn}")
                           for fn in line_functions],
                         rrb.TextDocumentView(origin="/code", name="policy code"),
                         row_shares=[2] * len(line_functions) + [1])
            if line_functions else rrb.TextDocumentView(origin="/code", name="policy code"),
            column_shares=[2, 1.6, 2.4] if line_functions else [2, 2, 1.5],  # room for the marked sources
        ),
        collapse_panels=True,
    )


def game_view(origin: str, name: str) -> rrb.Spatial2DView:
    """The 2D view of a frame with the boxes and overlays drawn on it (all of the step the label names)."""
    return rrb.Spatial2DView(origin=origin, name=name,
                             visual_bounds=rrb.VisualBounds2D(x_range=[0, SCREEN_W], y_range=[0, SCREEN_H]))


def objects_view(origin: str) -> rrb.Spatial2DView:
    """The boxes of every step, without a frame under them."""
    return rrb.Spatial2DView(origin=origin, name="objects, every step",
                             visual_bounds=rrb.VisualBounds2D(x_range=[0, SCREEN_W], y_range=[0, SCREEN_H]))


class _Rows:
    """Some rows of a built component batch (Rerun's ``ComponentBatchLike``: it only needs the Arrow array)."""

    def __init__(self, batch: Any, rows: np.ndarray):
        self._array = batch.as_arrow_array().take(pa.array(rows, type=pa.int64()))

    def as_arrow_array(self) -> pa.Array:
        return self._array


def _no_boxes(rows: int):
    """``rows`` empty rows of boxes (a category absent on those steps)."""
    return rr.Boxes2D.columns(centers=np.zeros((0, 2)), half_sizes=np.zeros((0, 2)),
                              labels=pa.array([], type=pa.utf8()), class_ids=np.zeros(0, dtype=np.uint16)
                              ).partition(np.zeros(rows, dtype=np.int64))


def _property_value(value: Any) -> Any:
    if isinstance(value, (bool, int, float, str)):
        return value
    return str(value)
