"""``codearcade sql``: one read-only query on the store, printed as a table, CSV or JSON."""

from __future__ import annotations

import argparse
import sys

from pipeline.cli.common import EXIT_OK, CliError, add_store, non_negative_int, open_store, show, show_json


def add_parser(verbs) -> None:
    """Add ``sql`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "sql",
        help="run a read-only SQL query on the store",
        description="Run one read-only SQL query (DuckDB dialect) on the store and print the result: an aligned "
        "table, CSV or JSON. One statement per call: SELECT (WITH, FROM, VALUES, SHOW, DESCRIBE, SUMMARIZE), "
        "EXPLAIN, PRAGMA or CALL; the store is opened read-only with DuckDB's external access off (no ATTACH, "
        "COPY, EXPORT, INSTALL, nor reading other files). Works while a run is writing to the store (it waits "
        "between the run's writes). "
        "Besides the tables, the views learning_curve, code_metrics, llm_usage, rejected_candidates and "
        "run_summary are there; docs/schema.md describes them all.",
    )
    p.add_argument("query", metavar="SQL", help="the query; '-' reads it from stdin")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", action="store_true", help="print CSV with a header row")
    fmt.add_argument("--json", action="store_true", help="print a JSON list of row objects")
    p.add_argument("--max-width", type=non_negative_int, default=40, metavar="N",
                   help="table mode: cut cells longer than N characters (default: 40; 0: never)")
    p.add_argument("--max-rows", type=non_negative_int, default=1000, metavar="N",
                   help="table mode: print at most N rows (default: 1000; 0: all)")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from store.views import run_user_query
    from viewers.tables import format_table, records, write_csv

    query = sys.stdin.read() if args.query == "-" else args.query
    if not query.strip():
        raise CliError("empty query; give a SQL statement, e.g. codearcade sql \"SELECT * FROM run_summary\"")
    store = open_store(args)
    result = run_user_query(store, query)  # read-only for real; every row is fetched and the file let go first
    if args.json:
        show_json(records(result.columns, result.types, result.rows), ensure_ascii=False)
    elif args.csv:
        write_csv(sys.stdout, result.columns, result.rows)
    elif result.columns:
        shown = result.rows[: args.max_rows] if args.max_rows else result.rows
        show(format_table(result.columns, shown, args.max_width), multiline=True)  # each cell made terminal-safe
        more = len(result.rows) - len(shown)
        show(f"({len(result.rows)} row{'s' * (len(result.rows) != 1)}"
             + (f", {more} not shown: use --max-rows 0, --csv or --json)" if more else ")"))
    return EXIT_OK
