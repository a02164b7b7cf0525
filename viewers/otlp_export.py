"""Export a stored run as OpenTelemetry traces over OTLP (``codearcade export RUN --otlp URL``).

One trace per run, read from the store (``store/run_trace.py``) and sent with the official OpenTelemetry SDK
and OTLP exporters, so the run opens in Arize Phoenix, Langfuse, Jaeger, Grafana Tempo or any OTLP receiver
beside a team's other LLM traces. The span tree::

    optimize pong                         the run (root): game, kind, model, seed, status, error, the best
                                          (view run_best: version, iteration, score, best_by, a finalized served
                                          run's by validation; an eval run: its score, none with a forfeit, and
                                          its forfeits)
    ├── iteration 0                       score (none with a forfeit, which it names), best score so far (a
    │                                     served run's by training score), update status, policy version,
    │                                     rolled back
    │   ├── train rollout                 return, length, lives lost, end reason (the traced rollout)
    │   └── eval episode 0                the same, per evaluation episode
    ├── iteration 1
    │   ├── chat openai/gpt-4o            the LLM call, after the gen_ai semantic conventions
    │   ├── train rollout
    │   └── eval episode 0
    ...

An eval run (no iterations) has its episodes directly under the root, and so has an optimize run its held-out
audit's (kind ``audit``), played after its iterations. LLM call spans are CLIENT spans named
``{gen_ai.operation.name} {gen_ai.request.model}`` with the ``gen_ai.*`` attributes the ``llm_calls`` columns
were named after (``gen_ai.provider.name`` and its older spelling ``gen_ai.system``, request model,
temperature, max tokens, seed, response model, id, finish reasons, input/output and cache tokens,
``error.type``), and the texts as the conventions' opt-in content attributes ``gen_ai.system_instructions``,
``gen_ai.input.messages`` and ``gen_ai.output.messages`` (JSON), each message's text capped. Everything
codearcade adds is under ``codearcade.*``. Each iteration's feedback is an event on its span. The other spans
also carry ``openinference.span.kind`` (AGENT for the run, CHAIN for an iteration, EVALUATOR for an episode),
which Arize Phoenix uses to draw them; it reads the ``gen_ai.*`` attributes of the LLM calls by itself.

Times are the stored ones, never the export's: a run spans ``runs.created_at``..``finished_at``, an iteration
``started_at``..``finished_at``, an LLM call ``created_at - latency_s``..``created_at`` (``created_at`` is
when it ended), an episode ``started_at``..``started_at + duration_s``. A span whose end is not stored (a
run killed mid-way, an iteration whose row was never written) ends at its last child.

Ids are derived from the store, not drawn at random: the trace id from the run id, each span id from the run
id and what the span stands for (``iteration:3``, ``llm:<call id>``, ``episode:<episode id>``). Exporting a
run again therefore sends the very same spans; what a receiver does with them is its own policy: Phoenix keeps
the first copy of a span id and drops repeats (checked in tests/test_otlp_export.py); a receiver that does not
deduplicate span ids (not tested here) stores the repeats under the same trace. A run that grew since (a
resumed run) re-sends its old spans unchanged beside the new ones.
"""

from __future__ import annotations

import hashlib
import json
import logging
import socket
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any, Iterator
from urllib.parse import urlsplit

from opentelemetry import trace
from opentelemetry.sdk.resources import Resource
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor, SpanExportResult
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter
from opentelemetry.sdk.trace.id_generator import IdGenerator
from opentelemetry.sdk.trace.sampling import ALWAYS_ON
from opentelemetry.trace import SpanKind, Status, StatusCode

from store.scores import NO_BEST, score_episodes

PROTOCOLS = ("http/protobuf", "grpc")
"""OTLP transports (the names of ``OTEL_EXPORTER_OTLP_PROTOCOL``)."""

DEFAULT_TEXT_LIMIT = 32_000
"""Characters kept of each prompt message, reply and feedback text (a cut one ends in a marker); 0 sends none
of these texts."""

EXPORT_BATCH = 256
"""Spans per OTLP request."""

FAILED_END_REASONS = ("policy_error", "timeout", "crashed", "tampered")
FAILED_RUN_STATUSES = ("failed", "interrupted", "diverged")

_EPOCH = datetime(1970, 1, 1)


class ExportError(ValueError):
    """The run could not be exported; the one-line message says why and what to do."""


@dataclass
class ExportReport:
    """What was sent: the trace id (32 hex digits), the endpoint, and the spans by what they stand for."""

    run_id: str
    trace_id: str
    endpoint: str
    protocol: str
    spans: dict[str, int] = field(default_factory=dict)
    input_tokens: int = 0
    output_tokens: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "trace_id": self.trace_id, "endpoint": self.endpoint,
                "protocol": self.protocol, "spans": sum(self.spans.values()), "spans_by_kind": self.spans,
                "input_tokens": self.input_tokens, "output_tokens": self.output_tokens}


def export_run(store, run_id: str, url: str, protocol: str = "http/protobuf", timeout_s: float = 10.0,
               headers: dict[str, str] | None = None, service_name: str = "codearcade",
               text_limit: int = DEFAULT_TEXT_LIMIT) -> ExportReport:
    """Read ``run_id`` from ``store`` and send it to the OTLP receiver at ``url``; :class:`ExportError` if the
    receiver cannot be reached or refuses the spans (nothing is retried beyond the exporter's own backoff
    within ``timeout_s``)."""
    from store.run_trace import run_trace_rows

    if protocol not in PROTOCOLS:
        raise ExportError(f"unknown --protocol {protocol!r}; use one of {', '.join(PROTOCOLS)}")
    endpoint = otlp_endpoint(url, protocol)
    with store.read() as con:
        try:
            rows = run_trace_rows(con, run_id, reply_chars=text_limit + 1)  # + 1: a cut reply says it was cut
        except KeyError:
            raise ExportError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs") from None
    spans = build_spans(rows, service_name=service_name, text_limit=text_limit)
    check_reachable(url, endpoint, protocol, timeout_s)
    send_spans(spans, endpoint, protocol, timeout_s, headers)
    report = ExportReport(run_id=run_id, trace_id=f"{trace_id_for(run_id):032x}", endpoint=endpoint, protocol=protocol)
    for span in spans:
        kind = span.attributes.get("codearcade.span")
        report.spans[kind] = report.spans.get(kind, 0) + 1
    report.input_tokens = sum(c["input_tokens"] or 0 for c in rows["llm_calls"])
    report.output_tokens = sum(c["output_tokens"] or 0 for c in rows["llm_calls"])
    return report


# ---- ids and times ------------------------------------------------------------------------------------------

def trace_id_for(run_id: str) -> int:
    """The run's trace id: 128 bits of SHA-256 of the run id (never 0, which OpenTelemetry reserves)."""
    return int.from_bytes(hashlib.sha256(f"codearcade-run:{run_id}".encode()).digest()[:16], "big") or 1


def span_id_for(run_id: str, key: str) -> int:
    """A span's id: 64 bits of SHA-256 of the run id and what the span stands for (never 0)."""
    return int.from_bytes(hashlib.sha256(f"codearcade-span:{run_id}:{key}".encode()).digest()[:8], "big") or 1


def _ns(moment: datetime | None) -> int | None:
    """Nanoseconds since the epoch of a stored (UTC, naive) timestamp, exactly (no float rounding)."""
    if moment is None:
        return None
    return (moment - _EPOCH) // timedelta(microseconds=1) * 1000


def _seconds_ns(seconds: float | None) -> int:
    return int(round((seconds or 0.0) * 1e9))


# ---- spans --------------------------------------------------------------------------------------------------

@dataclass
class _Planned:
    """One span before it is started: everything the tracer needs, with children nested."""

    key: str
    name: str
    kind: str  # codearcade.span: run, iteration, llm_call, episode
    start: int | None
    end: int | None
    attributes: dict[str, Any]
    span_kind: str = "INTERNAL"
    error: str | None = None
    events: list[tuple[str, dict[str, Any], int | None]] = field(default_factory=list)
    children: list["_Planned"] = field(default_factory=list)

    def resolve_times(self) -> tuple[int, int]:
        """Fill a missing start or end from the children (a killed run has no ``finished_at``)."""
        bounds = [child.resolve_times() for child in self.children]
        starts = [b[0] for b in bounds] + ([self.start] if self.start is not None else [])
        ends = [b[1] for b in bounds] + ([self.end] if self.end is not None else [])
        if self.start is None:
            self.start = min(starts) if starts else (min(ends) if ends else 0)
        if self.end is None:
            self.end = max(ends + [self.start])
        self.end = max(self.end, self.start)
        return self.start, self.end


def _attrs(**values: Any) -> dict[str, Any]:
    """Attributes with the ``__`` of keyword names as dots, NULLs dropped (OTLP has no null attribute)."""
    out = {}
    for key, value in values.items():
        if value is None:
            continue
        if isinstance(value, (list, tuple)):
            value = tuple(str(v) for v in value if v is not None)
        out[key.replace("__", ".")] = value
    return out


def _cap(text: str, limit: int, length: int | None = None) -> str:
    """``text`` within ``limit`` characters, a cut one ending in a marker; ``length``: the whole text's, where
    ``text`` is already its start (a reply, cut where it is read)."""
    length = len(text) if length is None else length
    if length > limit:
        return text[:limit] + f"… [cut {length - limit} characters]"
    return text


def _message_text(content: Any) -> str:
    """A stored message's content as text (a string, or provider blocks with ``text``)."""
    if isinstance(content, str):
        return content
    if isinstance(content, list):
        return "".join(block.get("text", "") for block in content if isinstance(block, dict))
    return json.dumps(content)


def _content_attributes(call: dict[str, Any], text_limit: int) -> dict[str, str]:
    """``gen_ai.system_instructions``, ``gen_ai.input.messages`` and ``gen_ai.output.messages`` in the
    conventions' JSON shapes (role, parts of type text)."""
    if not text_limit:
        return {}
    out: dict[str, str] = {}
    try:
        messages = json.loads(call["prompt_text"]) if call["prompt_text"] else []
    except ValueError:
        messages = [{"role": "user", "content": call["prompt_text"]}]
    system = [m for m in messages if m.get("role") == "system"]
    others = [m for m in messages if m.get("role") != "system"]
    if system:
        out["gen_ai.system_instructions"] = json.dumps(
            [{"type": "text", "content": _cap(_message_text(m.get("content")), text_limit)} for m in system])
    if others:
        out["gen_ai.input.messages"] = json.dumps(
            [{"role": m.get("role", "user"),
              "parts": [{"type": "text", "content": _cap(_message_text(m.get("content")), text_limit)}]}
             for m in others])
    if call["reply_text"] is not None:
        finish = (call["finish_reasons"] or ["stop"])[0]
        out["gen_ai.output.messages"] = json.dumps(
            [{"role": "assistant", "parts": [{"type": "text", "content": _cap(call["reply_text"], text_limit,
                                                                       call.get("reply_length"))}],
              "finish_reason": finish}])
    return out


def _llm_span(call: dict[str, Any], text_limit: int) -> _Planned:
    end = _ns(call["created_at"])
    start = end - _seconds_ns(call["latency_s"]) if end is not None else None
    operation = call["operation_name"] or "chat"
    attributes = _attrs(
        codearcade__span="llm_call",
        gen_ai__operation__name=operation,
        gen_ai__provider__name=call["provider_name"],
        gen_ai__system=call["provider_name"],  # the attribute's name before semconv 1.37; many backends key on it
        gen_ai__request__model=call["request_model"],
        gen_ai__request__temperature=call["request_temperature"],
        gen_ai__request__max_tokens=call["request_max_tokens"],
        gen_ai__request__seed=call["request_seed"],
        gen_ai__response__model=call["response_model"],
        gen_ai__response__id=call["response_id"],
        gen_ai__response__finish_reasons=call["finish_reasons"],
        gen_ai__usage__input_tokens=call["input_tokens"],
        gen_ai__usage__output_tokens=call["output_tokens"],
        gen_ai__usage__cache_read__input_tokens=call["cached_input_tokens"],
        gen_ai__usage__cache_creation__input_tokens=call["cache_creation_input_tokens"],
        error__type=call["error_type"],
        codearcade__llm__call_id=call["call_id"],
        codearcade__llm__purpose=call["purpose"],
        codearcade__llm__prompt_hash=call["prompt_hash"],
        codearcade__llm__prompt_tokens_counted=call["prompt_tokens_counted"],
        codearcade__llm__cost_usd=call["cost_usd"],
        codearcade__llm__attempts=call["attempts"],
        codearcade__llm__replayed=call["replayed"],
        codearcade__llm__parse_error=call["parse_error"],
        codearcade__llm__repair_of=call["repair_of"],  # a repair turn: the call whose rejected reply it repairs
        codearcade__llm__repair_turn=call["repair_turn"],
        codearcade__iteration=call["iteration"],
    )
    attributes.update(_content_attributes(call, text_limit))
    error = None
    if call["error_type"]:
        error = f"{call['error_type']}: {call['error_message'] or ''}".strip()[:2000]
    return _Planned(key=f"llm:{call['call_id']}", name=f"{operation} {call['request_model']}", kind="llm_call",
                    start=start, end=end, attributes=attributes, span_kind="CLIENT", error=error)


def _episode_span(episode: dict[str, Any]) -> _Planned:
    start = _ns(episode["started_at"])
    end = start + _seconds_ns(episode["duration_s"]) if start is not None else None
    name = "train rollout" if episode["kind"] == "train" else f"{episode['kind']} episode {episode['episode_index']}"
    attributes = _attrs(
        codearcade__span="episode",
        openinference__span__kind="EVALUATOR",
        codearcade__episode__id=episode["episode_id"],
        codearcade__episode__kind=episode["kind"],
        codearcade__episode__index=episode["episode_index"],
        codearcade__episode__seed=episode["seed"],
        codearcade__episode__return=episode["return"],
        codearcade__episode__length=episode["length"],
        codearcade__episode__lives_lost=episode["lives_lost"],
        codearcade__episode__end_reason=episode["end_reason"],
        codearcade__episode__max_steps=episode["max_steps"],
        codearcade__episode__traced=episode["traced"],
        codearcade__episode__verified=episode["verified"],
        codearcade__episode__env_s=episode["env_s"],
        codearcade__episode__policy_s=episode["policy_s"],
        codearcade__policy_version_id=episode["policy_version_id"],
        codearcade__iteration=episode["iteration"],
    )
    error = None
    if episode["end_reason"] in FAILED_END_REASONS:
        error = f"{episode['end_reason']}: {episode['error'] or ''}".strip()[:2000]
    return _Planned(key=f"episode:{episode['episode_id']}", name=name, kind="episode", start=start, end=end,
                    attributes=attributes, error=error)


def _iteration_span(iteration: int, row: dict[str, Any] | None) -> _Planned:
    if row is None:  # an iteration whose row was never written (the run stopped inside it)
        return _Planned(key=f"iteration:{iteration}", name=f"iteration {iteration}", kind="iteration", start=None,
                        end=None, attributes=_attrs(codearcade__span="iteration", openinference__span__kind="CHAIN",
                                                    codearcade__iteration=iteration,
                                                    codearcade__iteration__complete=False))
    attributes = _attrs(
        codearcade__span="iteration",
        openinference__span__kind="CHAIN",
        codearcade__iteration=iteration,
        codearcade__iteration__complete=True,
        codearcade__score=row["score"],
        # a forfeit has no score (store/scores.py): say why the score is missing, never its partial return
        codearcade__forfeit=row.get("forfeit"),
        codearcade__best_score=row["best_score"],
        codearcade__best_iteration=row["best_iteration"],
        codearcade__best_version_id=row["best_version_id"],
        codearcade__train_return=row["train_return"],
        codearcade__update_status=row["update_status"],
        codearcade__update_rejection=row["rejection"],
        codearcade__rolled_back=row["rolled_back"],
        codearcade__policy_version_id=row["policy_version_id"],
        codearcade__base_version_id=row["base_version_id"],
        codearcade__llm_call_id=row["llm_call_id"],
        codearcade__llm_s=row["llm_s"],
        codearcade__train_s=row["train_s"],
        codearcade__eval_s=row["eval_s"],
        codearcade__wall_s=row["wall_s"],
        codearcade__candidates=row.get("candidates"),
        # the evaluation cache: a version assessed before reuses its episodes; they are spans of that iteration
        codearcade__evaluation=row.get("evaluation"),
        codearcade__episodes_iteration=row.get("episodes_iteration"),
    )
    return _Planned(key=f"iteration:{iteration}", name=f"iteration {iteration}", kind="iteration",
                    start=_ns(row["started_at"]), end=_ns(row["finished_at"]), attributes=attributes)


def plan_spans(rows: dict[str, Any], text_limit: int = DEFAULT_TEXT_LIMIT) -> _Planned:
    """The span tree of a run (see the module docstring), times resolved, not yet started."""
    run = rows["run"]
    run_id = run["run_id"]
    root = _Planned(
        key="run", name=f"{run['kind']} {run['game']}", kind="run", start=_ns(run["created_at"]),
        end=_ns(run["finished_at"]),
        attributes=_attrs(codearcade__span="run", openinference__span__kind="AGENT", codearcade__run__id=run_id,
                          codearcade__run__kind=run["kind"],
                          codearcade__run__status=run["status"], codearcade__run__error=run["error"],
                          codearcade__game=run["game"], codearcade__run__seed=run["seed"],
                          codearcade__run__model=run["model"],
                          codearcade__run__starter_version_id=run["starter_version_id"],
                          codearcade__run__iterations=len(rows["iterations"])),
        error=(f"{run['status']}: {run['error'] or ''}".strip()[:2000]
               if run["status"] in FAILED_RUN_STATUSES else None),
    )
    if rows["iterations"] and rows["best"] is not None:  # the run's outcome, as run_summary gives it (view
        # run_best: validation picks a finalized served run's best; the iterations' best_* are the training best)
        best = rows["best"]
        forfeits = sum(1 for it in rows["iterations"] if it.get("forfeit"))
        root.attributes.update(_attrs(codearcade__best_score=best["score"],
                                      codearcade__best_iteration=best["iteration"],
                                      codearcade__best_version_id=best["policy_version_id"],
                                      codearcade__best_by=best["best_by"],
                                      codearcade__run__forfeits=forfeits or None,
                                      codearcade__run__no_score=NO_BEST if best["score"] is None and forfeits
                                      else None))
    elif rows["episodes"]:  # an eval run's score, by the one rule (store/scores.py): none with a forfeit
        score = score_episodes(e for e in rows["episodes"] if e["kind"] == "eval" and e["return"] is not None)
        root.attributes.update(_attrs(codearcade__run__mean_return=score.ranked, codearcade__run__score=score.ranked,
                                      codearcade__run__forfeits=len(score.forfeits),
                                      codearcade__run__no_score=score.no_score))
    by_iteration = {row["iteration"]: row for row in rows["iterations"]}
    wanted = set(by_iteration) | {c["iteration"] for c in rows["llm_calls"]}
    if run["kind"] != "eval":
        wanted |= {e["iteration"] for e in rows["episodes"] if e["kind"] != "audit"}
    spans = {i: _iteration_span(i, by_iteration.get(i)) for i in sorted(wanted)}
    for call in rows["llm_calls"]:
        spans[call["iteration"]].children.append(_llm_span(call, text_limit))
    for episode in rows["episodes"]:  # the held-out audit is played after the iterations: under the run itself
        in_iteration = run["kind"] != "eval" and episode["kind"] != "audit"
        parent = spans.get(episode["iteration"], root) if in_iteration else root
        parent.children.append(_episode_span(episode))
    for item in rows["feedback"]:
        if item["iteration"] in spans:
            span = spans[item["iteration"]]
            text = _cap(item["text"], text_limit) if text_limit and item["text"] else None
            span.events.append(("codearcade.feedback", _attrs(
                codearcade__feedback__mode=item["mode"], codearcade__feedback__stage=item["stage"],
                codearcade__feedback__score=item["score"], codearcade__feedback__text=text), None))
    root.children.extend(spans[i] for i in sorted(spans))
    root.resolve_times()
    for span in spans.values():  # feedback is written with the iteration's row: stamp it at the iteration's end
        span.events = [(name, attributes, span.end) for name, attributes, _ in span.events]
    return root


class _PlannedIds(IdGenerator):
    """An IdGenerator that hands out the ids chosen for the next span (the SDK asks it at ``start_span``)."""

    def __init__(self, trace_id: int):
        self.trace_id = trace_id
        self.next_span_id = 0

    def generate_trace_id(self) -> int:
        return self.trace_id

    def generate_span_id(self) -> int:
        return self.next_span_id


def build_spans(rows: dict[str, Any], service_name: str = "codearcade", text_limit: int = DEFAULT_TEXT_LIMIT):
    """The run's spans as the SDK's finished (readable) spans, ready for any span exporter, parents first."""
    run = rows["run"]
    run_id = run["run_id"]
    ids = _PlannedIds(trace_id_for(run_id))
    resource = Resource.create(_attrs(service__name=service_name, service__version=run["codearcade_version"],
                                      openinference__project__name=service_name))
    collected = InMemorySpanExporter()
    provider = TracerProvider(resource=resource, id_generator=ids, sampler=ALWAYS_ON)
    provider.add_span_processor(SimpleSpanProcessor(collected))
    tracer = provider.get_tracer("codearcade.export", run["codearcade_version"])

    started: dict[int, int] = {}  # span id -> place in the tree walk (parents before their children)

    def emit(planned: _Planned, parent_context) -> None:
        ids.next_span_id = span_id_for(run_id, planned.key)
        started[ids.next_span_id] = len(started)
        span = tracer.start_span(planned.name, context=parent_context, kind=getattr(SpanKind, planned.span_kind),
                                 attributes=planned.attributes, start_time=planned.start)
        for name, attributes, timestamp in planned.events:
            span.add_event(name, attributes, timestamp=timestamp)
        if planned.error:
            span.set_status(Status(StatusCode.ERROR, planned.error))
        context = trace.set_span_in_context(span)
        for child in planned.children:
            emit(child, context)
        span.end(end_time=planned.end)

    emit(plan_spans(rows, text_limit), None)
    provider.shutdown()
    finished = sorted(collected.get_finished_spans(), key=lambda s: started[s.context.span_id])
    if not finished:
        raise ExportError("the OpenTelemetry SDK made no spans (OTEL_SDK_DISABLED is set?); unset it for this command")
    return finished


# ---- sending ------------------------------------------------------------------------------------------------

def otlp_endpoint(url: str, protocol: str) -> str:
    """The exporter's endpoint for ``--otlp URL``: for http/protobuf, ``/v1/traces`` is appended unless the
    path already ends with it (as ``OTEL_EXPORTER_OTLP_ENDPOINT`` is read); gRPC takes the URL as given."""
    try:
        parts = urlsplit(url.strip())
        parts.port  # noqa: B018 - parsed here: a bad port or a broken [IPv6] literal raises ValueError
    except ValueError:
        parts = None
    if parts is None or parts.scheme not in ("http", "https") or not parts.hostname:
        raise ExportError(f"--otlp {url!r} is not an http(s) URL; give the receiver's address, e.g. "
                          "http://127.0.0.1:4318 (OTLP/HTTP) or http://127.0.0.1:4317 with --protocol grpc")
    if protocol == "grpc":
        return url.strip()
    path = parts.path.rstrip("/")
    if not path.endswith("/v1/traces"):
        path += "/v1/traces"
    return parts._replace(path=path).geturl()


def check_reachable(url: str, endpoint: str, protocol: str, timeout_s: float) -> None:
    """:class:`ExportError` at once if nothing accepts a connection at the URL's host and port (the exporter
    itself would retry with backoff for the whole time-out before saying so less clearly)."""
    parts = urlsplit(endpoint if protocol != "grpc" else url)
    port = parts.port or (443 if parts.scheme == "https" else 80)
    try:
        with socket.create_connection((parts.hostname, port), timeout=min(timeout_s, 5.0)):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ExportError(f"cannot reach the OTLP receiver at {url} ({parts.hostname}:{port}: {reason}); start one "
                          "there (e.g. `phoenix serve`, Jaeger, an OpenTelemetry Collector) or fix --otlp") from None


@contextmanager
def _exporter_messages() -> Iterator[list[str]]:
    """Collect what the OTLP exporters log (their only way of saying why an export failed) instead of letting
    it reach the terminal as log lines."""
    messages: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            messages.append(record.getMessage())

    logger = logging.getLogger("opentelemetry.exporter")
    handler, propagate = Collect(level=logging.WARNING), logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield messages
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _reason(messages: list[str]) -> str:
    """The receiver's answer from the exporter's log lines: the HTTP status, or gRPC's error details."""
    if not messages:
        return "no reason given"
    last = messages[-1].splitlines()[0]
    details = [m.split("Error details:", 1)[1].strip() for m in messages if "Error details:" in m]
    return (details[-1] if details else last)[:240]


def _exporter(endpoint: str, protocol: str, timeout_s: float, headers: dict[str, str] | None):
    if protocol == "grpc":
        from opentelemetry.exporter.otlp.proto.grpc.trace_exporter import OTLPSpanExporter as GrpcExporter

        return GrpcExporter(endpoint=endpoint, insecure=endpoint.startswith("http://"), timeout=timeout_s,
                            headers=headers or None)
    from opentelemetry.exporter.otlp.proto.http.trace_exporter import OTLPSpanExporter as HttpExporter

    return HttpExporter(endpoint=endpoint, timeout=timeout_s, headers=headers or None)


def send_spans(spans, endpoint: str, protocol: str, timeout_s: float, headers: dict[str, str] | None) -> None:
    """Send ``spans`` in batches of :data:`EXPORT_BATCH`; :class:`ExportError` with the receiver's answer if a
    batch is refused (parents go first, so a refusal never leaves children without their parent)."""
    exporter = _exporter(endpoint, protocol, timeout_s, headers)
    try:
        with _exporter_messages() as messages:
            for first in range(0, len(spans), EXPORT_BATCH):
                if exporter.export(spans[first:first + EXPORT_BATCH]) != SpanExportResult.SUCCESS:
                    why = _reason(messages)
                    hint = ("check that the URL is the receiver's OTLP/HTTP address (the path /v1/traces is added) "
                            "or try --protocol grpc" if protocol != "grpc" else
                            "check that the URL is the receiver's OTLP/gRPC address (often port 4317) or try "
                            "--protocol http/protobuf")
                    raise ExportError(f"the OTLP receiver at {endpoint} did not take the spans ({first} of {len(spans)} "
                                      f"sent): {why}; {hint}")
    finally:
        exporter.shutdown()
