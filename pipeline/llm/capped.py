"""The bytes an LLM endpoint's answer may hold, bounded while it is read, compressed or not.

litellm reads a provider's whole HTTP answer (and inflates a gzip one) before codearcade sees the reply: an
endpoint that answered 200 MB, or 416 KB of gzip that inflates to it, held ~1.9 GB in ``optimize``'s process,
whatever ``--max-tokens`` asked for. While :func:`capped` is active in a thread, every response that thread reads
through ``httpx`` (litellm's own handler: Anthropic, Ollama, Gemini, ...) or ``httpx2`` (the OpenAI SDK's) is
decoded by :class:`CappedDecoder`: identity, gzip or deflate, inflated a slice at a time, and
:class:`AnswerTooLarge` raised as soon as the answer passes the limit, raw or inflated (any other encoding is
refused: a provider asked by httpx for gzip or deflate sends one of those), or a JSON answer holds more elements
outside its strings than a reply could (:data:`MAX_ANSWER_ELEMENTS`: what its parse holds depends on those, not on
bytes), or an
event stream more events than its reply could take (each costs litellm ~0.4 ms and a few KB, an empty one too:
300,000 of ``{}``, 6 KB of gzip, took 115 s and 830 MB) or more elements than those events could
(:data:`EVENT_ELEMENTS` each beyond :data:`MAX_ANSWER_ELEMENTS`: litellm keeps every event's fields, so one event
of 5 million ``{}`` held 780 MB, and 19,000 events of 250 each 400 MB). Outside :func:`capped` the libraries
decode as they always do.

The hook is the response's ``_get_content_decoder``, the one place both libraries choose how to decode a body;
``tests/test_providers.py`` checks it against real servers speaking the OpenAI and Anthropic protocols.
"""

from __future__ import annotations

import contextlib
import contextvars
import importlib
import re
import zlib
from typing import Iterator

MAX_ANSWER_BYTES = 16 * 2**20
"""The most an LLM endpoint's answer may hold, inflated: a reply of ``MAX_REPLY_CHARS`` (1,000,000 characters) in
JSON with every character escaped, or a stream of ~100,000 tokens, each its own event."""
MAX_ANSWER_ELEMENTS = 10_000
"""The most ``{``, ``[`` and ``,`` a JSON answer may hold outside its strings (an event stream: these and
:data:`EVENT_ELEMENTS` an event). A reply's own text is one JSON string, and an honest answer's structure around it
has a few dozen; ``[{},{},…]`` in 16 KB of gzip (16 MB inflated) was 5.5 million dicts, ~1 GB a call, the SDK's
models built from it included, and 40,000 choices (2.7 MB, within the 250,000 elements counted before strings were
told apart) held 146 MB and took 8 s: litellm builds objects of ~3.6 KB for each. At this count the parse holds
~40 MB at most."""
EVENT_ELEMENTS = 32
"""The ``{``, ``[`` and ``,`` an event stream may hold for each event it has sent, beyond :data:`MAX_ANSWER_ELEMENTS`:
an honest event (OpenAI's chunk, Anthropic's delta, Ollama's line) has 5 to 15. Without it a stream's elements went
uncounted: litellm parses each event on its own but keeps its fields, so one event of 5 million ``{}`` (15 MB, or
16 KB of gzip) held 780 MB in ``optimize``'s process; at this count a stream of 20,000 events holds ~55 MB of
them, beside the ~70 MB litellm spends on the events themselves."""

_STRING_REST = re.compile(rb'(?:[^"\\\n]++|\\.)*+')
"""The rest of a JSON string's body: to its closing quote, a line end (strict JSON, which litellm and the SDKs
parse, holds none in a string: a stream's events and lines start afresh) or a backslash read last."""
_STRING = re.compile(rb'"(?:[^"\\\n]++|\\.)*+"')
"""A whole JSON string on one line."""

_LIMIT: contextvars.ContextVar[tuple[int, int] | None] = contextvars.ContextVar("codearcade_answer_limit",
                                                                                 default=None)
"""While :func:`capped` is active: (the bytes, the events of a stream) an answer may hold."""


class AnswerTooLarge(Exception):
    """An endpoint's answer past :data:`MAX_ANSWER_BYTES` (or in an encoding this module does not inflate)."""


class CappedDecoder:
    """Decodes one response body (identity, gzip or deflate) and counts what it has read and made."""

    def __init__(self, encodings: list[str], limit: int, elements: int | None = MAX_ANSWER_ELEMENTS,
                 events: int | None = None, event_mark: bytes = b"data:", event_elements: int = 0) -> None:
        encodings = [e.strip().lower() for e in encodings if e.strip().lower() not in ("", "identity")]
        if len(encodings) > 1 or (encodings and encodings[0] not in ("gzip", "x-gzip", "deflate")):
            raise AnswerTooLarge(f"the endpoint answered with content encoding {', '.join(encodings)!r}, which "
                                 "codearcade does not read")
        self.limit = limit
        self.elements = elements
        """How many ``{``, ``[`` and ``,`` the answer may hold (None: not counted), and ``event_elements`` more for
        each event of a stream it has sent."""
        self.event_elements = event_elements
        self.events = events
        """How many events (``data:`` lines) an event stream may hold (litellm reads past empty ones unseen)."""
        self.event_mark = event_mark
        """What each event holds once: ``data:`` (server-sent events), a line end (Ollama's JSON lines)."""
        self.raw = self.made = self.seen_elements = self.seen_events = 0
        self.in_string = self.escaped = False
        """Whether what was read ends inside a JSON string, and right after a backslash in it."""
        # 47: a gzip or zlib header, whichever the body has (servers send both for "deflate")
        self.inflater = zlib.decompressobj(47) if encodings else None

    def _count(self, out: bytes) -> None:
        self.made += len(out)
        if self.made > self.limit or self.raw > self.limit:
            raise AnswerTooLarge(f"the endpoint's answer passed {self.limit:,} bytes"
                                 + (f" (from {self.raw:,} compressed)" if self.inflater is not None else "")
                                 + ": no reply is that long; is --api-base an LLM endpoint?")
        if self.events is not None:  # first: an event's own elements come with it
            self.seen_events += out.count(self.event_mark)  # a mark split across two reads is not counted: one
            if self.seen_events > self.events:
                raise AnswerTooLarge(f"the endpoint's stream passed {self.events:,} events: no reply of the "
                                     "tokens asked for takes that many; is --api-base an LLM endpoint?")
        if self.elements is not None:
            structure = self._outside_strings(out)
            self.seen_elements += structure.count(b"{") + structure.count(b"[") + structure.count(b",")
            allowed = self.elements + self.event_elements * self.seen_events
            if self.seen_elements > allowed:
                per_event = (f" ({self.elements:,} and {self.event_elements} for each of its {self.seen_events:,} "
                             "events)" if self.event_elements else "")
                raise AnswerTooLarge(f"the endpoint's {'stream' if self.events is not None else 'answer'} holds "
                                     f"more than {allowed:,} JSON elements{per_event}: no reply has that many; is "
                                     "--api-base an LLM endpoint?")

    def _outside_strings(self, data: bytes) -> bytes:
        """``data`` (the next bytes of the answer) without what lies inside JSON strings: a reply's text, however
        many commas its code has, is one element, and its elements are counted by what a parse builds."""
        pos = 0
        if self.in_string and data:
            if self.escaped and data[:1] != b"\n":
                pos = 1  # the character the backslash read last escapes
            self.escaped = False
            pos = _STRING_REST.match(data, pos).end()
            if pos == len(data):
                return b""
            if data[pos] == 0x5C:  # a backslash
                if pos + 1 == len(data):
                    self.escaped = True
                    return b""
                pos += 1  # before a line end: the string ends there (it is no JSON)
            self.in_string = False
            if data[pos] == 0x22:  # its closing quote
                pos += 1
        rest = _STRING.sub(b"", data[pos:])
        opened = rest.find(b'"', rest.rfind(b"\n") + 1)  # a string still open at the end of what was read
        if opened < 0:
            return rest
        body = rest[opened + 1:]
        self.in_string, self.escaped = True, (len(body) - len(body.rstrip(b"\\"))) % 2 == 1
        return rest[:opened]

    def chunks(self, data: bytes) -> Iterator[bytes]:
        self.raw += len(data)
        if self.inflater is None:
            self._count(data)
            yield data
            return
        while data:
            try:
                out = self.inflater.decompress(data, 1 << 16)  # a slice at a time: a bomb never inflates whole
            except zlib.error as exc:
                raise AnswerTooLarge(f"the endpoint's compressed answer is broken ({exc})") from None
            self._count(out)
            yield out
            data = self.inflater.unconsumed_tail

    def rest(self) -> bytes:
        if self.inflater is None:
            return b""
        out = self.inflater.flush()
        self._count(out)
        return out


class _BytesDecoder:
    """``httpx``'s decoder interface: ``decode`` and ``flush`` return bytes."""

    def __init__(self, capped: CappedDecoder) -> None:
        self.capped = capped

    def decode(self, data: bytes) -> bytes:
        return b"".join(self.capped.chunks(data))

    def flush(self) -> bytes:
        return self.capped.rest()


class _ChunksDecoder:
    """``httpx2``'s decoder interface: ``decode`` and ``flush`` return iterables of bytes."""

    def __init__(self, capped: CappedDecoder) -> None:
        self.capped = capped

    def decode(self, data: bytes) -> Iterator[bytes]:
        return self.capped.chunks(data)

    def flush(self) -> list[bytes]:
        return [self.capped.rest()]


def _install(module_name: str, adapter: type) -> None:
    """Wrap ``module_name``'s ``Response._get_content_decoder`` (once): capped while :func:`capped` is active."""
    try:
        response = importlib.import_module(module_name).Response
    except ImportError:
        return
    original = response._get_content_decoder
    if getattr(original, "_codearcade_capped", False):
        return

    def decoder(self):  # noqa: ANN001 - the library's Response
        limits = _LIMIT.get()
        if limits is None:
            return original(self)
        if not hasattr(self, "_decoder"):
            limit, events = limits
            kind = self.headers.get("content-type", "").lower()
            mark = b"data:" if "event-stream" in kind else b"\n" if "ndjson" in kind or "jsonl" in kind else None
            self._decoder = adapter(CappedDecoder(self.headers.get_list("content-encoding", split_commas=True),
                                                  limit, MAX_ANSWER_ELEMENTS, events if mark else None,
                                                  mark or b"data:", EVENT_ELEMENTS if mark else 0))
        return self._decoder

    decoder._codearcade_capped = True
    response._get_content_decoder = decoder


@contextlib.contextmanager
def capped(limit: int = MAX_ANSWER_BYTES, events: int = 20_000) -> Iterator[None]:
    """Within the block, every HTTP answer this thread reads through httpx or httpx2 holds at most ``limit``
    bytes, and an event stream at most ``events`` events (see the module docstring)."""
    _install("httpx", _BytesDecoder)
    _install("httpx2", _ChunksDecoder)
    token = _LIMIT.set((limit, events))
    try:
        yield
    finally:
        _LIMIT.reset(token)


def too_large(exc: BaseException) -> AnswerTooLarge | None:
    """The :class:`AnswerTooLarge` behind ``exc`` (a library may wrap it as a connection error), or None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, AnswerTooLarge):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None
