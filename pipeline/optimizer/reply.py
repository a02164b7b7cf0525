"""Reading an LLM reply into suggested method sources, and saying how it was read.

The prompt asks for JSON only: ``{"reasoning": ..., "suggestion": {"select_action": "def select_action(...)..."}}``
(an empty suggestion means "no change"; a method given as ``null`` is unchanged), or, failing that, each changed
method as a complete ``def`` in a ```python fenced block (or a ``class Policy`` whose methods are taken). Where
the provider can be held to a schema (``pipeline/llm/providers.py``), the reply is that JSON object.

Models get the format slightly wrong, and such a reply still counts when what it means is unambiguous. The
near-misses recovered here are the ones models were seen to send (7 of the 20 replies of the authors' logged Pong
run nest the whole answer one level down under a key the model invented: ``{"json": {"reasoning": ...,
"suggestion": {...}}}``, likewise ``payload``, ``json_payload``, ``params``, ``value``); each recovery is named
in :attr:`Reading.repairs`:

- the JSON inside a code fence, or with prose before or after it;
- the answer nested under an invented key (looked for at most :data:`MAX_NESTING` levels down);
- a trailing comma before ``}`` or ``]``; a closing brace too many; closing braces missing at the end (but never
  a string cut off in the middle: that is a truncated reply, refused);
- raw line breaks inside JSON strings; a Python dict literal (single quotes, ``True``/``None``) instead of JSON;
- Trace's variable names as keys (``__code4``): the method's name is taken from its ``def``;
- the suggestion given as one string of code, or code with no fence at all.

:func:`read_reply` returns a :class:`Reading` (the suggestion and how it was read: ``structured``, ``parsed`` or
``repaired``) or raises :class:`ReplyParseError` (the reply is ``unusable``; its one-line message says why and
becomes feedback), and nothing else, whatever the text (empty, huge, binary garbage, deeply nested JSON): that
is the contract the fuzz tests check. Whether the names exist and the signatures match is decided later, by
validation.
"""

from __future__ import annotations

import ast
import json
import re
import textwrap
from dataclasses import dataclass
from itertools import islice

from tracing.policy_file import MAX_POLICY_CHARS

MAX_REPLY_CHARS = 1_000_000
MAX_NESTING = 3
"""How many levels below the top an answer nested under invented keys is looked for."""
MAX_OBJECT_STARTS = 8
"""How many places in the prose of a reply that look like the start of a JSON object (``{"``) are tried."""
REPAIR_MAX_CHARS = 200_000
"""Longer JSON candidates are only decoded as they are: the text repairs walk the text in Python."""

READINGS = ("structured", "parsed", "repaired", "unusable")
"""How a reply was read (``llm_calls.reply_reading``): ``structured``, the JSON object a provider held to the
reply schema, as is; ``parsed``, a reply in a format the prompt asks for, as is (the whole reply is the JSON, or
```python blocks); ``repaired``, read only after recovering a near-miss (:attr:`Reading.repairs` says which);
``unusable``, nothing could be read (``llm_calls.parse_error`` says why)."""

_FENCE = re.compile(r"```[ \t]*+([A-Za-z0-9_+-]*+)[^\n`]*+\n(.*?)(?:```|\Z)", re.DOTALL)
"""A fenced code block: its language and its body (to the closing fence, or the end of a reply cut off). Nothing is
given back once taken and an info string holds no backtick (CommonMark's rule), so each fence costs the length of
its own line: with ``[^\n]*`` a line of 999,000 backticks took each fence to the end of the line, 12 minutes."""
_KEY_PREFIXES = ("__code:", "code:", "__code_", "__")
_TRACE_VARIABLE = re.compile(r"code\d*")
_TRAILING_COMMA = re.compile(r",(\s*[}\]])")
_OBJECT_START = re.compile(r"\{\s*[\"']")
_PYTHON_FENCES = ("python", "py", "python3", "")


CUT_OFF_ADVICE = "raise --max-tokens"
"""What the person who runs it can do about a reply cut off at the token limit: said in the stored reason and the
log, never to the model, which cannot raise it (``pipeline/optimizer/propose.py`` tells it to write less)."""


class ReplyParseError(ValueError):
    """The reply holds no usable suggestion; the message says why (the stored reason), cleaned as untrusted
    text (``pipeline/boundary/untrusted.py``): it may quote the reply. ``reason`` is the same without the advice
    for a person that a reply cut off at the token limit (``cut_off``) adds: what the model is told."""

    def __init__(self, reason: object, cut_off: bool = False):
        from pipeline.boundary.untrusted import clean_untrusted_text

        self.reason, self.cut_off = clean_untrusted_text(reason), cut_off
        super().__init__(f"{self.reason} ({CUT_OFF_ADVICE})" if cut_off else self.reason)


@dataclass(frozen=True)
class Reading:
    """What a reply was read as."""

    suggestion: dict[str, str]
    """``{method name: new source}``; empty: no change."""
    how: str
    """``structured``, ``parsed`` or ``repaired`` (see :data:`READINGS`)."""
    repairs: tuple[str, ...] = ()
    """The near-misses recovered, in words (``the answer nested under 'json'``); empty unless ``repaired``."""


def clean_text(text: str) -> str:
    """Text safe to store: lone surrogates and NULs replaced (a reply may be arbitrary bytes)."""
    return text.encode("utf-8", "replace").decode("utf-8").replace("\x00", "\ufffd")


# --- JSON: where it is, and the text repairs --------------------------------------------------------------


def _json_candidates(text: str) -> list[tuple[str, tuple[str, ...]]]:
    """Pieces of ``text`` that may be the JSON answer, each with what taking it repairs: the whole text, each
    ```json (or unlabelled) fence, and the text from the first ``{`` on (prose around it)."""
    stripped = text.strip()
    candidates = [(stripped, ())]
    for lang, body in _FENCE.findall(text):
        if lang.lower() in ("json", "") and body.strip().startswith("{"):
            candidates.append((body.strip(), ("a code fence around the JSON",)))
    first = len(text) - len(text.lstrip())  # where the whole text's candidate starts
    starts = (m.start() for m in _OBJECT_START.finditer(text) if m.start() > first)
    candidates += [(text[start:].strip(), ("prose around the JSON",)) for start in islice(starts, MAX_OBJECT_STARTS)]
    return candidates


_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*(?P<closed>")?', re.DOTALL)
"""A JSON string from its opening quote: to its closing quote, or to the end of a text cut off inside it."""


def _outside_strings(text: str) -> tuple[list[tuple[int, int]], bool]:
    """The (start, end) of each stretch of ``text`` outside JSON strings, in order, and whether ``text`` ends inside
    a string. Outside a string every quote opens one, so one scan of the quotes finds them all."""
    spans, pos, in_string = [], 0, False
    for match in _JSON_STRING.finditer(text):
        spans.append((pos, match.start()))
        pos, in_string = match.end(), match["closed"] is None
    spans.append((pos, len(text)))
    return spans, in_string


def _string_state_at_end(text: str) -> tuple[bool, list[str]]:
    """Whether ``text`` ends inside a JSON string, and the brackets still open at its end (in order)."""
    spans, in_string = _outside_strings(text)
    stack: list[str] = []
    for start, stop in spans:
        for char in text[start:stop]:
            if char in "{[":
                stack.append(char)
            elif char in "}]" and stack:
                stack.pop()
    return in_string, stack


def _without_trailing_commas(text: str) -> str:
    """``text`` with each comma that directly precedes ``}`` or ``]`` outside a string removed."""
    spans, _ = _outside_strings(text)
    out: list[str] = []
    for (start, stop), (next_start, _) in zip(spans, spans[1:] + [(len(text), len(text))]):
        out.append(_TRAILING_COMMA.sub(r"\1", text[start:stop]))
        out.append(text[stop:next_start])  # the string after this stretch, as it is
    return "".join(out)


def _repaired_texts(candidate: str):
    """``candidate`` as is, then (computed only when asked for) without trailing commas, then with the closing
    brackets it lacks at its end (unless it ends inside a string: a reply cut off mid-string stays refused);
    each with the repairs it took."""
    yield candidate, ()
    if len(candidate) > REPAIR_MAX_CHARS:
        return
    uncommaed, repairs = candidate, ()
    if _TRAILING_COMMA.search(candidate):
        uncommaed = _without_trailing_commas(candidate)
        if uncommaed != candidate:
            repairs = ("a trailing comma",)
            yield uncommaed, repairs
    in_string, still_open = _string_state_at_end(uncommaed)
    if still_open and not in_string:
        closers = "".join("}" if b == "{" else "]" for b in reversed(still_open))
        yield _without_trailing_commas(uncommaed.rstrip().rstrip(",") + closers), \
            repairs + ("closing braces missing at the end",)


def _decode(candidate: str) -> tuple[object, tuple[str, ...]] | None:
    """The JSON value ``candidate`` starts with and the repairs it needed, or None. Tried in order: as is; with
    raw line breaks inside strings; then the same for each of :func:`_repaired_texts`; last, as a Python
    literal. Text after the value (a closing brace too many, prose) is left out."""
    if not candidate.startswith("{"):
        return None
    for text, repairs in _repaired_texts(candidate):
        for strict, lax in ((True, ()), (False, ("raw line breaks inside a JSON string",))):
            try:
                value, end = json.JSONDecoder(strict=strict).raw_decode(text)
            except (ValueError, RecursionError):
                continue
            after = text[end:].strip()
            extra = ()
            if after:
                extra = ("a closing brace too many",) if set(after) <= set("}]") else ("text after the JSON",)
            return value, repairs + lax + extra
    if len(candidate) > REPAIR_MAX_CHARS:
        return None
    try:
        value = ast.literal_eval(candidate)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return None
    return value, ("a Python dict instead of JSON",)


# --- the suggestion inside the JSON -----------------------------------------------------------------------


def _find_suggestion(data: object) -> tuple[object, tuple[str, ...]] | None:
    """The ``suggestion`` of the answer object (top level, or nested under invented keys at most
    :data:`MAX_NESTING` levels down, breadth first) and the repair its place needed; None if there is none."""
    if not isinstance(data, dict):
        return None
    level: list[tuple[dict, tuple[str, ...]]] = [(data, ())]
    for _ in range(MAX_NESTING + 1):
        below: list[tuple[dict, tuple[str, ...]]] = []
        for node, path in level:
            for key in ("suggestion", "suggestions"):
                if key in node:
                    nested = ("the answer nested under " + " > ".join(f"'{p}'" for p in path),) if path else ()
                    return node[key], nested
            below += [(value, path + (str(key)[:40],)) for key, value in node.items() if isinstance(value, dict)]
        level = below
    return None


def _method_name(key: str) -> str:
    for prefix in _KEY_PREFIXES:
        if key.startswith(prefix):
            return key[len(prefix):]
    return key


def _parsed(code: str) -> tuple[ast.Module | None, str | None]:
    """``ast.parse`` of code from a reply (this process parses it: see :data:`MAX_POLICY_CHARS`): its tree, or None
    and why it does not parse. A piece longer than a policy may be is refused unparsed (:class:`ReplyParseError`)."""
    if len(code) > MAX_POLICY_CHARS:
        raise ReplyParseError(f"the reply's code is {len(code):,} characters long, more than a whole policy may hold "
                              f"({MAX_POLICY_CHARS:,})")
    try:
        return ast.parse(code), None
    except (SyntaxError, ValueError, RecursionError, MemoryError) as exc:
        return None, f"{type(exc).__name__}: {getattr(exc, 'msg', exc)}"


def _def_name(source: str) -> str | None:
    """The name of the one function ``source`` defines (dedented), or None."""
    tree, _ = _parsed(textwrap.dedent(source))
    if tree is None:
        match = re.match(r"\s*(?:async\s+)?def\s+([A-Za-z_]\w*)\s*\(", source)
        return match.group(1) if match else None
    defs = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    return defs[0].name if len(defs) == 1 else None


def _from_suggestion(suggestion: object) -> tuple[dict[str, str], tuple[str, ...]]:
    """``{method name: source}`` from the JSON suggestion, and its repairs; :class:`ReplyParseError` if it is
    not an object of code strings."""
    if isinstance(suggestion, str):
        methods = _defs_in_code(suggestion)
        if methods:
            return methods, ("the suggestion given as one string of code",)
    if not isinstance(suggestion, dict):
        raise ReplyParseError("the JSON reply's 'suggestion' must be an object mapping method names to code")
    parsed: dict[str, str] = {}
    repairs: tuple[str, ...] = ()
    for key, value in suggestion.items():
        if value is None:  # a method the reply leaves as it is (a schema that lists every method allows null)
            continue
        if not isinstance(value, str):
            raise ReplyParseError(f"the suggestion for '{key}' must be a string of Python code, "
                                  f"not {type(value).__name__}")
        name = _method_name(str(key))
        if _TRACE_VARIABLE.fullmatch(name):  # Trace's parameter name (__code4): the def names the method
            defined = _def_name(value)
            if defined is not None:
                name = defined
                repairs = ("Trace's variable names as keys",)
        parsed[name] = textwrap.dedent(value).strip("\n") + "\n"
    return parsed, repairs


def _from_json(text: str) -> tuple[dict[str, str], tuple[str, ...]] | None:
    """The suggestion of the first JSON answer found in ``text``, with every repair it took; None if no piece
    of the text decodes to an object with a suggestion."""
    for candidate, where in _json_candidates(text):
        decoded = _decode(candidate)
        if decoded is None:
            continue
        data, text_repairs = decoded
        found = _find_suggestion(data)
        if found is None:
            continue
        suggestion, place = found
        parsed, key_repairs = _from_suggestion(suggestion)
        if where:  # prose around the JSON already says there is text after it
            text_repairs = tuple(r for r in text_repairs if r != "text after the JSON")
        return parsed, where + text_repairs + place + key_repairs
    return None


# --- code ---------------------------------------------------------------------------------------------------


def _defs_in_code(code: str, tree: ast.Module | None = None) -> dict[str, str] | None:
    """Each function ``code`` (dedented, or parsed already as ``tree``) defines at its top level or in a class, by
    name; None if it does not parse or defines none."""
    if tree is None:
        code = textwrap.dedent(code)
        tree, _ = _parsed(code)
        if tree is None:
            return None
    lines = code.splitlines(True)
    nodes = []
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            nodes.append(node)
        elif isinstance(node, ast.ClassDef):
            nodes.extend(n for n in node.body if isinstance(n, ast.FunctionDef))
    parsed = {}
    for node in nodes:
        source = textwrap.dedent("".join(lines[node.lineno - 1 : node.end_lineno]))
        parsed[node.name] = source.strip("\n") + "\n"
    return parsed or None


def _from_code_blocks(text: str) -> dict[str, str] | None:
    blocks = [body for lang, body in _FENCE.findall(text) if lang.lower() in _PYTHON_FENCES]
    if not blocks:
        return None
    parsed: dict[str, str] = {}
    errors = []
    for body in blocks:
        body = textwrap.dedent(body)
        tree, error = _parsed(body)
        if tree is None:
            errors.append(f"a code block does not parse ({error})")
            continue
        parsed.update(_defs_in_code(body, tree) or {})
    if parsed:
        return parsed
    if errors:
        raise ReplyParseError(errors[0])
    raise ReplyParseError("the reply's code blocks define no function")


def _from_bare_code(text: str) -> dict[str, str] | None:
    """The functions of unfenced code: from the first line that starts a ``def`` (or ``class``) to the last
    indented line after it (prose after the code is left out)."""
    match = re.search(r"^[ \t]*(?:def|class)\s+[A-Za-z_]\w*\s*[(:]", text, re.MULTILINE)
    if match is None:
        return None
    lines = text[match.start():].splitlines(True)
    last = max((i for i, line in enumerate(lines) if line[:1] in (" ", "\t") and line.strip()), default=0)
    return _defs_in_code("".join(lines[: last + 1]))


# --- the entry points ---------------------------------------------------------------------------------------


def read_reply(text: str, structured: bool = False, cut_off: bool = False) -> Reading:
    """How ``text`` reads (see the module docstring), or :class:`ReplyParseError`. ``structured``: the request
    held the provider to the reply schema; ``cut_off``: the reply stopped at the token limit (named in the
    reason when it is unusable). What a reply reads as depends on its text alone (the two flags change only the
    label and the reason), so a resumed or replayed run, which has only the stored text, reads it the same."""
    if not isinstance(text, str):
        raise ReplyParseError(f"the reply is not text but {type(text).__name__}")
    if not text.strip():
        raise ReplyParseError("the reply is empty" + (": it stopped at the token limit" if cut_off else ""), cut_off)
    if len(text) > MAX_REPLY_CHARS:
        raise ReplyParseError(f"the reply is {len(text):,} characters long, over the {MAX_REPLY_CHARS:,} limit")
    try:
        found = _from_json(text)
        if found is not None:
            parsed, repairs = found
            if repairs:
                return Reading(parsed, "repaired", repairs)
            return Reading(parsed, "structured" if structured else "parsed")
        parsed = _from_code_blocks(text)  # a block that does not parse is refused, never cut down to what parses
        if parsed is not None:
            return Reading(parsed, "parsed")
        parsed = _from_bare_code(text)
        if parsed is not None:
            return Reading(parsed, "repaired", ("code without a fence",))
    except ReplyParseError as exc:
        if cut_off:
            raise ReplyParseError(f"{exc.reason}; the reply stopped at the token limit", cut_off=True) from None
        raise
    except (ValueError, TypeError, RecursionError, MemoryError) as exc:  # pathological input: still our error
        raise ReplyParseError(f"the reply could not be parsed ({type(exc).__name__})") from None
    if cut_off:
        raise ReplyParseError("the reply stopped at the token limit before its answer was complete", cut_off=True)
    if text.lstrip().startswith("{"):
        in_string, _ = _string_state_at_end(text)
        if in_string:
            raise ReplyParseError("the JSON reply ends inside a string: it was cut off")
        raise ReplyParseError("the JSON reply holds neither a 'suggestion' object nor a ```python code block")
    raise ReplyParseError("the reply contains neither a JSON suggestion nor a fenced ```python code block")


def parse_reply(text: str) -> dict[str, str]:
    """``{method name: new source}`` from a reply, or :class:`ReplyParseError` (see the module docstring)."""
    return read_reply(text).suggestion
