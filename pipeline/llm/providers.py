"""What each LLM provider needs and accepts: credentials, request parameters, prompt caching, prices.

litellm knows all of this, but importing it takes 2-5 s on these machines, and a user who forgot a key
should hear so at once. So the credential check first looks the provider up in :data:`PROVIDER_KEYS`, a
table of the environment variables litellm itself asks for (``tests/test_providers.py`` checks the table
against ``litellm.validate_environment`` so it cannot drift), and imports litellm only for a provider the
table does not list. Everything else asks litellm:

- :func:`request_params` keeps only the parameters the provider accepts (``get_supported_openai_params``):
  Anthropic takes no ``seed``; reasoning models (OpenAI's o-series) take no ``temperature`` and get
  ``max_completion_tokens``. What is dropped is reported once, and what is kept is what gets sent and
  recorded in ``llm_calls.request_params``.
- :func:`reply_format` asks for the reply's structure where the provider can be held to it: a JSON schema as
  ``response_format``, which litellm's adapter for each provider turns into that provider's own form (OpenAI and
  vLLM: ``response_format`` as is; Gemini: ``generationConfig.response_json_schema``; Ollama: ``format``;
  Anthropic: a forced tool call whose input litellm hands back as the reply's text; llama.cpp's server, the
  offline model: ``response_format``, which it compiles into a grammar). It is sent only where litellm lists
  ``response_format`` as supported and the model can take a schema, and recorded with the other parameters.
- :func:`with_cache_breakpoint` marks the stable prefix of a prompt for providers with explicit prompt
  caching (Anthropic's ``cache_control``); OpenAI and others cache prefixes by themselves.
- :func:`price` gives litellm's price per input and output token, or None for a model it cannot price.

:func:`check_reachable` is the credential check's companion for ``--api-base``: a TCP connection to the URL's host
and port, with a short time-out, before anything plays.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Sequence

PROVIDER_KEYS: dict[str, tuple[str, ...]] = {
    "anthropic": ("ANTHROPIC_API_KEY",),
    "openai": ("OPENAI_API_KEY",),
    "gemini": ("GEMINI_API_KEY", "GOOGLE_API_KEY"),
    "mistral": ("MISTRAL_API_KEY",),
    "deepseek": ("DEEPSEEK_API_KEY",),
    "groq": ("GROQ_API_KEY",),
    "openrouter": ("OPENROUTER_API_KEY",),
    "xai": ("XAI_API_KEY",),
    "codestral": ("CODESTRAL_API_KEY",),
}
"""Provider prefix of ``--model`` -> environment variables of which one must be set (litellm's names)."""

NO_KEY_PROVIDERS = frozenset({"ollama", "ollama_chat", "hosted_vllm", "lm_studio", "llamafile"})
"""Providers that run on the user's own machine and need no key."""

LOCAL_SERVER_PROVIDERS = frozenset({"openai", "hosted_vllm", "ollama", "ollama_chat", "lm_studio", "llamafile"})
"""Providers whose ``--api-base`` usually points at the user's own server: no key is required there."""

KNOWN_PROVIDERS = frozenset(PROVIDER_KEYS) | NO_KEY_PROVIDERS | LOCAL_SERVER_PROVIDERS
"""Provider prefixes of ``--model`` that litellm places (``tests/test_providers.py`` asks it): a client for one
can be made before litellm is imported; any other model is put to litellm at once, which says if it knows it."""

CACHE_CONTROL_PROVIDERS = frozenset({"anthropic"})
"""Providers that cache a prompt prefix only where the request marks it (Anthropic's ``cache_control``)."""

CACHE_BREAKPOINT = "\n\n#Variables\n"
"""Where the stable part of an optimizer prompt ends: instruction, code stubs and documentation come first."""


OPENAI_REASONING_PROVIDERS = frozenset({"openai", "azure"})
"""Providers whose reasoning models take ``max_completion_tokens`` and no ``temperature`` (but 1)."""


class MissingCredentialsError(ValueError):
    """The provider's key is not in the environment; the message names the variable."""


def provider_of(model: str) -> str:
    """The litellm provider prefix of ``model`` (``anthropic/claude-...`` -> ``anthropic``), '' if it has none."""
    return model.split("/", 1)[0] if "/" in model else ""


FIX_ON_COMMAND_LINE = ("use --api-base URL for your own server", "leave out --model to use the offline model")
FIX_IN_BATCH_FILE = ("set api_base to your own server in the batch file",
                     "remove model from the batch file to use the offline model")
"""The other ways out of a missing key, said where the model was named (the command line, a batch file): your own
server (not offered when one is given already), or the offline model."""


def missing_keys(model: str, api_base: str | None = None, environ: dict[str, str] | None = None) -> list[str]:
    """The environment variables of which one must be set for ``model``, none of which is; [] when it needs none or
    has one.

    Answers from :data:`PROVIDER_KEYS` without importing litellm for the providers it lists (so a missing
    key is reported within a second); asks ``litellm.validate_environment`` for any other provider.
    """
    environ = os.environ if environ is None else environ
    provider = provider_of(model)
    if provider in NO_KEY_PROVIDERS or (api_base and provider in LOCAL_SERVER_PROVIDERS):
        return []
    if provider in PROVIDER_KEYS:
        names = PROVIDER_KEYS[provider]
        return [] if any(environ.get(name) for name in names) else list(names)
    from pipeline.llm.tokens import import_litellm

    if api_base:  # a proxy or self-hosted endpoint of an unlisted provider: let the server decide
        return []
    result = import_litellm().validate_environment(model)
    if result.get("keys_in_environment", True):
        return []
    return list(result.get("missing_keys") or [])


def check_credentials(model: str, api_base: str | None = None, environ: dict[str, str] | None = None,
                      other_fixes: tuple[str, str] = FIX_ON_COMMAND_LINE) -> None:
    """Raise :class:`MissingCredentialsError` naming the variable when ``model``'s key is not set (``other_fixes``:
    what else would do, said where the model was given)."""
    missing = missing_keys(model, api_base, environ)
    if missing:
        raise _needs_a_key(model, api_base, missing, other_fixes)


def _needs_a_key(model: str, api_base: str | None, missing: list[str],
                 other_fixes: tuple[str, str] = FIX_ON_COMMAND_LINE) -> MissingCredentialsError:
    """The error for ``model`` lacking all of ``missing`` (its :func:`missing_keys`)."""
    either = " or ".join(missing)
    return MissingCredentialsError(
        f"{model} needs an API key: set {either} in the environment (e.g. `export {missing[0]}=...`), or "
        + ", or ".join(other_fixes[1:] if api_base else other_fixes))


def check_ensemble_credentials(entries: list[dict], environ: dict[str, str] | None = None) -> None:
    """:func:`check_credentials` for every model of a run (``entries``: ``{"model", "api_base"}``), said at once:
    an ensemble of two hosted models without either key names both keys, not one key per attempt."""
    lacking = [(e["model"], e.get("api_base"), missing) for e in entries
               if (missing := missing_keys(e["model"], e.get("api_base"), environ))]
    if len(lacking) == 1:
        raise _needs_a_key(*lacking[0])
    if lacking:
        each = ", ".join(f"{model} ({' or '.join(missing)})" for model, _, missing in lacking)
        fixes = FIX_ON_COMMAND_LINE[1:] if all(api_base for _, api_base, _ in lacking) else FIX_ON_COMMAND_LINE
        raise MissingCredentialsError(
            f"{len(lacking)} models need an API key: {each}; set them in the environment (e.g. `export "
            f"{lacking[0][2][0]}=...`), or " + ", or ".join(fixes))


class UnreachableEndpointError(ValueError):
    """``--api-base`` names a server that does not answer; the message names the URL and the fix."""


def check_reachable(api_base: str, timeout_s: float = 3.0, given_as: str = "--api-base") -> None:
    """Raise :class:`UnreachableEndpointError` unless a TCP connection to ``api_base``'s host and port opens within
    ``timeout_s``: checked before iteration 0, as keys are, so a mistyped port or a server not started is one line
    at once rather than a failed LLM call after the first evaluation. Skipped when a proxy from the environment
    carries the request (only the proxy is reached then). ``given_as``: where the user wrote the URL, for the
    message."""
    import socket
    import urllib.parse
    import urllib.request

    example = "e.g. http://127.0.0.1:8000/v1 for vLLM, http://127.0.0.1:11434 for Ollama"
    parts = urllib.parse.urlsplit(api_base)
    try:
        port = parts.port or {"http": 80, "https": 443}.get(parts.scheme)
    except ValueError:
        port = None
    if parts.scheme not in ("http", "https") or not parts.hostname or port is None:
        raise UnreachableEndpointError(f"{given_as} {api_base!r} is not an http(s)://HOST[:PORT] URL; give the "
                                       f"server's URL ({example})")
    if urllib.request.getproxies().get(parts.scheme) and not urllib.request.proxy_bypass(parts.hostname):
        return
    try:
        with socket.create_connection((parts.hostname, port), timeout=timeout_s):
            return
    except socket.timeout:
        why = f"no answer within {timeout_s:g} s"
    except socket.gaierror:
        why = f"unknown host {parts.hostname}"
    except OSError as exc:
        why = (exc.strerror or type(exc).__name__).lower()
    raise UnreachableEndpointError(f"{given_as} {api_base} cannot be reached ({why} at {parts.hostname}:{port}): "
                                   f"start the server there, or give the URL it listens on ({example})")


IMPLIED_SERVERS = {"ollama": ("OLLAMA_API_BASE", "http://localhost:11434"),
                   "ollama_chat": ("OLLAMA_API_BASE", "http://localhost:11434"),
                   "hosted_vllm": ("HOSTED_VLLM_API_BASE", None)}
"""Providers of a server of the user's own that litellm finds without ``--api-base``: the variable it reads, then
its default (None: it has none)."""


def implied_server(model: str, environ: dict[str, str] | None = None) -> tuple[str, str] | None:
    """The server litellm calls for ``model`` given no ``--api-base``, and how the person named it (for
    :func:`check_reachable`'s message), when the provider is one of :data:`IMPLIED_SERVERS`; else None.
    :class:`UnreachableEndpointError` when there is none (``hosted_vllm/NAME`` needs a URL)."""
    environ = os.environ if environ is None else environ
    provider = provider_of(model)
    if provider not in IMPLIED_SERVERS:
        return None
    variable, default = IMPLIED_SERVERS[provider]
    if environ.get(variable):
        return environ[variable], f"${variable} (the server of --model {model})"
    if default is None:
        raise UnreachableEndpointError(f"--model {model} needs its server's URL: give --api-base URL (e.g. "
                                       f"http://127.0.0.1:8000/v1) or set {variable}")
    return default, f"the server of --model {model} (litellm's default; --api-base or ${variable} names another)"


REPLY_SCHEMA_NAME = "policy_update"

REPLY_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "reasoning": {"type": "string"},
        "suggestion": {"type": "object", "additionalProperties": {"type": "string"}},
    },
    "required": ["reasoning", "suggestion"],
    "additionalProperties": False,
}
"""The reply the prompt asks for (``pipeline/optimizer/prompt.py``'s system text), as a JSON schema: the reasoning, then
``{method name: complete new source}`` for the methods changed. It names no method, so one
schema serves every policy; validation checks the names. An object with open keys cannot be OpenAI's ``strict``
kind (that needs every key listed), so it is sent with ``strict: false``: the provider is guided by it and the
parser (``pipeline/optimizer/reply.py``) checks the result."""

@dataclass(frozen=True)
class ReplyLimits:
    """Lengths that make a reply held to the schema by a grammar end within its token limit (the offline model:
    SmolLM2 otherwise fills its few hundred reply tokens with reasoning, or repeats itself inside a string, and
    is cut off before the JSON closes)."""

    reasoning_chars: int
    """The reasoning's longest length."""
    reply_chars: int
    """The whole reply's: the methods' code shares what the reasoning and the JSON around it leave."""


OFFLINE_REASONING_CHARS = 160
OFFLINE_CHARS_PER_TOKEN = 2
"""The fewest characters a token of SmolLM2's replies held (2.1-5.6 measured over 13 cut-off replies): a reply of
``max_tokens`` tokens has room for at least this many characters a token."""
JSON_OVERHEAD_CHARS = 80
MIN_CODE_CHARS = 120


def reply_schema(limits: ReplyLimits | None = None, methods: Sequence[str] | None = None) -> dict[str, Any]:
    """:data:`REPLY_SCHEMA`; with ``methods``, the suggestion may hold only those keys (a closed object); with
    ``limits``, every string is held to its share of the reply's length."""
    schema = json.loads(json.dumps(REPLY_SCHEMA))
    if limits is not None:
        schema["properties"]["reasoning"]["maxLength"] = limits.reasoning_chars
    if methods:
        code: dict[str, Any] = {"type": "string"}
        if limits is not None:
            left = limits.reply_chars - limits.reasoning_chars - JSON_OVERHEAD_CHARS
            code["maxLength"] = max(MIN_CODE_CHARS, left // len(methods))
        schema["properties"]["suggestion"] = {"type": "object", "properties": {name: dict(code) for name in methods},
                                              "additionalProperties": False}
    return schema


def reply_format(litellm, model: str, provider: str, supported: frozenset[str] | set[str], api_base: str | None = None,
                 schema: dict[str, Any] | None = None) -> dict[str, Any] | None:
    """The ``response_format`` that holds ``model`` to ``schema`` (default :data:`REPLY_SCHEMA`), or None (then
    the prompt alone asks for the JSON). Sent where litellm lists ``response_format`` among the provider's
    parameters and either says the model takes a schema (``supports_response_schema``: hosted models it knows) or
    the model runs on the user's own server (Ollama, vLLM, llama.cpp, LM Studio: they compile a schema into a
    grammar; litellm cannot know their models). Should such a server still refuse it, the client stops sending
    it (``pipeline/llm/client.py``)."""
    if "response_format" not in supported:
        return None
    own_server = provider in NO_KEY_PROVIDERS or (api_base is not None and provider in LOCAL_SERVER_PROVIDERS)
    if not own_server:
        try:
            known = bool(litellm.supports_response_schema(model=model, custom_llm_provider=provider))
        except Exception:  # noqa: BLE001 - a model litellm cannot place: do not guess
            known = False
        if not known:
            return None
    return {"type": "json_schema",
            "json_schema": {"name": REPLY_SCHEMA_NAME, "schema": schema or REPLY_SCHEMA, "strict": False}}


@dataclass(frozen=True)
class RequestParams:
    """The parameters sent with every request of a run, and those the provider does not accept."""

    sent: dict[str, Any]
    dropped: tuple[str, ...]
    supported: frozenset[str] = frozenset()


def request_params(litellm, model: str, provider: str, *, temperature: float | None, max_tokens: int,
                   seed: int | None, timeout_s: float) -> RequestParams:
    """The sampling parameters for ``model`` that its provider accepts (see the module docstring)."""
    bare = model.split("/", 1)[1] if "/" in model else model
    try:
        supported = set(litellm.get_supported_openai_params(model=bare, custom_llm_provider=provider) or ())
    except Exception:  # noqa: BLE001 - an unknown provider config: send the common core only
        supported = {"temperature", "max_tokens"}
    wanted: dict[str, Any] = {}
    if temperature is not None:
        wanted["temperature"] = temperature
    if seed is not None:
        wanted["seed"] = seed
    # OpenAI's reasoning models (o-series, gpt-5) list temperature yet refuse any value but 1, and count the
    # reply's limit as max_completion_tokens (reasoning tokens included).
    openai_reasoning = provider in OPENAI_REASONING_PROVIDERS and _is_reasoning(litellm, model)
    if openai_reasoning and wanted.get("temperature") not in (None, 1):
        supported.discard("temperature")
    sent: dict[str, Any] = {"model": model, "timeout": timeout_s}
    dropped = []
    for name, value in wanted.items():
        if name in supported:
            sent[name] = value
        else:
            dropped.append(name)
    if openai_reasoning or ("max_tokens" not in supported and "max_completion_tokens" in supported):
        sent["max_completion_tokens"] = max_tokens
    else:
        sent["max_tokens"] = max_tokens
    return RequestParams(sent, tuple(dropped), frozenset(supported))


def _is_reasoning(litellm, model: str) -> bool:
    try:
        return bool(litellm.supports_reasoning(model=model))
    except Exception:  # noqa: BLE001 - unknown models are not reasoning models as far as we know
        return False


def with_cache_breakpoint(provider: str, messages: list[dict[str, str]]) -> list[dict[str, Any]]:
    """``messages`` as sent to ``provider``: for Anthropic, the system text and the user text up to
    :data:`CACHE_BREAKPOINT` become cached content blocks. The text itself is unchanged (the prompt hash is
    taken of the plain messages), so caching never changes what the model reads."""
    if provider not in CACHE_CONTROL_PROVIDERS:
        return messages
    out: list[dict[str, Any]] = []
    for message in messages:
        content = message["content"]
        if message["role"] == "system":
            out.append({"role": "system", "content": [
                {"type": "text", "text": content, "cache_control": {"type": "ephemeral"}}]})
        elif message["role"] == "user" and CACHE_BREAKPOINT in content:
            cut = content.index(CACHE_BREAKPOINT) + 2  # the blank line stays with the cached head
            out.append({"role": "user", "content": [
                {"type": "text", "text": content[:cut], "cache_control": {"type": "ephemeral"}},
                {"type": "text", "text": content[cut:]}]})
        else:
            out.append(message)
    return out


@dataclass(frozen=True)
class Price:
    """USD per token, from litellm's price table."""

    input: float
    output: float
    cached_input: float | None = None

    def cost(self, input_tokens: int, output_tokens: int) -> float:
        return input_tokens * self.input + output_tokens * self.output


def price(model: str) -> Price | None:
    """litellm's price of ``model``, or None when it has none (local and unknown models)."""
    from pipeline.llm.tokens import import_litellm

    litellm = import_litellm()
    try:
        info = litellm.get_model_info(model=model)
    except Exception:  # noqa: BLE001 - litellm raises for models it cannot map
        return None
    if not info.get("input_cost_per_token") and not info.get("output_cost_per_token"):
        return None
    return Price(info.get("input_cost_per_token") or 0.0, info.get("output_cost_per_token") or 0.0,
                 info.get("cache_read_input_token_cost"))
