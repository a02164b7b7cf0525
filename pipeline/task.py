"""Task settings of an optimization: rollout horizon, evaluation cap, feedback bands and instruction.

A policy file may declare them as upper-case literals (``ROLLOUT_STEPS``, ``EVAL_MAX_STEPS``, ``FEEDBACK``,
``INSTRUCTION``); whatever it leaves out comes from the game's scaffold in ``examples/``, which is the one
place the paper's settings are written down (400/300/15 steps, 4000-step evaluations, staged bands).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from pipeline.feedback import FeedbackBands
from pipeline.games import get_game
from tracing.policy_file import PolicyInfo, inspect_policy

EXAMPLES_DIR = Path(__file__).resolve().parents[1] / "examples"


def example_path(game: str) -> Path:
    """The scaffold policy file of ``game`` (``examples/pong.py``)."""
    return EXAMPLES_DIR / f"{get_game(game).name}.py"


@dataclass(frozen=True)
class TaskSettings:
    game: str
    rollout_steps: int
    eval_max_steps: int
    feedback: FeedbackBands
    instruction: str


def task_settings(info: PolicyInfo, game: str) -> TaskSettings:
    """The settings for optimizing ``info`` on ``game``: the file's constants over the scaffold's."""
    defaults = inspect_policy(example_path(game).read_text(), example_path(game).name).constants
    merged = {**defaults, **info.constants}
    return TaskSettings(
        game=get_game(game).name,
        rollout_steps=int(merged["ROLLOUT_STEPS"]),
        eval_max_steps=int(merged["EVAL_MAX_STEPS"]),
        feedback=FeedbackBands.from_constant(merged["FEEDBACK"], info.name),
        instruction=str(merged["INSTRUCTION"]),
    )
