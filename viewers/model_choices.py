"""An ensemble's choices of model, as ``codearcade runs`` (one short line: the latest) and ``codearcade report`` (a
table of every choice) show them, from ``llm_calls.model_choice`` (view ``model_choices``, docs/schema.md): the
rule, the budget that bound the run, why the model won, and per model the estimates the rule compared (pulls,
mean reward, cost per pull in the budget's unit, index). The rule itself is ``pipeline/optimizer/bandit.py``."""

from __future__ import annotations

import json
from typing import Any, Sequence

from viewers.safe_text import markdown_cell, terminal_text

UNITS = {"calls": "call", "dollars": "USD", "tokens": "token", "seconds": "s"}
"""The unit of each budget a choice can be counted in."""

WHY = {"index": "largest index", "tie": "cheaper, within 10% of the largest index", "untried": "not tried yet",
       "floor": "below its floor share of the budget", "share": "furthest below its weight's share"}


def parsed(value: Any) -> dict[str, Any] | None:
    """A stored ``model_choice`` (JSON text or already a dict) as a dict; None when absent or unreadable."""
    if value is None or isinstance(value, dict):
        return value
    try:
        found = json.loads(value)
    except (TypeError, ValueError):
        return None
    return found if isinstance(found, dict) else None


def _name(model: object) -> str:
    return terminal_text(str(model)).rsplit("/", 1)[-1]


def _number(value: Any) -> str:
    return "–" if value is None else f"{float(value):.3g}"


def short(choice: Any) -> str | None:
    """The latest choice of a run on one line: ``ucb per call: gpt-4o 0.97 > gpt-4o-mini 0.102``, the winner first
    (a choice by rule other than the index: ``thompson per USD: gpt-4o-mini (floor)``)."""
    choice = parsed(choice)
    if not choice or not choice.get("models"):
        return None
    budget = choice.get("budget")
    head = f"{terminal_text(choice.get('rule'))} per {UNITS.get(budget) or terminal_text(budget)}:"
    if choice.get("why") in ("untried", "floor"):
        return f"{head} {_name(choice.get('model'))} ({choice['why']})"
    models = sorted(choice["models"], key=lambda m: (m.get("model") != choice.get("model"), -(m.get("index") or 0)))
    text = " > ".join(f"{_name(m.get('model'))} {_number(m.get('index'))}" for m in models)
    return f"{head} {text}" + (" (tie: cheaper)" if choice.get("why") == "tie" else "")


def choice_section(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The report's *Model choices* section (Markdown lines) from the ``model_choices`` rows of a run, in order;
    nothing when the run recorded none."""
    rows = [r for r in rows if parsed(r.get("choice"))]
    if not rows:
        return []
    choices = [parsed(r["choice"]) for r in rows]
    models = list(dict.fromkeys(m.get("model") for c in choices for m in c.get("models") or ()))
    header = ["iteration", "candidate", "rule", "budget", "chosen", "why"] + [f"{_name(m)}: pulls, mean reward, cost "
                                                                             "per pull, index" for m in models]
    lines = ["| " + " | ".join(markdown_cell(h) for h in header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for row, choice in zip(rows, choices):
        per = {m.get("model"): m for m in choice.get("models") or ()}
        unit = UNITS.get(choice.get("budget"), "")
        cells = [row.get("iteration"), row.get("candidate"), choice.get("rule"), choice.get("budget"),
                 _name(choice.get("model")), WHY.get(choice.get("why"), choice.get("why"))]
        for model in models:
            m = per.get(model)
            cells.append("" if m is None else
                         f"{_number(m.get('pulls'))}, {_number(m.get('mean_reward'))}, "
                         f"{_number(m.get('cost'))} {unit}, {_number(m.get('index'))}")
        lines.append("| " + " | ".join(markdown_cell("" if c is None else c) for c in cells) + " |")
    last = choices[-1]
    return ["## Model choices", "",
            "Why each call went to its model (`llm_calls.model_choice`, view `model_choices`): the rule, the budget "
            "that bound the run when it chose (its cost per pull is in that budget's unit), and per model its "
            "pulls, its mean reward (the posterior mean of the share of the run's largest improvement a pull "
            "brings), its cost per pull and its index (ucb: the posterior's upper quantile per unit of cost; "
            "thompson: the draw per unit; fixed: how far below its share). See docs/models.md, Ensembles.", "",
            *lines, "",
            f"Latest: {markdown_cell(short(last) or '')}.", ""]
