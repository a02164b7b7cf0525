"""Feedback for the optimizer: the paper's staged messages, chosen by score band, plus what happened.

``staged`` feedback (the paper's method) comes from the evaluation score: a message per band (high, medium,
low) naming the score, how far it is from the target, and a hint. ``rollout`` feedback (the paper's
ablation) uses only the return of the short traced training rollout. Either way, notes of what the loop did
are appended: a candidate that was rejected and why, a rollback, a failed LLM call; each note is untrusted text,
capped at 2,000 characters and scrubbed of secrets (``pipeline/boundary/untrusted.py``).
"""

from __future__ import annotations

import math
import reprlib
from dataclasses import dataclass
from typing import Any, Callable

from pipeline.boundary.untrusted import clean_untrusted_text, single_line
from pipeline.optimizer.config import FEEDBACK_MODES  # ``feedback``'s choices, declared there
from store.recorded import unreadable_settings


@dataclass(frozen=True)
class FeedbackBands:
    """Staged feedback: ``score >= high`` is high, ``score <= low`` is low, anything between is medium."""

    high: float
    low: float
    target: float
    messages: dict[str, str]

    def stage(self, score: float) -> str:
        if score >= self.high:
            return "high"
        if score <= self.low:
            return "low"
        return "medium"

    def message(self, score: float) -> tuple[str, str]:
        """(stage, text) for ``score``; message templates may use ``{score}``, ``{target}`` and ``{gap}``."""
        stage = self.stage(score)
        template = self.messages.get(stage) or "Score {score:g} ({gap:g} from the target {target:g})."
        return stage, template.format(score=score, target=self.target, gap=abs(self.target - score))

    @classmethod
    def from_record(cls, value: Any, run_id: str) -> "FeedbackBands":
        """The bands run ``run_id`` recorded (``runs.config``'s ``feedback_bands``, as the loop writes them: exactly
        these fields); a :func:`unreadable_settings` error naming what is wrong (a key too many had ended
        ``--resume`` in a TypeError): a store is anyone's file, and a template the loop cannot fill would end
        the iteration that first writes that band's feedback."""
        def unreadable(problem: str) -> ValueError:
            return unreadable_settings(run_id, f"feedback_bands {problem}")

        if not isinstance(value, dict):
            raise unreadable(f"are {type(value).__name__}, not a JSON object")
        fields = {"high", "low", "target", "messages"}
        if set(value) != fields:
            wrong = sorted(set(value) ^ fields)
            shown = ", ".join(map(reprlib.repr, wrong[:3]))
            raise unreadable(f"must have exactly {', '.join(sorted(fields))}; {shown} "
                             f"{'is' if len(wrong) == 1 else 'are'} not so")  # a key may be any text: cut
        return cls._checked(value, unreadable)

    @classmethod
    def from_constant(cls, value: Any, source: str) -> "FeedbackBands":
        """The bands a policy file's ``FEEDBACK`` (or a game's task) declares: ``high`` and ``low``, optionally
        ``target`` (``high`` when left out) and ``messages``; checked as a recorded one is (:meth:`from_record`), so
        that what cannot be a band stops the command before anything starts, naming the file. A number past a
        float (an int of 401 digits) ended ``optimize`` in an OverflowError's traceback, and a message that is no
        template started the run and then refused it as a store "changed by hand or damaged"."""
        def wrong(problem: str) -> ValueError:
            return ValueError(f"{source}: FEEDBACK {problem}")

        if not isinstance(value, dict) or "high" not in value or "low" not in value:
            raise wrong("must be a dict with numeric 'high' and 'low' (and optional 'target', 'messages')")
        messages = value.get("messages", {})
        if not isinstance(messages, dict):
            raise wrong(f"messages must map each band to a text, not {reprlib.repr(messages)}")
        return cls._checked({"high": value["high"], "low": value["low"], "target": value.get("target", value["high"]),
                             "messages": {str(k): v for k, v in messages.items()}}, wrong)

    @classmethod
    def _checked(cls, value: dict, wrong: Callable[[str], Exception]) -> "FeedbackBands":
        """The bands of ``value`` (``high``, ``low``, ``target``, ``messages``), each checked; ``wrong(problem)``
        is raised for the first that cannot be: a number that is not a finite float, a message that is not text
        or not a template of ``score``, ``target`` and ``gap``."""
        numbers = {}
        for key in ("high", "low", "target"):
            number = value[key]
            if isinstance(number, bool) or not isinstance(number, (int, float)):
                raise wrong(f"{key} must be a finite number, not {reprlib.repr(number)}")
            try:
                numbers[key] = float(number)
            except OverflowError:  # an int past a float's range
                numbers[key] = math.inf
            if not math.isfinite(numbers[key]):
                raise wrong(f"{key} must be a finite number, not {reprlib.repr(number)}")
        messages = value["messages"]
        if not isinstance(messages, dict) or not all(isinstance(t, str) for t in messages.values()):
            raise wrong(f"messages must map each band to a text, not {reprlib.repr(messages)}")
        bands = cls(numbers["high"], numbers["low"], numbers["target"], dict(messages))
        for stage, template in messages.items():
            try:
                template.format(score=bands.low, target=bands.target, gap=abs(bands.target - bands.low))
            except (KeyError, IndexError, ValueError, AttributeError, TypeError) as exc:
                raise wrong(f"message {stage!r} is not a template of score, target and gap "
                            f"({type(exc).__name__}: {reprlib.repr(str(exc))})") from None
        return bands


def compose_feedback(
    mode: str,
    bands: FeedbackBands,
    eval_score: float,
    train_return: float,
    train_steps: int,
    notes: list[str],
    forfeit: str | None = None,
    forfeit_score: float | None = None,
) -> tuple[str, float, str]:
    """(stage, score the stage was chosen by, text) for one iteration. ``forfeit``: what ended an evaluation game
    the policy forfeited (``store/scores.py``; ``eval_score`` is then None and ``forfeit_score`` the mean return
    when it stopped): the stage is ``low`` whatever it had scored, and the text says why."""
    if mode == "staged" and forfeit:
        score = forfeit_score if forfeit_score is not None else 0.0
        stage = "low"
        text = (f"Evaluation (full game): the policy did not play the game to its end: {forfeit}. It had scored "
                f"{score:g} when it stopped, but a forfeited game counts below every game played to its end, "
                f"whatever its score: make the code run without errors and within its time limits first.")
    elif mode == "staged":
        score = eval_score
        stage, text = bands.message(score)
        text = f"Evaluation (full game): {text}"
    elif mode == "rollout":
        score = train_return
        stage = bands.stage(score)
        text = f"Training rollout: the policy scored {score:g} over {train_steps} steps."
        if forfeit:
            text += f" It did not play its evaluation game to the end: {forfeit}."
    else:
        raise ValueError(f"unknown feedback mode '{mode}'; use one of {', '.join(FEEDBACK_MODES)}")
    if notes:  # notes quote rejected code's errors and LLM errors: untrusted text, capped and scrubbed
        # one line each: a note's quoted error cannot begin a line that reads as the prompt's own header
        text += "\n" + "\n".join(single_line(clean_untrusted_text(note)) for note in notes)
    return stage, score, text
