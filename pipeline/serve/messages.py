"""What an agent's message may make ``codearcade serve`` build when it is parsed, counted before it is.

A JSON parse holds a Python object for every value, and a value can take two bytes to write (``{},`` is a dict,
``1,`` a list slot): bytes alone do not bound it. The MCP SDK parses a whole message (a stdio line of up to 4 MiB,
a ``--mcp-port`` body of up to 4 MiB) into Python objects and then validates it into its models: 3.5 MB of
``[{},{},...]`` in a request's arguments held ``serve --mcp`` at +175 MB, in a notification's params at +281 MB,
and an ``initialize`` request's params are kept with its session, so 16 sessions opened over ``--mcp-port`` with
such params held 1.36 GB for their idle timeout. An honest message holds a few dozen values: its long parts are
strings (the policy's text, a query), each one value however long. So each message's values are counted first
(:func:`json_values`), outside its strings, and a message with more than :data:`MAX_MESSAGE_VALUES` is refused
unparsed.
"""

from __future__ import annotations

import re

MAX_MESSAGE_VALUES = 10_000
"""Values (strings, and the ``{``, ``[`` and ``,`` outside strings) one agent's message may hold: an honest one holds
a few dozen (a submission's instances are at most a few dozen ids). At ~200 bytes of Python objects a value, a
message past it would cost the server more than ~2 MB, however few bytes it took."""

_STRING_REST = re.compile(rb'(?:[^"\\]++|\\.)*+"')
"""The rest of a JSON string after its opening quote, to its closing one (possessive: one pass, never back)."""


def json_values(data: bytes, limit: int = MAX_MESSAGE_VALUES) -> int:
    """How many values the JSON text ``data`` holds, as its parse would build them: its strings, and the ``{``, ``[``
    and ``,`` outside them; counting stops once past ``limit`` (it returns a number over it). Linear in ``data``:
    each string is skipped by one match, and there are at most ``limit`` of them before counting stops. What follows
    an unterminated string is not counted: a parse stops there."""
    count, at = 0, 0
    while count <= limit:
        quote = data.find(b'"', at)
        end = len(data) if quote < 0 else quote
        count += data.count(b"{", at, end) + data.count(b"[", at, end) + data.count(b",", at, end)
        if quote < 0:
            break
        rest = _STRING_REST.match(data, quote + 1)
        if rest is None:  # unterminated: not JSON past here
            break
        count += 1
        at = rest.end()
    return count
