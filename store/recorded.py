"""A run's recorded settings (``runs.config``) read back as untrusted: a store is anyone's file, and its settings
cell may hold anything JSON can (a list where an object goes, a list nested 10,000 deep, which raised
RecursionError in every reader of it) or no JSON at all.

:func:`read_recorded` is the one reading of them, for every layer (``viewers/`` cannot reach
``pipeline/settings.py``, which checks each setting against its declaration after it): a dict, or
:func:`unreadable_settings`, the one error of a run whose settings cannot be read, in one line naming the run.
"""

from __future__ import annotations

import json
from typing import Any

from tracing.bounded import MAX_DEPTH, deeper_than


def shape_problem(recorded: Any) -> str | None:
    """What makes ``recorded`` no settings at all (not a JSON object; nested deeper than any settings are, which a
    reader walking them would follow), or None."""
    if not isinstance(recorded, dict):
        return f"they are {type(recorded).__name__}, not a JSON object"
    if deeper_than(recorded, MAX_DEPTH):
        return f"they are nested more than {MAX_DEPTH} levels deep"
    return None


def read_recorded(text: str | None, run_id: str) -> dict[str, Any]:
    """Run ``run_id``'s recorded settings (``runs.config``: its config, its task's settings, what a replay, a batch
    or ``serve`` added) as a dict; an :func:`unreadable_settings` error when they are no settings
    (:func:`shape_problem`). Each reader checks the settings it uses after it (``pipeline/settings.py``)."""
    try:
        recorded = json.loads(text) if text is not None else None
    except RecursionError:  # the C decoder's own limit: nothing a run records is nested this deep
        raise unreadable_settings(run_id, f"they are nested more than {MAX_DEPTH} levels deep") from None
    except ValueError:
        recorded = text
    problem = shape_problem(recorded)
    if problem is not None:
        raise unreadable_settings(run_id, problem)
    return recorded


def unreadable_settings(run_id: str, problem: str) -> ValueError:
    """The one error of a run whose recorded settings (``runs.config``) cannot be read: ``problem`` says which."""
    return ValueError(f"run {run_id}'s recorded settings cannot be read: {problem} (the store was changed by hand "
                      "or is damaged)")
