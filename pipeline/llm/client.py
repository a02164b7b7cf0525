"""LLM calls: any provider through litellm, with retries, timeouts and everything needed for ``llm_calls``.

:class:`LiteLLMClient` calls ``litellm.completion`` (``--model anthropic/...``, ``openai/...``, or any
OpenAI-compatible server with ``--api-base``). Transient provider errors (rate limits, timeouts, connection
errors, 5xx) are retried with exponential backoff, or after the wait the provider asks for (``Retry-After``);
errors that retrying cannot fix (authentication, unknown model, a request the provider refuses, a wait asked for
that is longer than :data:`~pipeline.llm.errors.MAX_ASKED_WAIT_S`) fail at once: what an error says is read in
``pipeline/llm/errors.py``. An answer without text is no reply (``pipeline/llm/answers.py`` reads an answer): an
error of type :data:`~pipeline.llm.answers.EMPTY_REPLY` (retried: providers send an empty one now and then; not
retried when it stopped at the token limit), or :data:`~pipeline.llm.answers.CONTENT_FILTERED` (the provider
withheld it: Gemini's ``SAFETY``, ``RECITATION``; not retried, the same prompt is withheld again). Either way the
caller gets an :class:`LLMError` it can record, never a traceback. The provider bills every attempt it answered
(an empty answer, a stream that broke midway, each retried answer), so a call's reply or error carries the usage of
all of them, and a retry of a billed attempt is made only when the caller's ``before_retry`` says it fits (its
budgets). :class:`ReplayClient` answers from the replies already stored for a run, matched by prompt hash:
resuming and ``codearcade replay`` never pay for a call twice.
"""

from __future__ import annotations

import contextvars
import hashlib
import json
import os
import threading
import time
from typing import Any, Callable, Mapping, Protocol

from pipeline.boundary.untrusted import REDACTED, scrub_secrets
from pipeline.llm.answers import LLMReply, NoText, billed_reply, no_text, read_answer, reply_text
from pipeline.llm.capped import AnswerTooLarge, capped, too_large
from pipeline.llm.errors import FATAL, MAX_ASKED_WAIT_S, asked_wait_s, describe_error, error_name, \
    refuses_reply_format, without_credentials
from pipeline.llm.providers import KNOWN_PROVIDERS, LOCAL_SERVER_PROVIDERS, OFFLINE_CHARS_PER_TOKEN, \
    OFFLINE_REASONING_CHARS, ReplyLimits, provider_of, reply_format, reply_schema, with_cache_breakpoint
from pipeline.llm.providers import request_params as provider_request_params
from pipeline.llm.tokens import import_litellm, import_litellm_soon

DEFAULT_BACKOFF_S = 2.0
"""First wait before retrying a transient error; it doubles each retry (``CODEARCADE_LLM_BACKOFF_S`` changes it,
which the tests use to keep retries quick)."""

MAX_TOKENS = 4_096
"""The longest reply asked of a model unless told otherwise: ``--max-tokens``'s default (the offline model's is
:data:`OFFLINE_MAX_TOKENS`) and the client's."""


def prompt_hash(messages: list[dict[str, str]]) -> str:
    """SHA-256 of the canonical JSON of the messages (also their blob hash in the store)."""
    return hashlib.sha256(canonical_messages(messages).encode()).hexdigest()


def canonical_messages(messages: list[dict[str, str]]) -> str:
    """The messages as canonical JSON: what a prompt hash is the hash of, and what is stored."""
    return json.dumps(messages, sort_keys=True, ensure_ascii=False, separators=(",", ":"))


class LLMError(Exception):
    """A call that did not produce a reply; ``fatal`` when retrying later cannot help (a bad key, a bad model).
    ``answer``: what its attempts were answered, when any was an answer all the same (one without text, a stream
    that broke midway): the usage of them all, summed (:attr:`LLMReply.billed`), and the last one's finish reasons,
    which the provider bills and ``llm_calls`` records; no text of theirs is a reply."""

    def __init__(self, error_type: str, message: str, attempts: int, fatal: bool, latency_s: float = 0.0,
                 answer: LLMReply | None = None):
        super().__init__(f"{error_type}: {message}")
        self.error_type = error_type
        self.message = message
        self.attempts = attempts
        self.fatal = fatal
        self.latency_s = latency_s
        self.answer = answer


class _OutOfTime(Exception):
    """A call's deadline passed while it was in flight (:meth:`LiteLLMClient._within_time_limit`)."""


class LLMClient(Protocol):
    model: str
    provider: str

    def request_params(self) -> dict[str, Any]: ...

    def complete(self, messages: list[dict[str, str]], on_text: Callable[[str], None] | None = None,
                 candidate: int = 0, iteration: int | None = None, deadline: float | None = None,
                 before_retry: "BeforeRetry | None" = None) -> LLMReply:
        """The reply to ``messages``; ``on_text`` gets streamed text; ``candidate`` and ``iteration``: which
        proposal this is (a replay answers with that proposal's stored reply: the proposal pool may ask the same
        prompt in two iterations); ``deadline``: a ``time.monotonic()`` past which no reply is waited for (an
        :class:`LLMError` of type :data:`OUT_OF_TIME`); ``before_retry``: asked before an attempt that was
        answered (billed) is retried (:data:`BeforeRetry`)."""


BeforeRetry = Callable[["LLMReply"], "str | None"]
"""Asked before an attempt that was answered, and so billed, is retried, with that attempt (its usage; no counts
when none came): None lets the retry go, a reason ends the call as an :class:`LLMError` of type
:data:`BUDGET_SPENT` (the optimizer's budgets: a call may be billed for every attempt, and each retry must fit)."""


BUDGET_SPENT = "BudgetSpent"
"""The error type of a call ended before a retry because the budget had no room for another billed attempt
(:data:`BeforeRetry`). Never retried; the optimizer ends the run as a spent budget."""

OUT_OF_TIME = "OutOfTime"
"""The error type of a call given up on at its ``deadline``: the run's time budget (``--max-wall``) ran out while it
was in flight, or before a retry. Never retried; the optimizer ends the run as a spent budget."""

CALL_TIME_GRACE_S = 5.0
"""Past a call's time limit, how long its answer is still waited for before it is given up on: httpx's own error
for an endpoint that sent nothing in that time comes first, and says so in its words."""


_PREPARED = frozenset({"litellm", "provider", "_params", "dropped", "structured"})
"""The attributes of a :class:`LiteLLMClient` that litellm gives (:meth:`LiteLLMClient._prepare`)."""


class LiteLLMClient:
    """A model reached through litellm. ``complete`` retries transient errors, then raises :class:`LLMError`.

    Only the parameters the provider accepts are sent (``pipeline/llm/providers.py``); ``request_params()`` is
    exactly what goes to litellm besides the messages, and ``dropped`` names what the provider would refuse.
    With ``structured`` (the default) the reply is asked for as the provider module's ``REPLY_SCHEMA`` where the
    provider supports it; ``self.structured`` says whether it is. With ``reply_limits`` (the offline model, held
    to the schema by a grammar) every string of the reply is held to a length that ends it within ``max_tokens``,
    and :meth:`hold_reply_to_methods` names the policy's methods in the schema. A server that
    refuses the schema all the same (a bad request naming ``response_format``) is asked again without it, and the
    client sends it no more (``dropped`` then names it).
    ``label`` is the model as the user asked for it (``offline:...`` for the built-in model), ``model`` the
    name litellm is given.

    What litellm says of the model (its provider, the parameters it takes; ``notice`` hears what is dropped) is
    asked on first use, not when the client is made, for a model whose provider litellm places by its prefix
    (:data:`~pipeline.llm.providers.KNOWN_PROVIDERS`): litellm's import takes 2-5 s of CPU, which a run spends
    while iteration 0 plays (:func:`~pipeline.llm.tokens.import_litellm_soon`), not before its first line. Any
    other model is put to litellm as the client is made, so that one it does not know is an error then.
    """

    def __init__(
        self,
        model: str,
        api_base: str | None = None,
        api_key: str | None = None,
        temperature: float | None = 0.0,
        max_tokens: int = MAX_TOKENS,
        seed: int | None = None,
        timeout_s: float = 300.0,
        retries: int = 3,
        backoff_s: float = DEFAULT_BACKOFF_S,
        label: str | None = None,
        stream: bool = False,
        structured: bool = True,
        reply_limits: ReplyLimits | None = None,
        notice: Callable[[str], None] = lambda line: None,
    ):
        self.model = model
        self.label = label or model
        self.api_base = api_base
        self.api_key = api_key
        self.max_tokens = max_tokens
        self.timeout_s = timeout_s
        self.retries = retries
        self.backoff_s = backoff_s
        self.reply_limits = reply_limits
        self.notice = notice
        self._asked = dict(temperature=temperature, seed=seed, stream=stream, structured=structured)
        self._preparing = threading.Lock()
        if provider_of(model) not in KNOWN_PROVIDERS:  # only litellm can say whether it knows this model: asked
            self._prepare()  # now, before anything runs (else on first use; the loop's token counter starts the import)

    def __getattr__(self, name: str):
        """What litellm says of the model and provider, made on first use (:meth:`_prepare`)."""
        if name not in _PREPARED:
            raise AttributeError(name)
        self._prepare()
        return self.__dict__[name]

    def _prepare(self) -> None:
        """Import litellm and ask it what this model's provider is and which request parameters it takes; what it
        does not take is said once through ``notice``. Once, whichever thread asks first (the proposal pool's
        calls run on threads of their own)."""
        with self._preparing:
            if "structured" in self.__dict__:
                return
            model, api_base, asked = self.model, self.api_base, self._asked
            litellm = import_litellm()
            try:
                provider = litellm.get_llm_provider(model, api_base=api_base)[1]
            except Exception as exc:  # litellm raises BadRequestError for a model string it cannot place
                raise ValueError(f"unknown model '{model}': give it as provider/model (for example "
                                 f"anthropic/claude-sonnet-4-5 or openai/gpt-4o), or use --api-base for an "
                                 f"OpenAI-compatible server ({describe_error(exc, 120)})") from None
            params = provider_request_params(litellm, model, provider, temperature=asked["temperature"],
                                             max_tokens=self.max_tokens, seed=asked["seed"],
                                             timeout_s=self.timeout_s)
            sent = params.sent
            wanted = reply_format(litellm, model, provider, params.supported, api_base,
                                  reply_schema(self.reply_limits)) if asked["structured"] else None
            if wanted is not None:
                sent["response_format"] = wanted
            if api_base:
                sent["api_base"] = api_base
            if asked["stream"]:
                sent["stream"] = True
                if "stream_options" in params.supported:  # else the provider sends usage in its stream by itself
                    sent["stream_options"] = {"include_usage": True}
            self.litellm, self.provider, self._params, self.dropped = litellm, provider, sent, params.dropped
            self.structured = wanted is not None  # last: what says the client is prepared
        for name in params.dropped:
            self.notice(f"{self.label} takes no '{name}' parameter; it is not sent")

    def request_params(self) -> dict[str, Any]:
        return dict(self._params)

    def hold_reply_to_methods(self, methods: list[str]) -> None:
        """Let the reply's suggestion name only ``methods`` (the policy's trainable ones), each with its share of
        the reply's length. Only for a client with ``reply_limits`` (the offline model: a grammar built from the
        schema keeps a tiny model to real method names and a reply that closes); a hosted model reads the names
        from the prompt, and its schema stays one for every policy."""
        if self.structured and self.reply_limits is not None:
            self._params["response_format"] = {**self._params["response_format"], "json_schema": {
                **self._params["response_format"]["json_schema"], "schema": reply_schema(self.reply_limits, methods)}}

    def complete(self, messages: list[dict[str, str]], on_text: Callable[[str], None] | None = None,
                 candidate: int = 0, iteration: int | None = None, deadline: float | None = None,
                 before_retry: BeforeRetry | None = None) -> LLMReply:
        """One reply, retried as the class docstring says; with streaming on, ``on_text`` gets each piece of
        text as it arrives (a retry starts the text again). Past ``deadline`` (``time.monotonic()``) the call is
        given up on, and no retry starts: an :class:`LLMError` of type :data:`OUT_OF_TIME`. Every attempt that
        was answered is billed: the reply (or the error's ``answer``) carries the usage of them all, and before one
        is retried ``before_retry`` is asked whether another fits (:data:`BeforeRetry`)."""
        params = self.request_params()
        extra = {"api_key": self.api_key} if self.api_key else ({"api_key": "none"} if self.api_base and
                                                               self.provider in LOCAL_SERVER_PROVIDERS else {})
        sent = with_cache_breakpoint(self.provider, messages)
        start = time.monotonic()
        attempt = retried = 0
        billed: list[LLMReply] = []  # every attempt that was answered: the provider bills each, not only the last

        def error(error_type: str, message: str, fatal: bool, attempts: int | None = None) -> LLMError:
            return LLMError(error_type, message, attempt if attempts is None else attempts, fatal,
                            time.monotonic() - start, billed_reply(billed))

        def unreported() -> LLMReply:
            """This attempt, billed with its usage never come (a stream broken or given up on midway)."""
            return LLMReply("", latency_s=time.monotonic() - start, attempts=attempt, structured=self.structured)

        while True:
            attempt += 1
            if deadline is not None and time.monotonic() >= deadline:
                raise error(OUT_OF_TIME, "the run's time budget ran out before this call could be made"
                            + (f" again (after {attempt - 1} attempts)" if attempt > 1 else ""), True, attempt - 1)
            progress: dict[str, bool] = {}
            try:
                response = self._within_time_limit(lambda: self._answer(sent, params, extra, on_text, progress),
                                                   deadline)
            except _OutOfTime:
                if progress.get("answered", False):  # a stream had begun: the model was generating, and bills it
                    billed.append(unreported())
                raise error(OUT_OF_TIME, f"the call was given up on after {time.monotonic() - start:.0f} s, at the "
                            "run's deadline", True) from None
            except Exception as exc:  # noqa: BLE001 - every provider error becomes an LLMError
                # an answer without text was billed all the same, and so was a stream that broke midway (its
                # usage never came): each goes with the error, and with the reply of a later attempt
                answered = isinstance(exc, NoText) or progress.get("answered", False)
                if answered:
                    billed.append(self._reply(exc.response, attempt, time.monotonic() - start)
                                  if isinstance(exc, NoText) else unreported())
                large = too_large(exc)
                if large is not None:  # not retried: the same endpoint would send the same again
                    raise error("AnswerTooLarge", str(large) + self._asked_at(), False) from None
                if isinstance(exc, NoText) and not exc.retry:  # the same prompt would get the same
                    raise error(exc.error_type, str(exc) + self._asked_at(), False) from None
                name = error_name(exc)
                if self.structured and refuses_reply_format(name, exc):
                    # a server that does not take the reply schema: ask again without it (not a retry), and
                    # from now on
                    self.structured, self.dropped = False, self.dropped + ("response_format",)
                    del self._params["response_format"]
                    params = self.request_params()
                    continue
                fatal = name in FATAL
                asked = None if fatal else asked_wait_s(exc)
                too_long = asked is not None and asked > MAX_ASKED_WAIT_S
                if fatal or too_long or retried >= self.retries:
                    # the endpoint's text may quote the key it was sent: it is stored, printed and prompted
                    message = self._without_key(describe_error(exc)) + self._asked_at()
                    if too_long:
                        message += (f"; the provider asks to wait {asked:,.0f} s before the next request, longer "
                                    f"than a call waits ({MAX_ASKED_WAIT_S:.0f} s): resume the run once it allows")
                    raise error(name, message, fatal or too_long) from None
                # a billed attempt spent part of what was set aside for the call: another may not fit the budget
                why = before_retry(billed[-1]) if answered and before_retry is not None else None
                if why is not None:
                    raise error(BUDGET_SPENT, f"not retried after {name}: {why}", False) from None
                retried += 1
                # the provider knows when its limit resets: a backoff shorter than that is a call wasted
                pause = asked if asked is not None else self.backoff_s * 2 ** (retried - 1)
                time.sleep(pause if deadline is None else max(0.0, min(pause, deadline - time.monotonic())))
                continue
            billed.append(self._reply(response, attempt, time.monotonic() - start))
            return billed_reply(billed)

    def _asked_at(self) -> str:
        """`` (asked at URL)`` after an error's message when the endpoint is the user's ``--api-base`` (its
        credentials left out): "Connection error.", "Error code: 404" and the provider's own texts have no URL."""
        return f" (asked at {without_credentials(self.api_base)})" if self.api_base else ""

    def _answer(self, sent: list[dict[str, Any]], params: dict[str, Any], extra: dict[str, Any],
                on_text: Callable[[str], None] | None, progress: dict[str, bool]) -> Any:
        """One request and its whole answer (a stream read to its end), read and inflated within
        ``MAX_ANSWER_BYTES``. ``progress["answered"]``: a stream began (litellm raises an HTTP error before it
        hands one back), so the model was generating and the attempt is billed, whatever happens to it after."""
        with capped(events=self.max_events()):
            response = self.litellm.completion(messages=sent, num_retries=0, **params, **extra)
            if params.get("stream"):
                progress["answered"] = True
                response = self._collect(response, sent, on_text, time.monotonic())
        if not reply_text(response).strip():  # stored as a reply, it was read as one: "the reply is empty"
            raise no_text(response)
        return response

    def _within_time_limit(self, call: Callable[[], Any], deadline: float | None = None) -> Any:
        """``call()``'s result, given up on once the call's time limit (and a few seconds for httpx's own word on
        a silent endpoint) has passed in all: httpx's limit is per read, so an endpoint that sent a byte just
        inside it held ``optimize`` for as long as it liked (480 s and on, with a 30 s ``--max-wall``). The call
        runs in a thread of its own, with this thread's context (:func:`capped`'s limits); one given up on is
        left to end with its connection, still held to those limits. Given up on at ``deadline`` too, if that
        comes first (:class:`_OutOfTime`)."""
        outcome: dict[str, Any] = {}
        context = contextvars.copy_context()

        def run() -> None:
            try:
                outcome["response"] = context.run(call)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread as it was raised
                outcome["error"] = exc

        worker = threading.Thread(target=run, name="codearcade-llm-call", daemon=True)
        worker.start()
        wait_s = self.timeout_s + CALL_TIME_GRACE_S
        cut = deadline is not None and deadline - time.monotonic() < wait_s
        worker.join(max(0.0, deadline - time.monotonic()) if cut else wait_s)
        if worker.is_alive() and cut:
            raise _OutOfTime
        if worker.is_alive():
            raise self.litellm.Timeout(f"no whole answer within the call's time limit of {self.timeout_s:g} s",
                                       self.model, self.provider)
        if "error" in outcome:
            raise outcome["error"]
        return outcome["response"]

    def _without_key(self, text: str) -> str:
        """``text`` with this client's key and any secret of the environment or key-shaped string redacted."""
        if self.api_key and len(self.api_key) >= 8:
            text = text.replace(self.api_key, REDACTED)
        return scrub_secrets(text)

    def _collect(self, chunks: Any, sent: list[dict[str, Any]], on_text: Callable[[str], None] | None,
                 began: float) -> Any:
        """A streamed reply, read to its end (pieces of text to ``on_text``) and built into one response, no longer
        than the call's time limit in all (httpx's is per read: an endpoint that sent an event just inside it would
        never be let go; how many events it may send, :func:`capped` counts), each event with one choice and one
        tool call at most (seven choices in each of 19,900 events, 6.7 MB, held 330 MB, seven tool calls 250 MB:
        litellm builds an object for each, and every event is kept for the reply)."""
        received = []
        for chunk in chunks:
            if time.monotonic() - began > self.timeout_s:
                raise self.litellm.Timeout(f"the stream went on past the call's time limit of {self.timeout_s:g} s",
                                           self.model, self.provider)
            choices = getattr(chunk, "choices", None) or []
            calls = max((len(getattr(getattr(c, "delta", None), "tool_calls", None) or []) for c in choices),
                        default=0)
            if len(choices) > 1 or calls > 1:  # one is asked for: each costs litellm ~1.8 KB, and every event is kept
                many = f"{len(choices):,} choices" if len(choices) > 1 else f"{calls:,} tool calls"
                raise AnswerTooLarge(f"the endpoint's stream sent {many} in one event, where one was asked for: is "
                                     "--api-base an LLM endpoint?")
            if choices or getattr(chunk, "usage", None) is not None:  # an empty event adds nothing to the reply
                received.append(chunk)
            for choice in choices:
                piece = getattr(getattr(choice, "delta", None), "content", None)
                if piece and on_text is not None:
                    on_text(piece)
        response = self.litellm.stream_chunk_builder(received, messages=sent)
        if response is None:
            raise self.litellm.APIError(500, "the stream ended without a reply", self.provider, self.model)
        return response

    def max_events(self) -> int:
        """The events a streamed answer may hold (``pipeline.llm.capped``): four a token of ``max_tokens``
        (providers send a token or less an event, and some events carry none), at least 20,000."""
        return max(20_000, 4 * self.max_tokens)

    def _reply(self, response: Any, attempts: int, latency_s: float) -> LLMReply:
        return read_answer(response, attempts, latency_s, self.structured, self.litellm.completion_cost)


class ReplayClient:
    """Answers with replies stored for a run, by (iteration, prompt hash, candidate); a call the run only ever got
    an error for raises that error again (fatal as it was: :data:`FATAL`); a prompt never seen raises a fatal
    LLMError (``ReplayMiss``)."""

    provider = "replay"

    def __init__(self, replies: Mapping[tuple[int, str, int], str], model: str,
                 errors: dict[tuple[int, str, int], tuple[str, str, int]] | None = None):
        self.replies = replies
        self.errors = errors or {}
        self.model = model
        self.label = model

    def request_params(self) -> dict[str, Any]:
        return {"model": self.model, "replay": True}

    def complete(self, messages: list[dict[str, str]], on_text: Callable[[str], None] | None = None,
                 candidate: int = 0, iteration: int | None = None, deadline: float | None = None,
                 before_retry: BeforeRetry | None = None) -> LLMReply:
        key = (iteration, prompt_hash(messages), candidate)  # a stored reply takes no time: no deadline to keep
        if key not in self.replies and key in self.errors:
            error_type, message, attempts = self.errors[key]
            raise LLMError(error_type, message, attempts, fatal=error_type in FATAL)
        if key not in self.replies:
            raise LLMError("ReplayMiss", f"no stored reply for prompt {key[1][:12]} (iteration {iteration}, "
                           f"candidate {candidate})", 1, fatal=True)
        return LLMReply(text=self.replies[key], response_model=self.model, replayed=True, latency_s=0.0)


class EnsembleClient:
    """Several models behind one client (``--model`` given several times): each call is made by the member the
    run's rule chose for it (``pipeline/optimizer/ensemble.py``; propose asks :meth:`member`). The first member
    stands for the ensemble where one model is needed: its tokenizer counts the prompts (they are the same text
    for every model), and a call nobody chose for goes to it."""

    def __init__(self, members: list[Any]):
        self.members = {m.model: m for m in members}
        self.first = members[0]
        self.model = self.first.model
        self.label = " + ".join(m.label for m in members)

    @property
    def provider(self) -> str:
        return self.first.provider

    def member(self, model: str) -> Any:
        return self.members[model]

    def request_params(self) -> dict[str, Any]:
        return next(iter(self.members.values())).request_params()

    def complete(self, messages: list[dict[str, str]], on_text: Callable[[str], None] | None = None,
                 candidate: int = 0, iteration: int | None = None, deadline: float | None = None,
                 before_retry: BeforeRetry | None = None) -> LLMReply:
        return next(iter(self.members.values())).complete(messages, on_text, candidate, iteration, deadline,
                                                          before_retry)


OFFLINE_MODEL_LABEL = "offline:smollm2-135m-instruct"
"""What ``runs.model`` says of a run made with the built-in offline model (its config says ``model: null``, so
``--resume`` starts the local server again rather than calling the server's internal name as a hosted model)."""

OFFLINE_TOKEN_BUDGET = 3_000
OFFLINE_MAX_TOKENS = 512
OFFLINE_TOKENS_PER_COUNTED = 1.8
"""SmolLM2's tokens per token the prompt's budget counts (``pipeline/llm/tokens.py``: an estimate from cl100k_base
for a model without a tokenizer of its own in litellm). The offline model's prompt cap is its context less the reply,
divided by this: measured on llama.cpp's own tokenizer, code and prose are 0.96-1.03 of the count, a Pong prompt of
7,657 counted tokens 9,007 (1.18: ``--token-budget 20000`` was held to 7,680 counted, and the call exceeded the 8,192
context), a run of numbers 1.77 (SmolLM2 reads each digit as a token)."""
"""The offline model reads ~100-200 prompt tokens/s on two cores: small prompts keep an iteration near a minute.
These are the offline model's defaults of ``--token-budget`` and ``--max-tokens``, applied to a run's settings by
one function (``pipeline/optimizer/config.py: model_defaults``) for the command line and batches alike."""


def open_client(model: str | None, api_base: str | None, temperature: float, max_tokens: int, seed: int,
                stream: bool = False, models: list[dict[str, Any]] | None = None,
                notice: Callable[[str], None] = lambda line: None):
    """(client, local server or None, prompt-token cap or None) for ``--model``, or the offline default; with
    ``models`` (an ensemble's entries), an :class:`EnsembleClient` of one client per entry, each with its own
    endpoint. ``notice`` is told what a provider does not take (``--seed`` to Anthropic), once litellm has said so:
    by the first call, not before the run's first line (:class:`LiteLLMClient`).

    With no model, SmolLM2 is started on 127.0.0.1 (``pipeline/llm/local.py``) and a one-time notice says it
    only exercises the pipeline; the caller stops the server when done. ``max_tokens`` is the run's own: the
    model's default reply length was applied to its settings before (``model_defaults``), not here.
    """
    backoff_s = float(os.environ.get("CODEARCADE_LLM_BACKOFF_S", DEFAULT_BACKOFF_S))
    asked = dict(temperature=temperature, max_tokens=max_tokens, seed=seed, backoff_s=backoff_s, stream=stream,
                 notice=notice)
    if models:
        return EnsembleClient([LiteLLMClient(e["model"], api_base=e.get("api_base"), **asked)
                               for e in models]), None, None
    if model:
        return LiteLLMClient(model, api_base=api_base, **asked), None, None
    from pipeline.llm.local import LocalModelServer, show_offline_model_notice

    show_offline_model_notice()
    import_litellm_soon()  # while the server starts
    server = LocalModelServer().start()
    # llama.cpp compiles the schema into a grammar, so SmolLM2's reply is always this JSON; its strings are held
    # short enough that the JSON closes within max_tokens
    room = OFFLINE_CHARS_PER_TOKEN * max_tokens
    limits = ReplyLimits(min(OFFLINE_REASONING_CHARS, room // 4), room)
    client = LiteLLMClient(server.model, api_base=server.api_base, label=OFFLINE_MODEL_LABEL, reply_limits=limits,
                           **asked)
    return client, server, int((server.context_tokens - max_tokens) / OFFLINE_TOKENS_PER_COUNTED)
