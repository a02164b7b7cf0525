"""JSON values held to a bound on nesting and size, wherever a node's inputs or output are made or read again.

A node's inputs and output travel as JSON text: made in the policy's process (``tracing/capture.py``'s
``to_json``), checked where the parent receives them (``pipeline/boundary/untrusted.py``'s ``clean_nodes``), and
parsed again wherever they come back from the store (``store/readers.py``'s ``step_nodes``, the viewers, ``codearcade
sql --json``). Policy code controls the value, and may raise its own process's recursion limit, so a list nested
3,000 deep can be written by it; parsed or printed naively, such a value raises ``RecursionError`` in whatever
reads it (the optimizer building its next prompt, ``--resume`` doing the same). Every place holds it to the same
two bounds, and replaces what is over them by a marker that says so, never raising:

- **nesting**: at most :data:`MAX_DEPTH` levels of lists and objects. A deeper part of a value that can be parsed
  becomes the string :data:`TOO_DEEP` (the levels above it are kept); a text nested too deep to parse at all
  becomes ``{"$too_deep": "more than 64 levels", "preview": <its first 200 characters>}``;
- **size**: at most :data:`MAX_CHARS` characters of JSON text; a longer text becomes ``{"$truncated": <its length>,
  "preview": <its first 2,000 characters>}`` (the marker ``to_json`` has always written for a long value);
- a stored text that is not JSON at all (a store edited by hand) becomes ``{"$not_json": <its first 200
  characters>}``.

Nothing here recurses more than :data:`MAX_DEPTH` levels, whatever the value.
"""

from __future__ import annotations

import json
from typing import Any

MAX_DEPTH = 64
"""Levels of nested lists and objects a node value may have (``[]`` is one level, ``[[]]`` two)."""
MAX_CHARS = 20_000
"""Characters of JSON text a node value may have (``to_json`` cuts a longer one; readers mark a longer one)."""
TOO_DEEP = f"(nested deeper than {MAX_DEPTH} levels: cut)"
"""What stands for a list or object that is nested deeper than :data:`MAX_DEPTH`."""
PREVIEW_CHARS = 2_000
"""Characters of a too-long value shown in its ``$truncated`` marker."""
_SHORT_PREVIEW = 200
_NESTED = (dict, list, tuple)


def truncated(text: str) -> dict[str, Any]:
    """The marker of a JSON text longer than allowed: its length and a preview."""
    return {"$truncated": len(text), "preview": text[:PREVIEW_CHARS]}


def deeper_than(value: Any, limit: int = MAX_DEPTH) -> bool:
    """Whether ``value`` nests lists, tuples or dicts more than ``limit`` levels deep (walked level by level,
    without recursion; stops at the first level over the limit)."""
    if not isinstance(value, _NESTED):
        return False
    level, depth = [value], 1
    while depth <= limit:
        level = [v for item in level for v in (item.values() if isinstance(item, dict) else item)
                 if isinstance(v, _NESTED)]
        if not level:
            return False
        depth += 1
    return True


def prune(value: Any, limit: int = MAX_DEPTH) -> Any:
    """``value`` with every list or object below ``limit`` levels replaced by :data:`TOO_DEEP` (recursion stops
    at ``limit``)."""
    if isinstance(value, dict):
        return {k: prune(v, limit - 1) for k, v in value.items()} if limit > 0 else TOO_DEEP
    if isinstance(value, (list, tuple)):
        return [prune(v, limit - 1) for v in value] if limit > 0 else TOO_DEEP
    return value


def load_json(text: str, max_chars: int | None = MAX_CHARS, max_depth: int = MAX_DEPTH) -> Any:
    """A JSON text from outside (a worker, the store) as a value within the bounds (module docstring); never
    raises. ``max_chars=None``: any length (a reader that must show every stored character)."""
    return _load(text, max_chars, max_depth)[0]


def bound_json_text(text: str, max_chars: int = MAX_CHARS, max_depth: int = MAX_DEPTH) -> str:
    """A JSON text within the bounds: ``text`` itself when it is (the usual case; only a text with more than
    ``max_depth`` opening brackets can be too deep, and only such a one is parsed), else the JSON of its marker
    or of the value with its too-deep parts cut."""
    if len(text) <= max_chars and text.count("[") + text.count("{") <= max_depth:
        return text
    value, changed = _load(text, max_chars, max_depth)
    return json.dumps(value, separators=(",", ":")) if changed else text


def _load(text: str, max_chars: int | None, max_depth: int) -> tuple[Any, bool]:
    """(the value within the bounds, whether anything was cut or marked)."""
    if max_chars is not None and len(text) > max_chars:
        return truncated(text), True
    try:
        value = json.loads(text)
    except RecursionError:  # the C decoder's own limit: nested far deeper than max_depth
        return {"$too_deep": f"more than {max_depth} levels", "preview": text[:_SHORT_PREVIEW]}, True
    except (ValueError, TypeError):
        return {"$not_json": text[:_SHORT_PREVIEW]}, True
    if isinstance(value, (dict, list)) and deeper_than(value, max_depth):
        return prune(value, max_depth), True
    return value, False
