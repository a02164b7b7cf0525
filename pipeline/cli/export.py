"""``codearcade export RUN --otlp URL``: send a run to an OpenTelemetry receiver as one trace."""

from __future__ import annotations

import argparse

from pipeline.cli.common import (EXIT_OK, CliError, add_run, add_store, non_negative_int, open_store, positive_seconds,
                                 resolve_run, short_id, show, show_json)


def add_parser(verbs) -> None:
    """Add ``export`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "export",
        help="send a run to an OpenTelemetry receiver as traces (OTLP)",
        description="Send a stored run as one OpenTelemetry trace: a span for the run, one per iteration (score, "
        "best score, update status, policy version, rolled back), under it the LLM call(s) named and attributed "
        "after the gen_ai semantic conventions, the training rollout and the evaluation episodes (return, "
        "length, end reason), all with their stored times. Opens in Arize Phoenix, Langfuse, Jaeger, Grafana "
        "Tempo or any OTLP receiver. Ids come from the run id, so exporting again sends the same spans "
        "(viewers/otlp_export.py says what receivers do with them).",
    )
    add_run(p)
    p.add_argument("--otlp", required=True, metavar="URL",
                   help="the receiver: for http/protobuf its base URL (e.g. http://127.0.0.1:4318, Phoenix "
                   "http://127.0.0.1:6006; /v1/traces is appended unless the URL ends with it), for grpc its "
                   "address (e.g. http://127.0.0.1:4317)")
    p.add_argument("--protocol", choices=["http/protobuf", "grpc"], default="http/protobuf",
                   help="OTLP transport (default: http/protobuf)")
    p.add_argument("--header", action="append", default=[], metavar="KEY=VALUE",
                   help="a header to send with every request, e.g. Authorization=Bearer... (repeatable; "
                   "OTEL_EXPORTER_OTLP_HEADERS is read when none is given)")
    p.add_argument("--service-name", default="codearcade", metavar="NAME",
                   help="service.name of the spans, also Phoenix's project (default: codearcade)")
    p.add_argument("--max-text-chars", type=non_negative_int, default=None, metavar="N",
                   help="characters kept of each prompt message, reply and feedback text (default: 32000; 0 sends "
                   "no texts, only numbers and names)")
    p.add_argument("--timeout", type=positive_seconds, default=10.0, metavar="SECONDS",
                   help="per request, retries included (default: 10)")
    p.add_argument("--json", action="store_true", help="print what was sent as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from viewers.otlp_export import DEFAULT_TEXT_LIMIT, export_run

    headers = {}
    for item in args.header:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise CliError(f"--header {item!r} is not KEY=VALUE; e.g. --header 'Authorization=Bearer TOKEN'")
        headers[key.strip()] = value.strip()
    store = open_store(args)
    report = export_run(store, resolve_run(store, args.run_id), args.otlp, protocol=args.protocol,
                        timeout_s=args.timeout, headers=headers or None, service_name=args.service_name,
                        text_limit=DEFAULT_TEXT_LIMIT if args.max_text_chars is None else args.max_text_chars)
    if args.json:
        show_json(report.as_dict())
    else:
        names = {"run": ("run", "runs"), "iteration": ("iteration", "iterations"), "llm_call": ("LLM call", "LLM calls"),
                 "episode": ("episode", "episodes")}
        kinds = ", ".join(f"{n} {names.get(kind, (kind, kind))[n != 1]}" for kind, n in report.spans.items())
        show(f"run {short_id(store, report.run_id)}: {sum(report.spans.values())} spans ({kinds}) sent to "
             f"{report.endpoint} ({report.protocol}); trace id {report.trace_id}")
    return EXIT_OK
