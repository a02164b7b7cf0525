"""A side-by-side Rerun recording of two stored episodes on one ``step`` timeline (``codearcade compare --rerun``).

Each episode is logged exactly as ``codearcade view`` logs one (``viewers/rerun_replay.py``: frames regenerated
by replaying its actions, boxes, series, node outputs), under its own root, ``/A`` and ``/B``; the blueprint
puts the two game views side by side, the two action and score series on shared plots below, the first
divergent step as a log line at that step, and the diff of the two policies. Recording id
``compare.<episode A>.<episode B>``.

Entity layout: ``/A/...`` and ``/B/...`` each hold an episode's layout (``viewers/rerun_episode.py``);
``/compare/divergence`` TextLog at the first divergent step; ``/compare/diff`` TextDocument (static).

Rerun starts Rust threads on import, and ``codearcade compare`` forks episode workers, so the recording is
written by this module run as a separate process::

    python -m viewers.rerun_compare --store S --a EPISODE --b EPISODE [--divergent-step N] [--diff FILE]
                                    [--frames-every K] --to FILE.rrd|rerun+http://HOST:PORT/proxy
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import rerun as rr
import rerun.blueprint as rrb

from store import Store
from viewers.rerun_layout import game_view
from viewers.rerun_recording import close, new_recording, save_whole
from viewers.rerun_steps import STEP_SERIES
from viewers.rerun_replay import log_stored_episode, read_episode
from viewers.rerun_sinks import is_grpc_url
from viewers.safe_text import markdown_code_block

SIDES = ("A", "B")
SIDE_COLOURS = {"A": (31, 119, 180), "B": (214, 39, 40)}


class SubtreeRecording:
    """A recording seen through an entity-path prefix: what an :class:`~viewers.rerun_episode.EpisodeLogger`
    logs at ``/game/...`` lands at ``/A/game/...``. Properties get the prefix in their name; blueprints are
    left to the caller (one for the whole comparison)."""

    def __init__(self, rec: rr.RecordingStream, root: str):
        self.rec = rec
        self.root = root

    def _path(self, path: str) -> str:
        return f"/{self.root}/{str(path).lstrip('/')}"

    def log(self, path: str, *args: Any, **kwargs: Any) -> None:
        self.rec.log(self._path(path), *args, **kwargs)

    def send_columns(self, path: str, *args: Any, **kwargs: Any) -> None:
        self.rec.send_columns(self._path(path), *args, **kwargs)

    def send_property(self, name: str, values: Any) -> None:
        self.rec.send_property(f"{self.root}_{name}", values)

    def set_time(self, *args: Any, **kwargs: Any) -> None:
        self.rec.set_time(*args, **kwargs)

    def reset_time(self) -> None:
        self.rec.reset_time()

    def send_blueprint(self, *args: Any, **kwargs: Any) -> None:
        """Ignored: the comparison sends one blueprint for both episodes."""


def compare_blueprint(names: dict[str, str]) -> rrb.Blueprint:
    """The two game views side by side; the actions and scores of both on shared plots; divergence and diff."""
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(*(game_view(f"/{side}/game", f"{side}: {names[side]}") for side in SIDES)),
            rrb.Horizontal(
                rrb.TimeSeriesView(origin="/", contents=[f"/{s}/series/action" for s in SIDES], name="actions"),
                rrb.TimeSeriesView(origin="/", contents=[f"/{s}/series/score" for s in SIDES], name="scores"),
                rrb.TextLogView(origin="/compare", name="divergence"),
                rrb.TextDocumentView(origin="/compare/diff", name="diff A -> B"),
            ),
            row_shares=[3, 1.3],
        ),
        collapse_panels=True,
    )


def write(store: Store, episodes: dict[str, str], to: str, divergent_step: int | None = None, diff: str = "",
          frames_every: int = 4) -> list[str]:
    """Write the side-by-side recording of ``episodes`` (``{"A": id, "B": id}``) to a file or gRPC url; the
    replay checks' descriptions (one per side)."""
    with store.read() as con:
        data = {side: read_episode(con, episodes[side]) for side in SIDES}
    rec = new_recording(f"compare.{episodes['A']}.{episodes['B']}", name=f"compare {episodes['A']} vs {episodes['B']}")
    names = {side: f"{data[side].episode['policy_version_id']} (seed {data[side].episode['seed']})" for side in SIDES}
    blueprint = compare_blueprint(names)
    partial = None
    if is_grpc_url(to):
        rec.connect_grpc(to, default_blueprint=blueprint)
    else:
        partial = save_whole(rec, to, default_blueprint=blueprint)
    notes = []
    try:
        for side in SIDES:
            check = log_stored_episode(data[side], SubtreeRecording(rec, side), frames_every)  # type: ignore[arg-type]
            notes.append(f"{side}: {check.describe()}")
            for name in STEP_SERIES:  # one legend entry per side: "A action", "B action"
                rec.log(f"/{side}/series/{name}", rr.SeriesLines(names=f"{side} {name}", colors=SIDE_COLOURS[side],
                                                                 interpolation_mode="StepAfter"), static=True)
        rec.log("/compare/diff", rr.TextDocument(markdown_code_block(diff or "(the same code)", "diff"),
                                                 media_type="text/markdown"), static=True)
        if divergent_step is not None:
            actions = {side: _action_at(data[side].steps, divergent_step) for side in SIDES}
            rec.set_time("step", sequence=divergent_step)
            rec.log("/compare/divergence", rr.TextLog(
                f"first divergent step {divergent_step}: A chose {actions['A']}, B chose {actions['B']}",
                level=rr.TextLogLevel.WARN))
            rec.reset_time()
        rec.send_blueprint(blueprint)
    except BaseException:
        close(rec, partial, to, whole=False)
        raise
    close(rec, partial, None if is_grpc_url(to) else to)  # a file's path names it in an error
    return notes


def _action_at(steps, step: int) -> Any:
    column = steps.column("step").to_pylist()
    return steps.column("action")[column.index(step)].as_py() if step in column else "nothing (episode over)"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m viewers.rerun_compare", description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--a", required=True, metavar="EPISODE")
    parser.add_argument("--b", required=True, metavar="EPISODE")
    parser.add_argument("--to", required=True, metavar="FILE.rrd|URL")
    parser.add_argument("--divergent-step", type=int)
    parser.add_argument("--diff", metavar="FILE", help="a file holding the diff of the two policies")
    parser.add_argument("--frames-every", type=int, default=4)
    args = parser.parse_args(argv)
    diff = Path(args.diff).read_text() if args.diff else ""
    for note in write(Store(args.store), {"A": args.a, "B": args.b}, args.to, args.divergent_step, diff,
                      args.frames_every):
        print(note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
