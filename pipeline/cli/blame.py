"""``codearcade blame RUN``: a version's code with the iteration and LLM call that wrote each line."""

from __future__ import annotations

import argparse

from pipeline.cli.common import (EXIT_OK, add_run, add_store, non_negative_int, open_store, resolve_run, short_id, show,
                                 show_json)


def add_parser(verbs) -> None:
    """Add ``blame`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "blame",
        help="show a policy version's code with the iteration and LLM call that wrote each line",
        description="Print the trainable methods of a policy version of a run, each line annotated with the "
        "iteration that introduced it, that version's short id and the LLM call that wrote it, carried across "
        "versions like `git blame` (table policy_lines, view line_blame). The version is the run's best unless "
        "--version or --iteration names another.",
    )
    add_run(p)
    which = p.add_mutually_exclusive_group()
    which.add_argument("--version", metavar="V", help="policy version id, or a unique prefix of one (default: the best)")
    which.add_argument("--iteration", type=non_negative_int, metavar="I", help="the version evaluated in iteration I")
    p.add_argument("--json", action="store_true", help="print the annotated lines as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from viewers.blame import blame, format_blame

    store = open_store(args)
    run_id = resolve_run(store, args.run_id, verb="blame")
    # neither given: the run's best, a served run's by validation (store.comparisons.resolve_version)
    report = blame(store, run_id, args.version, args.iteration)
    if args.json:
        show_json(report, default=str)
    else:  # each line of it terminal-safe already (a policy's own lines)
        show(format_blame({**report, "run_id": short_id(store, report["run_id"])}), multiline=True)
    return EXIT_OK

