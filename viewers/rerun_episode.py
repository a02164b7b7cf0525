"""One Rerun recording per episode: the entity layout, and the logger that writes all of it.

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
one alike; the logger draws the boxes and overlays of ``/game`` on those steps only (``viewers/rerun_layout.py``
says why).

:class:`EpisodeLogger` writes the recording's static parts (the code, the episode's properties and end error, the
blueprint) and hands the rest to the modules that know each part: ``viewers/rerun_steps.py`` (the series, the boxes
and the frames of each step), ``viewers/rerun_nodes.py`` (the outputs, exceptions, overlays and lines that ran of each
call of a trainable method), ``viewers/rerun_layout.py`` (the blueprint), ``viewers/rerun_recording.py`` (the
recording stream, its ids, entity paths).

Every function takes an explicit ``recording`` (a ``rr.RecordingStream``) and falls back to the ambient one
(``rr.init`` / ``with rec:``), as Rerun's own functions do.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from viewers.rerun_layout import episode_blueprint
from viewers.rerun_nodes import NodeLogger
from viewers.rerun_recording import resolve_recording
from viewers.rerun_steps import StepColumns, StepLogger
from viewers.safe_text import markdown_code_block, plain_text


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
        self._steps = StepLogger(self.rec, self.frames_every)
        self._nodes = NodeLogger(self.rec, self.frames_every)
        self._has_errors = False

    # -- static parts ------------------------------------------------------------------------------------

    def code(self, policy_text: str) -> None:
        """The policy file, as a markdown text document at ``/code``."""
        self._nodes.policy_text(policy_text)
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
            self.rec.log("/policy/errors", rr.TextLog(plain_text(f"episode ended ({episode.get('end_reason')}): "
                                                                 f"{episode['error']}"), level=rr.TextLogLevel.ERROR))
            self.rec.reset_time()

    # -- per-step and per-call data ----------------------------------------------------------------------

    def steps(self, cols: StepColumns) -> None:
        """Series and object boxes of a chunk of consecutive steps."""
        self._steps.steps(cols)

    def frames(self, steps: Sequence[int], pngs: Sequence[bytes]) -> None:
        """PNG frames taken at ``steps``."""
        self._steps.frames(steps, pngs)

    def nodes(self, table: pa.Table | Mapping[str, Sequence]) -> None:
        """Outputs and exceptions of bundled calls (a ``nodes`` table; ``viewers/rerun_nodes.NodeLogger.nodes``)."""
        self._nodes.nodes(table)

    # -- layout ------------------------------------------------------------------------------------------

    def blueprint(self) -> rrb.Blueprint:
        """The layout for what has been logged so far (call after the data)."""
        return episode_blueprint(traced=self.traced or bool(self._nodes.functions),
                                 errors=self._has_errors or self._nodes.has_errors,
                                 line_functions=self._nodes.line_functions)

    def send_blueprint(self) -> None:
        self.rec.send_blueprint(self.blueprint())


def _property_value(value: Any) -> Any:
    """A recording property's value: a number as it is, anything else as plain text (an episode's error quotes the
    policy)."""
    if isinstance(value, (bool, int, float)):
        return value
    return plain_text(value)
