"""Parsing an LLM reply into suggested method sources.

Two formats are accepted:

1. JSON (what the prompt asks for): ``{"reasoning": ..., "suggestion": {"select_action": "def select_action(...)..."}}``.
   The JSON may be wrapped in a ```json fence or surrounded by prose; keys may also be written in Trace's
   style (``__code:select_action``). An empty suggestion means "no change".
2. Fenced code blocks: each ```python block holding one or more complete ``def``s (or a ``class Policy``
   whose methods are taken).

:func:`parse_reply` returns ``{method name: source}`` or raises :class:`ReplyParseError`, and nothing else,
whatever the text (empty, huge, binary garbage, deeply nested JSON): that is the contract the fuzz tests check.
Whether the names exist and the signatures match is decided later, by validation.
"""

from __future__ import annotations

import ast
import json
import re
import textwrap

MAX_REPLY_CHARS = 1_000_000
_FENCE = re.compile(r"```[ \t]*([A-Za-z0-9_+-]*)[^\n]*\n(.*?)(?:```|\Z)", re.DOTALL)
_KEY_PREFIXES = ("__code:", "code:", "__code_", "__")


class ReplyParseError(ValueError):
    """The reply holds no usable suggestion; the message says why (it becomes feedback), cleaned as untrusted
    text (``pipeline/boundary/untrusted.py``): it may quote the reply."""

    def __init__(self, reason: object):
        from pipeline.boundary.untrusted import clean_untrusted_text

        super().__init__(clean_untrusted_text(reason))


def clean_text(text: str) -> str:
    """Text safe to store: lone surrogates and NULs replaced (a reply may be arbitrary bytes)."""
    return text.encode("utf-8", "replace").decode("utf-8").replace("\x00", "\ufffd")


def _method_name(key: str) -> str:
    for prefix in _KEY_PREFIXES:
        if key.startswith(prefix):
            return key[len(prefix):]
    return key


def _json_candidates(text: str) -> list[str]:
    candidates = [text.strip()]
    for lang, body in _FENCE.findall(text):
        if lang.lower() in ("json", ""):
            candidates.append(body.strip())
    start, end = text.find("{"), text.rfind("}")
    if 0 <= start < end:
        candidates.append(text[start : end + 1])
    return candidates


def _from_json(text: str) -> dict[str, str] | None:
    for candidate in _json_candidates(text):
        if not candidate.startswith("{"):
            continue
        try:
            data = json.loads(candidate)
        except (ValueError, RecursionError):
            continue
        if not isinstance(data, dict):
            continue
        suggestion = data.get("suggestion", data.get("suggestions"))
        if suggestion is None:
            continue
        if not isinstance(suggestion, dict):
            raise ReplyParseError("the JSON reply's 'suggestion' must be an object mapping method names to code")
        parsed: dict[str, str] = {}
        for key, value in suggestion.items():
            if not isinstance(value, str):
                raise ReplyParseError(f"the suggestion for '{key}' must be a string of Python code, "
                                      f"not {type(value).__name__}")
            parsed[_method_name(str(key))] = textwrap.dedent(value).strip("\n") + "\n"
        return parsed
    return None


def _from_code_blocks(text: str) -> dict[str, str] | None:
    blocks = [body for lang, body in _FENCE.findall(text) if lang.lower() in ("python", "py", "python3", "")]
    if not blocks:
        return None
    parsed: dict[str, str] = {}
    errors = []
    for body in blocks:
        body = textwrap.dedent(body)
        try:
            tree = ast.parse(body)
        except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
            errors.append(f"a code block does not parse ({type(exc).__name__}: {getattr(exc, 'msg', exc)})")
            continue
        lines = body.splitlines(True)
        nodes = []
        for node in tree.body:
            if isinstance(node, ast.FunctionDef):
                nodes.append(node)
            elif isinstance(node, ast.ClassDef):
                nodes.extend(n for n in node.body if isinstance(n, ast.FunctionDef))
        for node in nodes:
            source = textwrap.dedent("".join(lines[node.lineno - 1 : node.end_lineno]))
            parsed[node.name] = source.strip("\n") + "\n"
    if parsed:
        return parsed
    if errors:
        raise ReplyParseError(errors[0])
    raise ReplyParseError("the reply's code blocks define no function")


def parse_reply(text: str) -> dict[str, str]:
    """``{method name: new source}`` from a reply, or :class:`ReplyParseError` (see the module docstring)."""
    if not isinstance(text, str):
        raise ReplyParseError(f"the reply is not text but {type(text).__name__}")
    if not text.strip():
        raise ReplyParseError("the reply is empty")
    if len(text) > MAX_REPLY_CHARS:
        raise ReplyParseError(f"the reply is {len(text):,} characters long, over the {MAX_REPLY_CHARS:,} limit")
    try:
        parsed = _from_json(text)
        if parsed is None:
            parsed = _from_code_blocks(text)
    except ReplyParseError:
        raise
    except (ValueError, TypeError, RecursionError, MemoryError) as exc:  # pathological input: still our error
        raise ReplyParseError(f"the reply could not be parsed ({type(exc).__name__})") from None
    if parsed is None:
        raise ReplyParseError("the reply contains neither a JSON suggestion nor a fenced ```python code block")
    return parsed
