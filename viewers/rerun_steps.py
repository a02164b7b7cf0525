"""The per-step logging of an episode's recording: the series (action, reward, score, lives), the objects' boxes
and the frames.

:class:`StepColumns` is a run of consecutive steps as columns (from the store or from the host's step log), and
:class:`StepLogger` sends them with ``send_columns`` in chunks of many steps, so logging costs a few microseconds per
step rather than one ~100 µs ``log`` call per entity per step: ``/series/<name>``, ``/objects/<Category>`` every step,
``/game/objects/<Category>`` on the frame's steps (``viewers/rerun_layout.framed_steps``), ``/game/frame`` and its
label ``/game/frame_step``. One entity per object category, coloured and labelled by an annotation context; a
category that vanishes gets empty rows, so its boxes disappear rather than staying on screen.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import rerun as rr

from games import GAMES
from viewers.rerun_layout import framed_steps
from viewers.rerun_recording import entity

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
                    x, y, w, h) -> StepColumns:
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
    def from_table(cls, table: pa.Table) -> StepColumns:
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


class StepLogger:
    """Logs the steps and frames of one episode into ``rec``, in chunks of steps (see the module docstring).

    Stateful across chunks: it remembers which object categories it has drawn, so that a category that vanishes
    gets empty rows (its boxes disappear) rather than staying on screen.
    """

    def __init__(self, rec: rr.RecordingStream, frames_every: int = 0):
        self.rec = rec
        self.frames_every = frames_every
        """K: frames are taken on the multiples of K (0: no frames), and ``/game`` is drawn on those steps only."""
        self._categories: dict[str, int] = {}
        self._static_sent = False

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
        framed = framed_steps(cols.step, self.frames_every)  # rows whose boxes are also drawn over their frame
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
        at = np.asarray(steps, dtype=np.int64)
        t = rr.TimeColumn("step", sequence=at)
        self.rec.send_columns("/game/frame", indexes=[t],
                              columns=rr.EncodedImage.columns(blob=list(pngs), media_type=["image/png"] * len(pngs)))
        # the picture's own step, written on it: scrubbing between frames shows the last frame, and says so
        self.rec.send_columns("/game/frame_step", indexes=[t], columns=rr.Points2D.columns(
            positions=np.tile(FRAME_LABEL_AT, (len(at), 1)), labels=[f"frame of step {s}" for s in at.tolist()],
            radii=np.full(len(at), 0.5, dtype=np.float32), colors=np.tile((0, 0, 0), (len(at), 1)),
            show_labels=np.ones(len(at), dtype=bool)))


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
