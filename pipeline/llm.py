"""LLM calls: any provider through litellm, with retries, timeouts and everything needed for ``llm_calls``.

:class:`LiteLLMClient` calls ``litellm.completion`` (``--model anthropic/...``, ``openai/...``, or any
OpenAI-compatible server with ``--api-base``). Transient provider errors (rate limits, timeouts, connection
errors, 5xx) are retried with exponential backoff; errors that retrying cannot fix (authentication, unknown
model, a request the provider refuses) fail at once. Either way the caller gets an :class:`LLMError` it can
record, never a traceback. :class:`ReplayClient` answers from the replies already stored for a run, matched by
prompt hash: resuming and ``codearcade replay`` never pay for a call twice.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Protocol

from pipeline.prompt import prompt_hash
from pipeline.tokens import import_litellm

RETRYABLE = ("RateLimitError", "Timeout", "APIConnectionError", "ServiceUnavailableError", "InternalServerError",
             "BadGatewayError", "APIError")
FATAL = ("AuthenticationError", "PermissionDeniedError", "NotFoundError", "BadRequestError",
         "ContextWindowExceededError", "ContentPolicyViolationError", "UnsupportedParamsError",
         "PaymentRequiredError", "BudgetExceededError")


@dataclass
class LLMReply:
    text: str
    response_model: str | None = None
    response_id: str | None = None
    finish_reasons: list[str] = field(default_factory=list)
    input_tokens: int | None = None
    output_tokens: int | None = None
    cost_usd: float | None = None
    latency_s: float = 0.0
    attempts: int = 1
    replayed: bool = False


class LLMError(Exception):
    """A call that did not produce a reply; ``fatal`` when retrying later cannot help (a bad key, a bad model)."""

    def __init__(self, error_type: str, message: str, attempts: int, fatal: bool, latency_s: float = 0.0):
        super().__init__(f"{error_type}: {message}")
        self.error_type = error_type
        self.message = message
        self.attempts = attempts
        self.fatal = fatal
        self.latency_s = latency_s


class LLMClient(Protocol):
    model: str
    provider: str

    def request_params(self) -> dict[str, Any]: ...

    def complete(self, messages: list[dict[str, str]]) -> LLMReply: ...


def _error_name(exc: BaseException) -> str:
    for klass in type(exc).__mro__:
        if klass.__name__ in RETRYABLE + FATAL:
            return klass.__name__
    return type(exc).__name__


def _first_line(text: str, limit: int = 500) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[:limit] + "…"


class LiteLLMClient:
    """A model reached through litellm. ``complete`` retries transient errors, then raises :class:`LLMError`."""

    def __init__(
        self,
        model: str,
        api_base: str | None = None,
        api_key: str | None = None,
        temperature: float | None = 0.0,
        max_tokens: int = 4096,
        seed: int | None = None,
        timeout_s: float = 300.0,
        retries: int = 3,
        backoff_s: float = 2.0,
    ):
        self.litellm = import_litellm()
        self.model = model
        self.api_base = api_base
        self.api_key = api_key
        self.temperature = temperature
        self.max_tokens = max_tokens
        self.seed = seed
        self.timeout_s = timeout_s
        self.retries = retries
        self.backoff_s = backoff_s
        try:
            self.provider = self.litellm.get_llm_provider(model, api_base=api_base)[1]
        except Exception as exc:  # litellm raises BadRequestError for a model string it cannot place
            raise ValueError(f"unknown model '{model}': give it as provider/model (for example "
                             f"anthropic/claude-3-5-sonnet-20241022 or openai/gpt-4o), or use --api-base for an "
                             f"OpenAI-compatible server ({_first_line(exc, 120)})") from None

    def request_params(self) -> dict[str, Any]:
        params: dict[str, Any] = {"model": self.model, "max_tokens": self.max_tokens, "timeout": self.timeout_s}
        if self.temperature is not None:
            params["temperature"] = self.temperature
        if self.seed is not None:
            params["seed"] = self.seed
        if self.api_base:
            params["api_base"] = self.api_base
        return params

    def complete(self, messages: list[dict[str, str]]) -> LLMReply:
        params = self.request_params()
        extra = {"api_key": self.api_key} if self.api_key else ({"api_key": "none"} if self.api_base else {})
        start = time.monotonic()
        for attempt in range(1, self.retries + 2):
            try:
                response = self.litellm.completion(messages=messages, num_retries=0, **params, **extra)
            except Exception as exc:  # noqa: BLE001 - every provider error becomes an LLMError
                name = _error_name(exc)
                fatal = name in FATAL
                if fatal or attempt > self.retries:
                    raise LLMError(name, _first_line(exc), attempt, fatal, time.monotonic() - start) from None
                time.sleep(self.backoff_s * 2 ** (attempt - 1))
                continue
            return self._reply(response, attempt, time.monotonic() - start)
        raise AssertionError("unreachable")

    def _reply(self, response: Any, attempts: int, latency_s: float) -> LLMReply:
        choice = response.choices[0] if response.choices else None
        text = (choice.message.content if choice is not None and choice.message is not None else None) or ""
        usage = getattr(response, "usage", None)
        try:
            cost = self.litellm.completion_cost(completion_response=response)
        except Exception:  # unknown models have no price
            cost = None
        return LLMReply(
            text=text,
            response_model=getattr(response, "model", None),
            response_id=getattr(response, "id", None),
            finish_reasons=[c.finish_reason for c in response.choices if getattr(c, "finish_reason", None)],
            input_tokens=getattr(usage, "prompt_tokens", None),
            output_tokens=getattr(usage, "completion_tokens", None),
            cost_usd=cost or None,
            latency_s=latency_s,
            attempts=attempts,
        )


class ReplayClient:
    """Answers with replies stored for a run, by prompt hash; a prompt never seen raises a fatal LLMError."""

    provider = "replay"

    def __init__(self, replies: dict[str, str], model: str):
        self.replies = replies
        self.model = model

    def request_params(self) -> dict[str, Any]:
        return {"model": self.model, "replay": True}

    def complete(self, messages: list[dict[str, str]]) -> LLMReply:
        digest = prompt_hash(messages)
        if digest not in self.replies:
            raise LLMError("ReplayMiss", f"no stored reply for prompt {digest[:12]}", 1, fatal=True)
        return LLMReply(text=self.replies[digest], response_model=self.model, replayed=True, latency_s=0.0)


OFFLINE_TOKEN_BUDGET = 3_000
OFFLINE_MAX_TOKENS = 512
"""The offline model reads ~100-200 prompt tokens/s on two cores: small prompts keep an iteration near a minute."""


def open_client(model: str | None, api_base: str | None, temperature: float, max_tokens: int | None, seed: int):
    """(client, local server or None, prompt-token cap or None) for ``--model``, or the offline default.

    With no model, SmolLM2 is started on 127.0.0.1 (``pipeline/local_llm.py``) and a one-time notice says it
    only exercises the pipeline; the caller stops the server when done.
    """
    if model:
        return LiteLLMClient(model, api_base=api_base, temperature=temperature, max_tokens=max_tokens or 4096,
                             seed=seed), None, None
    from pipeline.local_llm import LocalModelServer, show_offline_model_notice

    show_offline_model_notice()
    server = LocalModelServer().start()
    max_tokens = max_tokens or OFFLINE_MAX_TOKENS
    client = LiteLLMClient(server.model, api_base=server.api_base, temperature=temperature, max_tokens=max_tokens,
                           seed=seed)
    return client, server, server.context_tokens - max_tokens
