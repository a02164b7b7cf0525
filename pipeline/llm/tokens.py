"""Counting prompt tokens against the budget, with the model's own tokenizer where litellm knows it.

litellm bundles tokenizers for some model families (Anthropic's, DeepSeek's, Cohere's) and counts those
exactly. For every other model (OpenAI's, local servers, SmolLM2) the count is an estimate: tiktoken's
``cl100k_base`` (bundled with litellm, no download) times a 10 % safety margin, which covered the
SmolLM2/Llama tokenizers with room to spare when we compared them. The budget is a hard limit on *our*
count; :class:`TokenCounter` says which of the two it used.

A prompt is counted many times while it is fitted to the budget, each time a little different. For the
estimate the whole text is not encoded again: tiktoken first splits a text with its pattern, then encodes each
piece on its own, and no piece of ``cl100k_base`` runs from a newline into a following non-space character, so
the text's count is the sum of its lines' counts (each line counted once and kept). ``test_prompt.py`` checks
the sum against the whole encoding.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import math
import os
import re
import sys
import threading
from functools import lru_cache
from typing import Callable

ESTIMATE_MARGIN = 1.10
MESSAGE_OVERHEAD = 4
"""Tokens chat templates add around each message (role markers); counted so the budget holds."""

_LINE_ENDS = re.compile(r"\n(?=\S)")
"""Where tiktoken's cl100k_base pattern always ends a piece: a newline before a non-space character."""


def _lines(text: str) -> list[str]:
    """``text`` cut after each newline that a non-space character follows (a lookbehind split is 6x slower)."""
    parts = _LINE_ENDS.split(text)
    return [part + "\n" for part in parts[:-1]] + [parts[-1]]


_SETTING_UP = threading.Lock()
"""Held while litellm's settings are made: the thread of :func:`import_litellm_soon` and the one that needs litellm
may both finish importing it at once."""


def import_litellm():
    """litellm, imported once, quietly, without reaching for the network (its cost map is bundled). If
    :func:`import_litellm_soon` is importing it on its own thread, this waits for that import (Python's lock on the
    module), and imports it again where that one failed, raising its error here."""
    os.environ.setdefault("LITELLM_LOCAL_MODEL_COST_MAP", "True")
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")  # we fork workers; HF tokenizers would warn
    with _collections_paused() if "litellm" not in sys.modules else contextlib.nullcontext():
        import litellm

    with _SETTING_UP:
        if not getattr(litellm, "_codearcade_ready", False):
            _set_up(litellm)
    return litellm


@contextlib.contextmanager
def _collections_paused():
    """No cyclic garbage collection in this process meanwhile (as it was after). litellm's import makes hundreds of
    thousands of objects that live as long as the process (its pydantic models, its tables): the collections
    they start, each walking everything made so far, are a quarter of the import (3.3 -> 2.5 s here). What the
    other threads leave in cycles meanwhile is collected once collections resume."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def import_litellm_soon() -> None:
    """Start importing litellm on a thread of its own, unless it is imported or being imported. The import takes
    2-5 s of CPU on these machines: a command that will call a model only after it has played iteration 0 spends
    that time while its game hosts play, not before its first line. Whatever needs litellm then calls
    :func:`import_litellm`, which waits for this import to end. A daemon thread: a command that ends before the
    import does is not held back by it."""
    global _importing
    with _SETTING_UP:
        if "litellm" in sys.modules or _importing is not None:
            return
        _importing = threading.Thread(target=_import_quietly, name="import litellm", daemon=True)
    _importing.start()


_importing: threading.Thread | None = None


def _import_quietly() -> None:
    try:
        import_litellm()
    except BaseException:  # noqa: BLE001 - said where litellm is needed: import_litellm imports it again there
        pass


def _set_up(litellm) -> None:
    """codearcade's settings of litellm, made once, after its import."""
    litellm.suppress_debug_info = True
    litellm.telemetry = False
    # litellm hands each streamed event to its logging callbacks on a thread of its own, in an event loop made
    # for it: ~2 ms of CPU an event here, more than reading it (a streamed reply of 1,600 pieces took 5.5 s of
    # CPU, 2.3 without). codearcade registers no litellm callback (the store is its log; bench/stream_read.py)
    litellm.disable_streaming_logging = True
    from viewers.safe_text import make_logs_terminal_safe

    # its log quotes a reply's fields (an unknown finish_reason), escape sequences and all
    make_logs_terminal_safe("LiteLLM", "LiteLLM Router", "LiteLLM Proxy")
    atexit.register(_close_leftover_event_loop)  # runs before litellm's own exit hooks (registered earlier)
    litellm._codearcade_ready = True


def _close_leftover_event_loop() -> None:
    """Close the event loop litellm's logging sets on the main thread and leaves open. Left to the interpreter's
    last garbage collection, it may be collected after its own self-pipe socket and print "Exception ignored ...
    Invalid file descriptor: -1" under the last line a command wrote (what ``codearcade optimize`` says when
    interrupted), depending on the order the collection happens to take."""
    import asyncio
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            loop = asyncio.get_event_loop_policy().get_event_loop()
        except RuntimeError:  # none on this thread
            return
    if not loop.is_running() and not loop.is_closed():
        loop.close()


@lru_cache(maxsize=None)
def _cl100k():
    import_litellm()  # sets TIKTOKEN_CACHE_DIR to the tokenizer files litellm ships
    from litellm.litellm_core_utils.default_encoding import encoding

    return encoding


class TokenCounter:
    """``counter(text)`` -> tokens of ``text`` for ``model`` (exact or a documented estimate). Made at once; litellm
    is imported when the first text is counted (:func:`import_litellm_soon` starts it meanwhile)."""

    def __init__(self, model: str):
        self.model = model
        import_litellm_soon()

    def __getattr__(self, name: str):
        if name not in ("exact", "method", "_count", "_cached"):
            raise AttributeError(name)
        self._choose_tokenizer()
        return self.__dict__[name]

    def _choose_tokenizer(self) -> None:
        model = self.model
        litellm = import_litellm()
        from litellm.utils import huggingface_tokenizer_kind

        kind = huggingface_tokenizer_kind(model)
        if kind in ("anthropic", "deepseek", "cohere"):
            self.exact = True
            self.method = f"litellm's bundled {kind} tokenizer"
            self._count: Callable[[str], int] = lambda text: litellm.token_counter(model=model, text=text)
        else:
            self.exact = False
            self.method = f"estimate: cl100k_base tokens x {ESTIMATE_MARGIN}"
            encoding = _cl100k()
            # the same lines come back in prompt after prompt (a parent's rollout is shown to each of its
            # children, and an unchanged version's rollout is reused): encode each line once
            pieces = lru_cache(maxsize=65_536)(lambda chunk: len(encoding.encode(chunk, disallowed_special=())))
            self._count = lambda text: math.ceil(sum(map(pieces, _lines(text))) * ESTIMATE_MARGIN)
            self._cached = self._count  # the lines are kept, not the whole prompts they make
            return
        self._cached = lru_cache(maxsize=4_096)(self._count)  # count each text once

    def __call__(self, text: str) -> int:
        return self._cached(text) if text else 0

    def messages(self, messages: list[dict[str, str]]) -> int:
        """Tokens of a chat request: every message's content plus the per-message overhead."""
        return sum(self(m["content"]) + MESSAGE_OVERHEAD for m in messages) + MESSAGE_OVERHEAD
