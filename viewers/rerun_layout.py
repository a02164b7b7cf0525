"""The layout of an episode's recording: the screen it is drawn on, which steps carry the game view, and the
blueprint that arranges the views.

Frames are taken on the steps that are multiples of K (``frames_every``), by the live recorder and the rebuilt one
alike, and ``/game`` (the frame, the boxes and the policy's overlays) is drawn on those steps only
(:func:`framed_steps`): Rerun shows the latest value at or before the time cursor, so had the boxes been logged
every step, a scrubbed view would show the frame of step 4 under the boxes of step 7 (a fast paddle well off its
box).

Blueprint (:func:`episode_blueprint`): the 2D view has origin ``/game`` so it draws the frame, the boxes and the
policy overlay together (the default layout would draw only the frame), with a second tab showing the boxes of every
step (``/objects``); time-series views for score, reward/lives, action and the policy outputs beside it; the lines
that ran of each method and the code as text documents.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun.blueprint as rrb

from viewers.rerun_recording import entity

SCREEN_W, SCREEN_H = 160, 210


def framed_steps(steps: np.ndarray, frames_every: int) -> np.ndarray:
    """Mask of ``steps`` that have a frame, those taken every ``frames_every`` steps (all of them when 0: no
    frames)."""
    if not frames_every:
        return np.ones(len(steps), dtype=bool)
    return np.asarray(steps) % frames_every == 0


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
