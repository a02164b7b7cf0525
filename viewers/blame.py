"""``codearcade blame``: a policy version's trainable methods, each line annotated with where it came from.

Each line shows the iteration that introduced it, that version's short id and the LLM call that wrote it
(``-`` for lines of the starting policy), and, where the version was played traced, in how many calls the line
ran (0: never; blank for lines without code), read from the ``line_blame`` and ``line_coverage`` views (``store/lines.py`` explains how
the origins are carried). The version is the run's best unless one is named, by id (or a unique prefix of
one) or by the iteration that evaluated it; an iteration that wrote no version of its own (its update rejected,
unchanged or failed) evaluated the version the run held, an earlier iteration's, and one line says so. Runs stored
before migration 7 get their lines computed the first time they are blamed.
"""

from __future__ import annotations

from typing import Any

from store import Store
from store.comparisons import resolve_version
from store.lines import backfill_lines, has_lines, version_blame
from store.readers import first_iteration_of, get_run, iteration_update, version_of_iteration
from store.runs import resolve_run_id
from viewers.safe_text import terminal_text

SHORT_VERSION = 8
SHORT_CALL = 12
"""Leading characters of a call id shown: a ULID's 10 time characters and 2 more, unique within a run."""


def _resolve_version(con: Any, run_id: str, version: str | None, iteration: int | None) -> tuple[str, int]:
    """(version id, the first iteration that stored it) of what was asked; ValueError saying what exists."""
    if iteration is not None:
        version = version_of_iteration(con, run_id, iteration)
    chosen = resolve_version(con, run_id, version if version is not None else "best")
    return chosen, first_iteration_of(con, run_id, chosen)


_NO_VERSION = {"rejected": "its update was rejected", "unchanged": "its update changed nothing",
               "llm_error": "its LLM call failed"}
"""Why an iteration wrote no version of its own, by its ``update_status`` (docs/schema.md, ``iterations``)."""


def _not_its_own(asked: int, first: int | None, update_status: str | None, proposed: list[str]) -> str:
    """One line: the version shown for ``--iteration asked`` is not one that iteration wrote, and why; with the
    versions its candidates proposed and were refused (``proposed``), which ``--version`` shows."""
    why = _NO_VERSION.get(update_status or "", f"it evaluated iteration {first}'s version again")
    seen = (f"; its candidate{'s' if len(proposed) > 1 else ''} {', '.join(v[:SHORT_VERSION] for v in proposed)}: "
            f"--version {proposed[0][:SHORT_VERSION]}") if proposed else ""
    return (f"iteration {asked} wrote no version of its own ({why}): shown is the version it evaluated, "
            f"iteration {first}'s{seen}")


def blame(store: Store, run: str, version: str | None = None, iteration: int | None = None) -> dict[str, Any]:
    """The blame of one version of a run as plain data: run, version, and per method its annotated lines; with
    ``iteration``, ``note`` says when the version shown is an earlier iteration's (None otherwise)."""
    note = None
    with store.read() as con:
        run_id = resolve_run_id(con, run, store)
        version_id, first = _resolve_version(con, run_id, version, iteration)
        if iteration is not None and first != iteration:
            status, proposed = iteration_update(con, run_id, iteration)
            refused = [v for v in dict.fromkeys(proposed) if v != version_id]
            note = _not_its_own(iteration, first, status, refused)
        missing = not has_lines(con, run_id, version_id)
    if missing:  # a run stored before migration 7: compute its versions' lines once
        with store.write() as con:
            backfill_lines(con, run_id)
    with store.read() as con:
        game = get_run(con, run_id)["game"]
        best = resolve_version(con, run_id, "best")
        rows = version_blame(con, run_id, version_id)
    functions: list[dict[str, Any]] = []
    for row in rows:
        if not functions or functions[-1]["name"] != row["function"]:
            functions.append({"name": row["function"], "lines": []})
        functions[-1]["lines"].append({k: v for k, v in row.items() if k != "function"})
    return {"run_id": run_id, "game": game, "policy_version_id": version_id, "iteration": first,
            "best": version_id == best, "asked_iteration": iteration, "note": note, "functions": functions}


def format_blame(report: dict[str, Any]) -> str:
    """The report as text: a header per method, then ``iteration version call ran line_no text`` per line; each
    line terminal-safe (``viewers/safe_text.py``)."""
    out = [f"run {report['run_id']} ({report['game']}), policy version {report['policy_version_id']} "
           f"(iteration {report['iteration']}{', the best' if report['best'] else ''})"]
    if report.get("note"):
        out.append(report["note"])
    for function in report["functions"]:
        out.append("")
        out.append(f"{'iter':>4}  {'version':<{SHORT_VERSION}}  {'llm call':<{SHORT_CALL}}  {'ran':>6}  "
                   f"{function['name']}")
        for line in function["lines"]:
            call = (line["origin_call_id"] or "-")[:SHORT_CALL]
            ran = "" if line["times_ran"] is None or not line["executable"] else line["times_ran"]
            out.append(f"{line['origin_iteration']:>4}  {line['origin_version_id'][:SHORT_VERSION]:<{SHORT_VERSION}}  "
                       f"{call:<{SHORT_CALL}}  {ran:>6} {line['line_no']:>4}  {line['text']}")
    if not report["functions"]:
        out.append("(the version has no trainable methods)")
    return "\n".join(terminal_text(line) for line in out)  # a policy's line may hold escape sequences
