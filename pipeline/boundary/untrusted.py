"""Text that came out of policy code (or an LLM's reply) is never trusted as it is.

Whatever a worker process sends back (an episode's error message, a node's exception message, inputs and
output), whatever a candidate's validation reports, and every note composed into feedback passes through
:func:`clean_untrusted_text` before it reaches the store, a prompt or the terminal:

- **size-capped**: at most ``limit`` characters (default :data:`MESSAGE_LIMIT`, 2,000), the rest replaced by a
  marker saying how much was cut (``… [cut 8,388,608 characters]``), so an 8 MB exception message cannot fill
  the store, a terminal or the next prompt;
- **scrubbed of secrets**: the values of this process's environment variables whose names look secret
  (:func:`secret_env_names`: ``*_API_KEY``, ``*KEY``, ``*TOKEN``, ``*SECRET*``, ``*PASSWORD*``, ``*PASSWD*``,
  ``*CREDENTIAL*``, and litellm's provider variables listed in :data:`KNOWN_SECRET_VARIABLES`) and anything shaped
  like a common API key (``sk-...``, ``sk-ant-...``, ``AKIA...``, ``ghp_...``, ``xox?-...``, ``AIza...``,
  ``hf_...``) become ``[redacted]``. Values shorter than :data:`MIN_SECRET_CHARS` are left alone (a
  ``*_KEY`` set to ``1`` must not redact every digit).

:func:`clean_json_text` does the same for a JSON text (a node's inputs and output), keeps it valid JSON, and
holds it to the bounds of ``tracing/bounded.py`` (lists and objects nested at most 64 levels deep: a worker whose
policy raised its recursion limit, or that forged its node table, can send a list nested 3,000 deep, which would
raise ``RecursionError`` in every later reader: the optimizer building its next prompt, ``--resume``);
``to_json``'s own bound runs in the policy's process, so a node table from a policy process with a value nested
deeper is refused before it gets here (``pipeline/boundary/nodes.py``), and this bound holds for the rest. :func:`clean_nodes` applies both
to the string columns of a node table as it arrives from a worker, and :func:`clean_step_objects` to the object
names inside a step table.
"""

from __future__ import annotations

import json
import os
import re
from functools import lru_cache
from typing import TYPE_CHECKING

from tracing.bounded import MAX_DEPTH, bound_json_text

if TYPE_CHECKING:  # pyarrow is imported where Arrow tables are cleaned: the LLM client imports this module for
    import pyarrow as pa  # its scrubbing of secrets, and `codearcade --help` reached pyarrow through it (~0.07 s)

MESSAGE_LIMIT = 2_000
"""Characters kept of one message (an error, an exception message, a validation reason, a feedback note)."""
JSON_LIMIT = 16_000
"""UTF-8 bytes kept of one JSON value (a node's inputs or output: Breakout's observations run to a few KB). Bytes,
not characters: a value of astral characters is held to what it costs the store (4 bytes each), and its escaped
form (``json.dumps`` of a cut value) to about twice that."""
MIN_SECRET_CHARS = 8
"""Environment values shorter than this are not treated as secrets."""
REDACTED = "[redacted]"

KNOWN_SECRET_VARIABLES = frozenset({
    "OPENAI_API_KEY", "ANTHROPIC_API_KEY", "AZURE_API_KEY", "AZURE_AD_TOKEN", "AZURE_OPENAI_API_KEY",
    "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_BEARER_TOKEN_BEDROCK",
    "GEMINI_API_KEY", "GOOGLE_API_KEY", "VERTEXAI_CREDENTIALS", "MISTRAL_API_KEY", "COHERE_API_KEY",
    "CO_API_KEY", "GROQ_API_KEY", "TOGETHERAI_API_KEY", "TOGETHER_API_KEY", "REPLICATE_API_KEY",
    "REPLICATE_API_TOKEN", "HUGGINGFACE_API_KEY", "HF_TOKEN", "HUGGING_FACE_HUB_TOKEN", "OPENROUTER_API_KEY",
    "OR_API_KEY", "DEEPSEEK_API_KEY", "XAI_API_KEY", "PERPLEXITYAI_API_KEY", "PERPLEXITY_API_KEY",
    "FIREWORKS_AI_API_KEY", "FIREWORKS_API_KEY", "DATABRICKS_TOKEN", "DATABRICKS_API_KEY", "WATSONX_APIKEY",
    "WATSONX_TOKEN", "WATSONX_API_KEY", "CLOUDFLARE_API_KEY", "VOYAGE_API_KEY", "NVIDIA_NIM_API_KEY",
    "CEREBRAS_API_KEY", "SAMBANOVA_API_KEY", "AI21_API_KEY", "NLP_CLOUD_API_KEY", "ALEPH_ALPHA_API_KEY",
    "ANYSCALE_API_KEY", "DEEPINFRA_API_KEY", "PREDIBASE_API_KEY", "FRIENDLIAI_API_KEY", "GITHUB_API_KEY",
    "GITHUB_TOKEN", "LITELLM_MASTER_KEY", "LITELLM_API_KEY", "LANGFUSE_SECRET_KEY", "LANGFUSE_PUBLIC_KEY",
    "DATABASE_URL",
})
"""litellm's provider credentials (and a few neighbours) that do not all follow the name patterns."""

_SECRET_NAME = re.compile(r"(KEY|TOKEN|SECRET|PASSWORD|PASSWD|CREDENTIAL|APIKEY)", re.IGNORECASE)
_KEY_SHAPES = re.compile(
    r"sk-ant-[A-Za-z0-9_\-]{8,}"          # Anthropic
    r"|sk-[A-Za-z0-9_\-]{16,}"            # OpenAI and compatible (sk-proj-..., sk-...)
    r"|A(?:KIA|SIA)[0-9A-Z]{16}"          # AWS access key ids
    r"|gh[pousr]_[A-Za-z0-9]{30,}"        # GitHub tokens
    r"|xox[abposr]-[A-Za-z0-9\-]{10,}"    # Slack tokens
    r"|AIza[0-9A-Za-z_\-]{30,}"           # Google API keys
    r"|hf_[A-Za-z0-9]{30,}"               # Hugging Face tokens
)


def secret_env_names(environ: dict[str, str] | None = None) -> list[str]:
    """Names of the environment variables whose values are treated as secrets."""
    environ = os.environ if environ is None else environ
    return sorted(n for n in environ if n in KNOWN_SECRET_VARIABLES or _SECRET_NAME.search(n))


@lru_cache(maxsize=8)
def _secret_pattern(values: tuple[str, ...]) -> re.Pattern | None:
    if not values:
        return None
    return re.compile("|".join(re.escape(v) for v in values))


def _secret_values() -> tuple[str, ...]:
    """The secret environment values long enough to look for, longest first."""
    values = {os.environ[n].strip() for n in secret_env_names()}
    return tuple(sorted((v for v in values if len(v) >= MIN_SECRET_CHARS), key=lambda v: (-len(v), v)))


def _secrets_now() -> re.Pattern | None:
    return _secret_pattern(_secret_values())


def scrub_secrets(text: str) -> str:
    """``text`` with secret environment values and key-shaped strings replaced by ``[redacted]``."""
    pattern = _secrets_now()
    if pattern is not None:
        text = pattern.sub(REDACTED, text)
    return _KEY_SHAPES.sub(REDACTED, text)


def cap(text: str, limit: int = MESSAGE_LIMIT) -> str:
    """At most ``limit`` characters, the cut marked with how many characters went."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}… [cut {len(text) - limit:,} characters]"


def clean_untrusted_text(text: object, limit: int = MESSAGE_LIMIT) -> str | None:
    """Untrusted text as it may be stored, prompted or printed: scrubbed of secrets, then capped; None stays None.

    Scrubbing comes first, on (a generous prefix of) the whole text, so that a secret straddling the cut is
    not left half visible; non-strings are turned into text first; lone surrogates are replaced."""
    if text is None:
        return None
    if not isinstance(text, str):
        text = str(text)
    text = text.encode("utf-8", "replace").decode("utf-8", "replace")
    if len(text) <= limit:
        return cap(scrub_secrets(text), limit)
    head = scrub_secrets(text[: limit + 4096])
    return f"{head[:limit]}… [cut {len(text) - limit:,} characters]"


_LINE_BREAKS = {c: repr(c)[1:-1] for c in "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"}
"""Every character at which ``str.splitlines`` breaks a line, and its escape (``\\n``, ``\\x85``, ``\\u2028``)."""


def single_line(text: str) -> str:
    """Untrusted text on one line, each line break written as its escape: quoted inside a section of a prompt, it
    cannot begin a line of its own (an exception message of ``"\\n\\n#Feedback: ... perfect"`` read as the prompt's
    own header). Scrubbing and capping stay :func:`clean_untrusted_text`'s."""
    return text.translate(_LINE_BREAK_TABLE)


_LINE_BREAK_TABLE = str.maketrans(_LINE_BREAKS)


def utf8_prefix(text: str, limit: int) -> str:
    """The longest prefix of ``text`` whose UTF-8 encoding is at most ``limit`` bytes."""
    if len(text) * 4 <= limit:
        return text
    return text.encode("utf-8", "replace")[:limit].decode("utf-8", "ignore")


def clean_json_text(text: str | None, limit: int = JSON_LIMIT) -> str | None:
    """A JSON text from a worker, scrubbed, capped at ``limit`` UTF-8 bytes and bounded in nesting, and still valid
    JSON (a cut value becomes a JSON string of as much of its text as fits, marked; a value nested too deep, its
    marker: ``tracing/bounded.py``)."""
    if text is None:
        return None
    if not isinstance(text, str):
        text = str(text)
    head = utf8_prefix(text, limit)
    cleaned = scrub_secrets(text) if len(head) == len(text) else None
    if cleaned is not None:
        if cleaned == text:
            return bound_json_text(text, limit, MAX_DEPTH)
        try:
            json.loads(cleaned)
        except (ValueError, RecursionError):
            pass
        else:
            if len(cleaned.encode("utf-8")) <= limit:  # a secret of 8 characters is 10 as "[redacted]"
                return bound_json_text(cleaned, limit, MAX_DEPTH)
    return _as_json_string(clean_untrusted_text(head, limit), len(text) - len(head), limit)


def _as_json_string(shown: str, dropped: int, limit: int) -> str:
    """``shown`` (the cleaned start of a text, ``dropped`` of its characters left out) as a JSON string of at most
    ``limit`` UTF-8 bytes, as much of it as fits, its cut marked. Written as JSON, a quote, a backslash or a line
    break takes two bytes: the first 16,000 bytes of ``[\\n\\n\\n...]`` were stored as 32,000, twice what the store
    was said to hold. The longest start that fits is searched where the bytes would put it were they spread evenly
    over the characters (two or three encodings of a usual text), every other try halving the range (at most ~28
    for a text made to mislead that guess)."""
    def written(kept: int) -> tuple[str, int]:
        left_out = dropped + len(shown) - kept
        cut = f"… [cut {left_out:,} characters]" if left_out else ""
        text = json.dumps(f"{shown[:kept]}{cut}", ensure_ascii=False)
        return text, len(text.encode("utf-8"))

    best, size = written(len(shown))
    if size <= limit:
        return best
    best, fits_size = written(0)  # the marker alone, written even where it does not fit (a tiny limit)
    fits, too_long, long_size, halve = 0, len(shown), size, False
    while too_long - fits > 1:
        if halve:
            middle = (fits + too_long) // 2
        else:
            share = (limit - fits_size) / max(1, long_size - fits_size)
            middle = min(max(fits + int((too_long - fits) * share), fits + 1), too_long - 1)
        halve = not halve
        text, size = written(middle)
        if size <= limit:
            best, fits, fits_size = text, middle, size
        else:
            too_long, long_size = middle, size
    return best


_NODE_TEXT = {"function": 200, "exc_type": 200, "exc_message": MESSAGE_LIMIT, "exc_source": MESSAGE_LIMIT}
_NODE_JSON = ("inputs", "output")


def clean_nodes(nodes: pa.Table | None) -> pa.Table | None:
    """A node table from a worker with its string columns cleaned (:func:`clean_untrusted_text`,
    :func:`clean_json_text`); only columns whose text needs it are rebuilt."""
    if nodes is None or nodes.num_rows == 0:
        return nodes
    for name, limit in _NODE_TEXT.items():
        if name in nodes.column_names:
            nodes = _clean_column(nodes, name, lambda v, limit=limit: clean_untrusted_text(v, limit), limit)
    for name in _NODE_JSON:
        if name in nodes.column_names:
            nodes = _clean_column(nodes, name, clean_json_text, JSON_LIMIT, nested=True)
    return nodes


def clean_step_objects(steps: pa.Table) -> pa.Table:
    """A step table (``tracing.steps.STEP_SCHEMA``) from a worker with the strings inside its ``objects``
    (``key``, ``category``: a handful of distinct names) cleaned; unchanged when they are clean (the usual case)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if steps.num_rows == 0:
        return steps
    objects = steps.column("objects").combine_chunks()
    values = objects.values
    fields = {}
    for name in ("key", "category"):
        column = values.field(name)
        distinct = pc.unique(column)
        # the distinct names checked at once (reading the environment's secrets once, not once per name)
        suspects = _suspects(pa.chunked_array([distinct]), 100)
        if not suspects:
            continue
        names = distinct.to_pylist()
        mapping = {names[i]: clean_untrusted_text(names[i], 100) for i in suspects}
        if any(cleaned != v for v, cleaned in mapping.items()):
            fields[name] = pa.array([mapping.get(v, v) for v in column.to_pylist()], type=pa.string())
    if not fields:
        return steps
    children = [fields.get(f.name, values.field(f.name)) for f in values.type]
    struct = pa.StructArray.from_arrays(children, fields=list(values.type))
    rebuilt = pa.ListArray.from_arrays(objects.offsets, struct, mask=objects.is_null() if objects.null_count else None)
    index = steps.column_names.index("objects")
    return steps.set_column(index, steps.schema.field(index), rebuilt.cast(steps.schema.field(index).type))


def _suspects(column: pa.ChunkedArray, limit: int, nested: bool = False) -> list[int]:
    """Rows of a string column that cleaning could change: too long, a secret's value, or a key's shape; with
    ``nested``, also a JSON text with more opening brackets than the nesting allowed (only such a one can be
    nested too deep). Found with Arrow's vectorised kernels, so the common case (a traced episode's thousands of
    short, clean values) costs a few milliseconds instead of a Python call per value."""
    import pyarrow.compute as pc

    mask = pc.greater(pc.binary_length(column), limit)  # UTF-8 bytes: a cap in characters let astral text be 4 x
    if nested:
        openers = pc.add(pc.count_substring(column, "["), pc.count_substring(column, "{"))
        mask = pc.or_(mask, pc.greater(openers, MAX_DEPTH))
    mask = pc.or_(mask, pc.match_substring_regex(column, _KEY_SHAPES.pattern))
    for value in _secret_values():
        mask = pc.or_(mask, pc.match_substring(column, value))
    mask = pc.fill_null(mask, False)
    if not pc.any(mask).as_py():
        return []
    return pc.indices_nonzero(mask).to_pylist()


def _clean_column(table: pa.Table, name: str, clean, limit: int, nested: bool = False) -> pa.Table:
    import pyarrow as pa

    rows = _suspects(table.column(name), limit, nested)
    if not rows:
        return table
    values = table.column(name).to_pylist()
    for i in rows:
        values[i] = clean(values[i])
    index = table.column_names.index(name)
    return table.set_column(index, table.schema.field(index), pa.array(values, type=pa.string()))
