"""Task settings of an optimization: rollout horizon, evaluation cap, feedback bands and instruction.

The game's module holds them (``games/<game>.py``: the paper's 400/300/15 steps, 4000-step evaluations,
staged bands); a policy file may override any of them with an upper-case literal (``ROLLOUT_STEPS``,
``EVAL_MAX_STEPS``, ``FEEDBACK``, ``INSTRUCTION``), the step caps within the ranges of their flags.
"""

from __future__ import annotations

import reprlib
from dataclasses import dataclass
from pathlib import Path

from games import get_game
from games.base import one_life_setting
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.feedback import FeedbackBands
from pipeline.settings import check_value
from tracing.policy_file import PolicyInfo, read_policy_file


def example_path(game: str) -> Path:
    """The scaffold policy file of ``game`` (``games/scaffolds/pong.py``); ValueError for a generic game."""
    spec = get_game(game)
    if spec.scaffold is None:
        raise ValueError(f"{spec.name} is played generically and has no scaffold: write one with "
                         f"`codearcade new my_policy.py --game {spec.name}` and start from it")
    return spec.scaffold


@dataclass(frozen=True)
class TaskSettings:
    game: str
    rollout_steps: int
    eval_max_steps: int
    feedback: FeedbackBands
    instruction: str


def task_settings(info: PolicyInfo, game: str) -> TaskSettings:
    """The settings for optimizing ``info`` on ``game``: the file's constants over the game's task, the step caps
    held to the ranges of ``--rollout-steps`` and ``--eval-max-steps`` (ValueError in one line naming the file)."""
    spec = get_game(game)
    task = spec.task
    merged = {"ROLLOUT_STEPS": task.rollout_steps, "EVAL_MAX_STEPS": task.eval_max_steps,
              "FEEDBACK": dict(task.feedback), "INSTRUCTION": task.instruction, **info.constants}
    steps = {}
    for name, constant in (("rollout_steps", "ROLLOUT_STEPS"), ("eval_max_steps", "EVAL_MAX_STEPS")):
        # a file's ROLLOUT_STEPS = 4611686018427387904 played its whole game and ended in a DuckDB conversion error
        # (a traceback) when the episode was stored, as the flag had; = 1e999 ended in an OverflowError's, = None
        # in a TypeError's, and = 3.7 was taken as 3: the flag's type and range, in one line naming the file
        label = f"{info.name}: {constant}"
        if merged[constant] is None:  # the flag's own None is "the game's", which a file's None is not
            raise ValueError(f"{label} must be a whole number, not None")
        check_value(OptimizeConfig, name, merged[constant], label=label)
        steps[name] = merged[constant]
    instruction = merged["INSTRUCTION"]
    if not isinstance(instruction, str):  # INSTRUCTION = None was sent to the model as the text "None"
        raise ValueError(f"{info.name}: INSTRUCTION must be a text, not {reprlib.repr(instruction)}")
    return TaskSettings(
        game=spec.name,
        rollout_steps=steps["rollout_steps"],
        eval_max_steps=steps["eval_max_steps"],
        feedback=FeedbackBands.from_constant(merged["FEEDBACK"], info.name),
        instruction=instruction,
    )


RECORDED_TASK = {"instruction": str, "rollout_steps": int, "eval_max_steps": int}
"""The task settings a run records beside its config (``runs.config``), each of the type its readers take."""


def recorded_task_problem(recorded: dict, keys: tuple[str, ...] = tuple(RECORDED_TASK)) -> str | None:
    """What makes the task settings ``keys`` of a stored run's ``recorded`` settings not what a run records (a
    store is anyone's file: an instruction that is an object went to the agent and the prompt as it was), or None.
    The numbers' ranges are checked with the config's (``OptimizeConfig.from_record``)."""
    for key in keys:
        kind, value = RECORDED_TASK[key], recorded.get(key)
        if not isinstance(value, kind) or isinstance(value, bool):
            return f"{key} must be {'a text' if kind is str else 'a whole number'}, not {reprlib.repr(value)}"
    return None


def resolve_start(config: OptimizeConfig) -> tuple[PolicyInfo, str]:
    """The starting policy and the game, with one-line errors for bad input."""
    from pipeline.play.validate import checked_inspect, resolve_game  # the confined workers: only when asked

    if config.policy is None:
        if config.game is None:
            raise ValueError("give a policy file or --game (`codearcade games` lists them)")
        path = example_path(config.game)
    else:
        path = Path(config.policy)
    info = checked_inspect(read_policy_file(path), path.name, workers=config.workers)  # parsed confined first
    game = resolve_game(info.game, config.game, path.name)
    get_game(game).check_one_life(one_life_setting(config.one_life))
    if not info.trainable:
        raise ValueError(f"{path.name}: Policy has no trainable methods; mark some with @trace.bundle(trainable=True)")
    return info, game
