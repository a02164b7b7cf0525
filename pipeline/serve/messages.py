"""What an agent's message may make ``codearcade serve`` build when it is parsed, counted before it is.

A JSON parse holds a Python object for every value, and a value can take two bytes to write (``{},`` is a dict,
``1,`` a list slot): bytes alone do not bound it. The MCP SDK parses a whole message (a stdio line of up to 4 MiB,
a ``--mcp-port`` body of up to 4 MiB) into Python objects and then validates it into its models: 3.5 MB of
``[{},{},...]`` in a request's arguments held ``serve --mcp`` at +175 MB, in a notification's params at +281 MB,
and an ``initialize`` request's params are kept with its session, so 16 sessions opened over ``--mcp-port`` with
such params held 1.36 GB for their idle timeout. An honest message holds a few dozen values: its long parts are
strings (the policy's text, a query), each one value however long. So each message's values are counted first
(:func:`json_values`), outside its strings, and a message with more than :data:`MAX_MESSAGE_VALUES` is refused
unparsed; so is one with a number longer than :data:`MAX_NUMBER_CHARS` (:func:`json_long_number`).
"""

from __future__ import annotations

import functools
import re
from typing import Iterator

MAX_MESSAGE_VALUES = 10_000
"""Values (strings, and the ``{``, ``[`` and ``,`` outside strings) one agent's message may hold: an honest one holds
a few dozen (a submission's instances are at most a few dozen ids). At ~200 bytes of Python objects a value, a
message past it would cost the server more than ~2 MB, however few bytes it took."""

MAX_NUMBER_CHARS = 100
"""Characters of one number (outside strings) an agent's message may hold: an honest message's numbers are ids and
counts, a few dozen characters at most. A parse's cost grows faster than a long number's digits (an int's, up to
Python's 4,300: a 4 MiB message of them took ~0.1 s to parse, of one 4 MiB float ~0.01 s, of a 4 MiB string
~0.002 s); a message with a longer one is refused unparsed."""

_STRING_REST = re.compile(rb'(?:[^"\\]++|\\.)*+"')
"""The rest of a JSON string after its opening quote, to its closing one (possessive: one pass, never back)."""


def _stretches(data: bytes | bytearray) -> Iterator[tuple[int, int, bool]]:
    """The (start, end) of each stretch of the JSON text ``data`` outside its strings, in order, each with whether a
    (terminated) string follows it. Linear in ``data``: each string is skipped by one match. What follows an
    unterminated string is not JSON (a parse stops there): the stretches end there."""
    at = 0
    while True:
        quote = data.find(b'"', at)
        if quote < 0:
            yield at, len(data), False
            return
        rest = _STRING_REST.match(data, quote + 1)
        yield at, quote, rest is not None
        if rest is None:
            return
        at = rest.end()


def json_values(data: bytes | bytearray, limit: int = MAX_MESSAGE_VALUES) -> int:
    """How many values the JSON text ``data`` holds, as its parse would build them: its strings, and the ``{``, ``[``
    and ``,`` outside them; counting stops once past ``limit`` (it returns a number over it), so at most ``limit``
    strings are matched, whatever ``data`` holds."""
    count = 0
    for start, end, string in _stretches(data):
        count += data.count(b"{", start, end) + data.count(b"[", start, end) + data.count(b",", start, end) + string
        if count > limit:
            break
    return count


def json_long_number(data: bytes | bytearray, limit: int = MAX_NUMBER_CHARS) -> bool:
    """Whether the JSON text ``data`` holds, outside its strings, a number (a run of ``-+.0-9eE``) of more than
    ``limit`` characters. Linear in ``data``: a run is tried from its start only, over at most ``limit + 1``
    characters; at most :data:`MAX_MESSAGE_VALUES` strings are skipped (a message of more is refused for them)."""
    long_number = _long_number(limit)
    for strings, (start, end, _) in enumerate(_stretches(data)):
        if long_number.search(data, start, end) is not None:
            return True
        if strings > MAX_MESSAGE_VALUES:
            break
    return False


@functools.lru_cache(maxsize=4)
def _long_number(limit: int) -> re.Pattern[bytes]:
    return re.compile(rb"(?<![-+.0-9eE])[-+.0-9eE]{%d}" % (limit + 1))
