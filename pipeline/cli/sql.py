"""``codearcade sql``: one read-only query on the store, printed as a table, CSV or JSON; ``--schema`` lists what
there is to query."""

from __future__ import annotations

import argparse
import re
import sys

from pipeline.cli.common import EXIT_OK, CliError, add_store, non_negative_int, open_store, short_ids, show, show_json


def add_parser(verbs) -> None:
    """Add ``sql`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "sql",
        help="run a read-only SQL query on the store",
        description="Run one read-only SQL query (DuckDB dialect) on the store and print the result: an aligned "
        "table, CSV or JSON. One statement per call: SELECT (WITH, FROM, VALUES, SHOW, DESCRIBE, SUMMARIZE), "
        "EXPLAIN, PRAGMA or CALL; the store is opened read-only with DuckDB's external access off (no ATTACH, "
        "COPY, EXPORT, INSTALL, nor reading other files). Works while a run is writing to the store (it waits "
        "between the run's writes). `codearcade sql --schema` lists every table, view and macro with one line "
        "each; docs/schema.md describes their columns. The macro run(ref) takes a run as every verb does: "
        "WHERE run_id = run('last') (or last~1, -2, a label, a unique prefix of an id).",
        epilog="examples: codearcade sql \"SELECT * FROM run_summary ORDER BY created_at DESC\"   |   "
        "codearcade sql \"SELECT iteration, score FROM learning_curve WHERE run_id = run(?) ORDER BY iteration\" "
        "--param last   |   codearcade sql --schema",
    )
    p.add_argument("query", metavar="SQL", nargs="?", help="the query; '-' reads it from stdin")
    p.add_argument("--param", action="append", default=[], metavar="VALUE",
                   help="a value for the query's parameters, repeatable: one per ? (or $1, $2, ...), in order; "
                   "NAME=VALUE (or $NAME=VALUE) for $NAME; cast to the type its place asks for")
    p.add_argument("--schema", action="store_true",
                   help="list the tables, views and macros of the store with one line each, and nothing else")
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
    from store.views import Result, run_user_query, schema_listing

    if args.schema:
        if args.query is not None or args.param:
            raise CliError("--schema lists what there is to query and runs no query; drop the SQL (and --param)")
        store = open_store(args)
        rows = schema_listing(store)
        _print(args, Result(["name", "kind", "what it holds"], ["VARCHAR"] * 3, rows), max_width=0)
        return EXIT_OK
    if args.query is None:
        raise CliError("give a query, e.g. codearcade sql \"SELECT * FROM run_summary\", or --schema to list the "
                       "tables and views")
    query = sys.stdin.read() if args.query == "-" else args.query
    if not query.strip():
        raise CliError("empty query; give a SQL statement, e.g. codearcade sql \"SELECT * FROM run_summary\"")
    store = open_store(args)
    # read-only for real; the file let go. A table shows --max-rows rows: the rest are counted, not held
    keep = args.max_rows if args.max_rows and not (args.json or args.csv) else None
    result = run_user_query(store, query, args.param, keep)
    _print(args, result, args.max_width)
    if not result.rows and result.columns:
        for line in _why_no_rows(store, query, args.param):
            show(line, file=sys.stderr)
    return EXIT_OK


def _why_no_rows(store, query: str, params: list[str]) -> list[str]:
    """Notes for a query that found nothing while comparing a value that names a run but is no run id (the short
    id `codearcade runs` prints, ``last``, a label): the store keeps ids whole, and ``run(...)`` resolves them."""
    from store.views import run_references_by_value

    notes = []
    short = short_ids(store)
    for text, how, run_ids in run_references_by_value(store, query, params):
        quoted = "'" + text.replace("'", "''") + "'"
        if len(run_ids) > 1:
            what = (f"the start of {len(run_ids)} run ids" if how == "prefix" else f"the label of {len(run_ids)} "
                    "runs")
            notes.append(f"codearcade: note: no rows; {quoted} is {what}, not a run id (ids are stored whole): "
                         f"FROM run_matches({quoted}) lists them, and run(...) with one of their short ids names "
                         f"one, e.g. WHERE run_id = run('{short[run_ids[0]]}')")
            continue
        run = short.get(run_ids[0], run_ids[0])
        what = {"prefix": f"the start of run {run}'s id, and the store keeps ids whole ({len(run_ids[0])} "
                          "characters)",
                "name": f"run {run}'s label, not its id", "recency": f"names run {run} only through run()"}[how]
        notes.append(f"codearcade: note: no rows; {quoted} {'' if how == 'recency' else 'is '}{what}: write "
                     f"run({quoted}) where a run id goes, e.g. WHERE run_id = run({quoted})")
    notes += _runs_named(store, query, short)
    return notes


_RUN_CALL = re.compile(r"\brun\(\s*'((?:[^']|'')*)'\s*\)", re.IGNORECASE)


def _runs_named(store, query: str, short: dict[str, str]) -> list[str]:
    """For a query that found nothing: which run each ``run('...')`` in it names, with its kind and game. ``last``
    is the newest run of any kind: after an ``eval``, ``run('last')`` is that evaluation, which ``learning_curve``
    and the other views of optimizations hold no rows of."""
    from store.readers import get_run
    from store.runs import RECENT_FORM, resolve_run_id

    notes = []
    refs = [m.group(1).replace("''", "'") for m in _RUN_CALL.finditer(query)]
    with store.read() as con:
        for ref in dict.fromkeys(r for r in refs if RECENT_FORM.fullmatch(r.strip())):  # an id or label: as meant
            try:
                run = get_run(con, resolve_run_id(con, ref, store))
            except ValueError:
                continue  # the query itself said why (run() raises the same error)
            notes.append(f"codearcade: note: no rows; run('{ref}') is {run['kind']} run {short.get(run['run_id'])} "
                         f"({run['game']}): last counts runs of every kind")
    return notes


def _print(args: argparse.Namespace, result, max_width: int) -> None:
    from viewers.tables import format_table, records, write_csv

    if args.json:
        show_json(records(result.columns, result.types, result.rows), ensure_ascii=False)
    elif args.csv:
        write_csv(sys.stdout, result.columns, result.rows)
    elif result.columns:
        shown = result.rows[: args.max_rows] if args.max_rows else result.rows
        show(format_table(result.columns, shown, max_width), multiline=True)  # each cell made terminal-safe
        total = len(result.rows) if result.total is None else result.total
        more = total - len(shown)
        show(f"({total} row{'s' * (total != 1)}"
             + (f", {more} not shown: use --max-rows 0, --csv or --json)" if more else ")"))
