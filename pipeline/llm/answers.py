"""Reading an endpoint's answer into an :class:`LLMReply`: its text, and what it reports of itself (usage, model,
id, finish reasons), none of it trusted: a count the store cannot hold is unknown, a name is made storable. An
answer without text is no reply but the error it is (:func:`no_text`: :data:`EMPTY_REPLY` or
:data:`CONTENT_FILTERED`), and a call's answered attempts, each billed, make one reply with the usage of them all
(:func:`billed_reply`). The client (``pipeline/llm/client.py``) asks and retries; this module only reads.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable


@dataclass
class LLMReply:
    """A call's reply: the text of its answer and what the endpoint reported of it, as the store can hold it."""

    text: str
    response_model: str | None = None
    response_id: str | None = None
    finish_reasons: list[str] = field(default_factory=list)
    input_tokens: int | None = None
    output_tokens: int | None = None
    cached_input_tokens: int | None = None
    """Input tokens read from the provider's prompt cache (billed at the cache price)."""
    cache_creation_input_tokens: int | None = None
    """Input tokens written to the provider's prompt cache (Anthropic)."""
    cost_usd: float | None = None
    latency_s: float = 0.0
    attempts: int = 1
    replayed: bool = False
    structured: bool = False
    """The request held the provider to the reply schema (``response_format``)."""
    billed: list["LLMReply"] = field(default_factory=list)
    """Every answered attempt of the call, in order, with its own usage: the counts and cost above are their sum
    (a count or cost is None when an attempt did not report it). An attempt whose usage never came (a stream that
    broke midway: billed, by how much only the provider knows) is here with no counts at all. Empty: one attempt,
    the one above (a replay's)."""

    @property
    def cut_off(self) -> bool:
        """The reply stopped at the token limit."""
        return "length" in self.finish_reasons


EMPTY_REPLY = "EmptyReply"
"""The error type of an answer with no text (nothing, or only whitespace): no reply to read, though it is billed."""
CONTENT_FILTERED = "ContentFiltered"
"""The error type of an answer the provider withheld (finish reason ``content_filter``) and sent no text for."""

_MAX_COUNT = 2 ** 31 - 1
REPORTED_TEXT_LIMIT = 200
"""The characters kept of a name or id an endpoint reports (its model, the response's id, a finish reason)."""


class NoText(Exception):
    """An answer without text (:func:`no_text`; raised by ``LiteLLMClient._answer``): ``retry`` when another
    attempt may bring one."""

    def __init__(self, error_type: str, message: str, retry: bool, response: Any = None):
        super().__init__(message)
        self.error_type, self.retry, self.response = error_type, retry, response


def read_answer(response: Any, attempts: int, latency_s: float, structured: bool,
                cost_of: Callable[..., Any]) -> LLMReply:
    """The reply an answer holds: its text, the usage and names the endpoint reported (as the store can hold
    them: :func:`_usage_number`, :func:`_reported_text`), and its price by ``cost_of`` (litellm's
    ``completion_cost``; none where it has none)."""
    text = reply_text(response)
    usage = getattr(response, "usage", None)
    inputs, outputs = _usage_number(usage, "prompt_tokens"), _usage_number(usage, "completion_tokens")
    # litellm fills a usage the endpoint left out with zeros; no prompt is 0 tokens, nor a reply with text
    inputs = None if inputs == 0 else inputs
    outputs = None if outputs == 0 and text else outputs
    try:
        cost = cost_of(completion_response=response)
    except Exception:  # unknown models have no price
        cost = None
    return LLMReply(
        text=text,
        response_model=_reported_text(getattr(response, "model", None)),
        response_id=_reported_text(getattr(response, "id", None)),
        finish_reasons=[reason for reason in (_reported_text(getattr(c, "finish_reason", None))
                                              for c in response.choices) if reason],
        input_tokens=inputs,
        output_tokens=outputs,
        cached_input_tokens=_usage_number(usage, "prompt_tokens_details", "cached_tokens"),
        cache_creation_input_tokens=_usage_number(usage, "cache_creation_input_tokens"),
        # litellm prices the usage as reported: of counts not trusted (a negative one made a negative cost,
        # which gave the budget room) there is no cost; the optimizer charges such a call its worst case
        cost_usd=cost if inputs is not None and outputs is not None and _is_cost(cost) else None,
        latency_s=latency_s,
        attempts=attempts,
        structured=structured,
    )


def billed_reply(attempts: list[LLMReply]) -> LLMReply | None:
    """The last of a call's answered ``attempts`` with the usage of them all (what the provider bills): each count
    and the cost summed, None where an attempt did not report it (the optimizer charges that attempt its worst
    case); the cache counts are the sum of those reported. None without any answered attempt."""
    if not attempts:
        return None

    def total(name: str, known_only: bool = False) -> int | float | None:
        values = [getattr(a, name) for a in attempts]
        if known_only:
            values = [v for v in values if v is not None] or [None]
        return None if any(v is None for v in values) else sum(values)

    return dataclasses.replace(attempts[-1], input_tokens=total("input_tokens"), output_tokens=total("output_tokens"),
                               cost_usd=total("cost_usd"), cached_input_tokens=total("cached_input_tokens", True),
                               cache_creation_input_tokens=total("cache_creation_input_tokens", True),
                               billed=list(attempts))


def reply_text(response: Any) -> str:
    """The text of an answer's first choice (a forced tool's input, should an adapter leave it as a tool call)."""
    choice = response.choices[0] if response.choices else None
    message = choice.message if choice is not None else None
    text = (message.content if message is not None else None) or ""
    if not isinstance(text, str):
        return ""
    if not text and message is not None and getattr(message, "tool_calls", None):
        # litellm hands a forced tool's input back as the text; should an adapter leave it as a tool call,
        # its arguments are the reply
        text = getattr(message.tool_calls[0].function, "arguments", None) or ""
    return text if isinstance(text, str) else ""


def no_text(response: Any) -> NoText:
    """Why an answer has no text, as the error it is, by its finish reason (litellm's, the same for every
    provider: Anthropic's ``max_tokens`` and Gemini's ``MAX_TOKENS`` are ``length``; Gemini's ``SAFETY`` and
    ``RECITATION`` are ``content_filter``)."""
    reasons = [_reported_text(getattr(c, "finish_reason", None)) for c in response.choices or []]
    if "content_filter" in reasons:
        return NoText(CONTENT_FILTERED, "the provider withheld the reply (finish reason content_filter) and sent no "
                      "text", False, response)
    if "length" in reasons:
        return NoText(EMPTY_REPLY, "the reply stopped at the token limit before any text: raise --max-tokens",
                      False, response)
    return NoText(EMPTY_REPLY, "the endpoint answered with no text" + (
        f" (finish reason {', '.join(r for r in reasons if r)})" if any(reasons) else ""), True, response)


def _usage_number(usage: Any, *path: str) -> int | None:
    """A token count the endpoint reported, as the store's INTEGER column holds it; None for anything else (a
    count of 2^31 or 10^20, a negative or non-finite one, a string): the endpoint's word is not trusted, and a
    count it got wrong is unknown, not the end of the run (the insert failed, with a traceback)."""
    value = usage
    for name in path:
        value = value.get(name) if isinstance(value, dict) else getattr(value, name, None)
        if value is None:
            return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= _MAX_COUNT:
        return None  # NaN fails the range check too
    return int(value)


def _is_cost(value: Any) -> bool:
    """Whether litellm's price of a reply is one: a positive, finite number (0 is what it says of no usage)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < math.inf


def _reported_text(value: Any) -> str | None:
    """A name or id the endpoint reported, as the store can hold it: a string, lone surrogates and NULs replaced
    (a JSON ``\\ud800`` in a response's id failed the insert, ending the run with a traceback), at most
    :data:`REPORTED_TEXT_LIMIT` characters; anything else None."""
    if not isinstance(value, str):
        return None
    return value.encode("utf-8", "replace").decode("utf-8").replace("\x00", "\ufffd")[:REPORTED_TEXT_LIMIT]
