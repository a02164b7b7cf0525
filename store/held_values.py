"""How a reader holds a stored node value it shows only the start of: pure text handling, no SQL.

A policy's traced values can be any JSON its process wrote (``tracing/capture.py``), up to ``tracing/bounded.py``'s
limits. A reader that shows ``chars`` characters of each (the optimizer's prompt) keeps a few bytes per character
shown, whatever was stored: :func:`bounded_value` decodes short values and keeps a :class:`JsonHead` of the rest,
and :func:`held_bytes` is the upper estimate of what such rows hold, which ``store.readers.step_nodes`` stops at.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from json.decoder import scanstring
from typing import Any

from tracing.bounded import MAX_CHARS, PREVIEW_CHARS, load_json


@dataclass(frozen=True)
class JsonHead:
    """A stored JSON value a reader did not decode: the first characters of its text (``text``, at most what the
    reader shows) and the whole text's ``length`` in characters. A value the policy's process wrote is compact
    JSON (``tracing/capture.py``'s ``to_json``), so ``text`` is the start of what ``json.dumps(value,
    separators=(",", ":"))`` would print."""

    text: str
    length: int


MAX_KEYS = 32
"""Keys of an object of inputs a bounded reader splits (a method's parameters); one with more comes back as a
:class:`JsonHead` of the whole object."""
HEAD_VALUES = 8
"""Values of an object of inputs a bounded reader keeps a head of (each ``value_chars`` long) before it keeps one
head of the whole object instead."""
SMALL = 32
"""Characters of a list or object a bounded reader decodes (``{"$ref":"obs"}``, which the prompt shows as ``obs``),
two of them a row at most; a longer one is a :class:`JsonHead`."""
_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"')
_SCALAR = re.compile(r"[^,}\s]+")
_DECODER = json.JSONDecoder()
_SPACE = re.compile(r"[ \t\n\r]*")
_MARKER = re.compile(r'\{"\$truncated": \d+, "preview": "[^"\\]*(?:\\.[^"\\]*)*"\}')
"""The marker ``to_json`` writes for a value too long to store (``json.dumps`` with its default separators, the
one stored text that is not compact): an int and a string, decoded at the cost of their text."""


def bounded_value(text: str | None, length: int | None, chars: int, split: bool = False) -> Any:
    """A stored node value as a reader that shows ``chars`` characters of it holds it, in a few bytes per character
    stored whatever the value: a number, string or literal of at most ``chars`` characters decoded; a list or
    object as a :class:`JsonHead` of its first ``chars`` characters, unless it is tiny (:data:`SMALL`, such as
    ``{"$ref":"obs"}``) and decoded (a decoded container costs up to ~24 bytes a character: an empty dict for
    ``{},``); the ``$truncated`` marker of ``tracing/bounded.py`` (from a preview) for a text longer than
    :data:`MAX_CHARS`. With ``split`` an object (a call's inputs, shown key by key) comes back as a dict of its
    keys' values held the same way (at most :data:`MAX_KEYS` keys and :data:`HEAD_VALUES` values' worth of heads;
    else one head of the whole). ``length``: the whole text's (``text`` may be its start)."""
    if text is None:
        return None
    if length is None:
        length = len(text)
    if length > MAX_CHARS:
        return {"$truncated": length, "preview": text[:PREVIEW_CHARS]}
    whole = len(text) == length
    if whole and _MARKER.fullmatch(text):
        return load_json(text)
    if split and whole:
        items = _object_items(text, chars)
        if items is not None:
            return items
    return _held(text, length, chars, [2 * SMALL])


def _held(text: str, length: int, chars: int, small: list[int]) -> Any:
    """:func:`bounded_value` of one value; ``small``: the characters of tiny containers the row may still decode."""
    if text[_SPACE.match(text).end():][:1] in ("[", "{"):
        if length <= SMALL and len(text) == length and length <= small[0]:
            small[0] -= length
            return load_json(text)
    elif length <= chars and len(text) == length:
        return load_json(text)
    return JsonHead(text[:chars], length)


def _object_items(text: str, chars: int) -> dict[str, Any] | None:
    """``text`` (a JSON object) as a dict of its keys' values, each held by :func:`_held`; None when it is not an
    object, or has more than :data:`MAX_KEYS` keys or :data:`HEAD_VALUES` x ``chars`` characters of heads."""
    pos = _SPACE.match(text).end()
    if not text.startswith("{", pos):
        return None
    items: dict[str, Any] = {}
    small, heads = [2 * SMALL], HEAD_VALUES * chars
    pos = _SPACE.match(text, pos + 1).end()
    if text.startswith("}", pos):
        return items
    try:
        while True:
            if len(items) >= MAX_KEYS or not text.startswith('"', pos):
                return None
            key, pos = scanstring(text, pos + 1)
            pos = _SPACE.match(text, pos).end()
            if not text.startswith(":", pos):
                return None
            begin = _SPACE.match(text, pos + 1).end()
            end = _value_end(text, begin)
            if end is None:
                return None
            span = text[begin:end].rstrip(" \t\n\r")
            value = items[key] = _held(span, len(span), chars, small)
            if isinstance(value, JsonHead):
                heads -= len(value.text)
                if heads < 0:
                    return None
            if text[end] == "}":
                return items
            pos = _SPACE.match(text, end + 1).end()
    except ValueError:  # a key that is not a JSON string: a store edited by hand
        return None


def _value_end(text: str, pos: int) -> int | None:
    """Where the JSON value that starts at ``pos`` (inside an object) ends: the index of the ``,`` or ``}`` after
    it; None for a text that is not JSON there. A list or object is found by the C decoder (one value of at most
    :data:`MAX_CHARS` characters, let go at once: only its extent is kept); a string by one regular expression."""
    if text.startswith(("[", "{"), pos):
        try:
            end = _DECODER.raw_decode(text, pos)[1]
        except (ValueError, RecursionError):
            return None
    else:
        match = (_STRING if text.startswith('"', pos) else _SCALAR).match(text, pos)
        if match is None:
            return None
        end = match.end()
    end = _SPACE.match(text, end).end()
    return end if text.startswith((",", "}"), end) else None


_ROW_BYTES = 800
"""What a bounded node row holds beside its values' text: its dict, step, call index, function."""


def held_bytes(rows: list[dict[str, Any]]) -> int:
    """An upper estimate of the bytes of Python objects bounded node rows (:func:`step_nodes` with
    ``value_chars``) hold: 4 bytes a character of text (astral text), ~800 bytes a decoded tiny container."""
    total = 0
    for row in rows:
        total += _ROW_BYTES + sum(4 * len(row[k] or "") for k in ("function", "exc_type", "exc_message", "exc_source"))
        for value in (row["inputs"], row["output"]):
            items = value.items() if isinstance(value, dict) and not _is_marker(value) else [(None, value)]
            for key, item in items:
                total += (4 * len(key) + 100 if key is not None else 0) + _value_bytes(item)
    return total


def _is_marker(value: dict) -> bool:
    return "$truncated" in value


def _value_bytes(value: Any) -> int:
    if isinstance(value, JsonHead):
        return 100 + 4 * len(value.text)
    if isinstance(value, str):
        return 50 + 4 * len(value)
    if isinstance(value, dict) and _is_marker(value):
        return 200 + 4 * len(str(value.get("preview", "")))
    if isinstance(value, (dict, list)):
        return 24 * SMALL
    return 32
