"""What a provider's error says, for the client (``pipeline/llm/client.py``) to decide what to do with it: its
kind (litellm's exception class: :data:`RETRYABLE` or :data:`FATAL`, :func:`error_name`), whether it refuses the
reply schema (:func:`refuses_reply_format`), the wait the provider asked for (:func:`asked_wait_s`, over
:data:`MAX_ASKED_WAIT_S` not waited out), and its message as stored and shown (:func:`describe_error`, the
endpoint's URL without credentials: :func:`without_credentials`). Nothing here asks or retries.
"""

from __future__ import annotations

import email.utils
import math
import re
import time
from typing import Mapping

from pipeline.llm.answers import NoText

RETRYABLE = ("RateLimitError", "Timeout", "APIConnectionError", "ServiceUnavailableError", "InternalServerError",
             "BadGatewayError", "APIError")
FATAL = ("AuthenticationError", "PermissionDeniedError", "NotFoundError", "BadRequestError",
         "ContextWindowExceededError", "ContentPolicyViolationError", "UnsupportedParamsError",
         "PaymentRequiredError", "BudgetExceededError")
"""litellm's exception classes by what retrying can do: the first list is retried, the second is fatal.
An error of neither kind is retried (an unknown failure is more likely transient than a bad key)."""

UNREADABLE_ANSWER = re.compile(r"Error converting to valid response block")
"""litellm's words for an answer its adapter could not read (Gemini's: a 200 whose body is an error object), which
it raises as a bad request (422): the endpoint's answer was at fault, not the request, and another may be read."""

MAX_ASKED_WAIT_S = 300.0
"""The longest wait before a retry that a provider may ask for (``Retry-After``) and be waited out. A longer one
(a quota for the day, a hostile ``--api-base``'s ``Retry-After: 1e308``) stops the run as an error that retrying
cannot fix, saying how long it asked: ``--resume`` it once the provider allows, rather than sit silent for hours."""

MAX_HEADER_CHARS = 64
"""The longest ``Retry-After`` value read: seconds or an HTTP date are far shorter; a longer one is not parsed."""

ERROR_MESSAGE_LIMIT = 1_000
"""Characters of a provider's error message kept in ``llm_calls.error_message`` and shown to the user."""


def error_name(exc: BaseException) -> str:
    """An error's type as ``llm_calls.error_type`` records it: an answer without text's own (:class:`NoText`), an
    answer litellm could not read an ``APIError`` (retried), else litellm's class of :data:`RETRYABLE` or
    :data:`FATAL` it is one of, else its own class's name."""
    if isinstance(exc, NoText):
        return exc.error_type
    if UNREADABLE_ANSWER.search(str(exc)):
        return "APIError"
    for klass in type(exc).__mro__:
        if klass.__name__ in RETRYABLE + FATAL:
            return klass.__name__
    return type(exc).__name__


def refuses_reply_format(name: str, exc: BaseException) -> bool:
    """Whether a provider error refuses the reply schema (a bad request that names it)."""
    return name in ("BadRequestError", "UnsupportedParamsError") and bool(
        re.search(r"response_format|json_schema|response_schema|structured output", str(exc), re.IGNORECASE))


def describe_error(exc: BaseException, limit: int = ERROR_MESSAGE_LIMIT) -> str:
    """The useful part of a provider error, on one line: litellm's own prefixes (``litellm.AuthenticationError:
    AnthropicException - ``) and JSON wrapping are taken off, so what is kept (and cut at ``limit``) is what the
    provider said."""
    text = str(getattr(exc, "message", None) or exc)
    # litellm puts the traceback of its own failure to read an answer into the message (Ollama's 200 with an error
    # object: "... not NoneType\nTraceback (most recent call last): File ..."): it was stored and shown
    text = " ".join(text.split("Traceback (most recent call last)", 1)[0].split())
    text = re.sub(r"^((litellm\.)?\w+(Error|Exception): )+", "", text)  # "litellm.X: YException: ..."
    text = re.sub(r"^\w+Exception - ", "", text)
    match = re.search(r'"(?:message|error)"\s*:\s*"((?:[^"\\]|\\.)*)"', text)
    if match:
        text = match.group(1)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def asked_wait_s(exc: BaseException) -> float | None:
    """Seconds the provider asked to wait before the next request, from the response headers litellm keeps on its
    exception for every provider (``litellm_response_headers``): OpenAI's ``retry-after-ms``, else ``retry-after``
    as seconds or an HTTP date (one in the past: 0). None when it asked nothing readable (no header, a negative,
    non-finite or over-long value), and the client's own backoff decides."""
    headers = getattr(exc, "litellm_response_headers", None)
    if not isinstance(headers, Mapping):
        return None
    named = {str(name).lower(): str(value).strip() for name, value in headers.items()}
    for name, scale in (("retry-after-ms", 1e-3), ("retry-after", 1.0)):
        value = named.get(name, "")
        if not value or len(value) > MAX_HEADER_CHARS:
            continue
        try:
            seconds = float(value) * scale
        except ValueError:
            if name == "retry-after-ms":
                continue
            try:  # an HTTP date: Retry-After: Wed, 21 Oct 2026 07:28:00 GMT
                seconds = max(0.0, email.utils.parsedate_to_datetime(value).timestamp() - time.time())
            except (TypeError, ValueError, OverflowError):
                continue
        if math.isfinite(seconds) and seconds >= 0:
            return seconds
    return None


def without_credentials(url: str) -> str:
    """``url`` without a ``user:password@`` part and a query (where a key given in the URL would be): shown and
    stored without them."""
    import urllib.parse

    parts = urllib.parse.urlsplit(url)
    return urllib.parse.urlunsplit(parts._replace(netloc=parts.netloc.rsplit("@", 1)[-1], query="", fragment=""))
