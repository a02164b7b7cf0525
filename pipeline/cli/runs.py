"""``codearcade runs``: the runs in the store (view ``run_summary``)."""

from __future__ import annotations

import argparse

from pipeline.cli.common import EXIT_OK, add_store, open_store, show, show_json


def add_parser(verbs) -> None:
    """Add ``runs`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "runs",
        help="list the runs in the store",
        description="List the runs in the store, oldest first: kind, game, model, status, iterations done of "
        "those planned, best score (the mean return for eval runs), episodes and LLM tokens (view run_summary).",
    )
    p.add_argument("--json", action="store_true", help="print the run_summary rows as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from store.locks import run_is_live
    from store.views import run_query
    from viewers.tables import format_table, records

    store = open_store(args)
    result = run_query(store, "SELECT * FROM run_summary ORDER BY created_at, run_id")
    runs = records(result.columns, result.types, result.rows)
    for r, row in zip(runs, result.rows):
        r["_created"] = row[result.columns.index("created_at")]
        if r["status"] == "running" and not run_is_live(store.path, r["run_id"]):
            r["status"] = "interrupted"  # killed: no process holds its lock (`doctor` says the same)
    if args.json:
        show_json([{k: v for k, v in r.items() if k != "_created"} for r in runs])
        return EXIT_OK
    if not runs:
        show(f"no runs in {store.path}")
        return EXIT_OK
    rows = []
    for r in runs:
        done = "-" if r["kind"] == "eval" else f"{r['iterations_done']}/{r['iterations_planned'] or '?'}"
        rows.append((r["run_id"], r["_created"].strftime("%Y-%m-%d %H:%M"), r["kind"], r["game"],
                     r["model"], r["status"], done, None if r["best_score"] is None else round(r["best_score"], 2),
                     r["episodes"], r["total_tokens"]))
    show(format_table(("run", "created (UTC)", "kind", "game", "model", "status", "iterations", "best", "episodes",
                       "tokens"), rows, max_width=32, null="-"), multiline=True)  # labels, models: cells made safe
    return EXIT_OK
