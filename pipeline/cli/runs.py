"""``codearcade runs``: the runs in the store, newest first, with what tells them apart (``store/runs.py``)."""

from __future__ import annotations

import argparse
import os

from pipeline.cli.common import EXIT_OK, CliError, add_store, open_store, positive_int, show, show_json
from store.scores import score_text

KINDS = ("eval", "optimize", "replay", "serve")
STATUSES = ("running", "finished", "failed", "interrupted", "budget", "diverged")
"""``runs.status`` (store/runs.py's RUN_STATUSES, written out so that ``codearcade --help`` imports no store)."""


def add_parser(verbs) -> None:
    """Add ``runs`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "runs",
        help="list the runs in the store, newest first",
        description="List the runs in the store, newest first: the shortest unique prefix of each id (what every "
        "verb takes, as do last, last~N, -N and a label), label, when, kind, game, starting policy file, "
        "strategy, feedback, seed, batch, model, status, iterations done of those planned, best score (the mean "
        "return for eval runs; 'no score' where a forfeit leaves none: store/scores.py), forfeits, episodes and "
        "LLM tokens (view run_summary). The evaluations `codearcade compare` "
        "plays of two versions are left out unless --all.",
    )
    p.add_argument("-n", "--limit", type=positive_int, metavar="N", help="the N newest runs (after the filters)")
    p.add_argument("--game", help="only this game's runs")
    p.add_argument("--kind", choices=KINDS, help="only runs of this kind")
    p.add_argument("--status", choices=STATUSES,
                   help="only runs with this status (interrupted: killed, or running with no live process)")
    p.add_argument("--all", action="store_true", dest="everything",
                   help="also the eval runs `codearcade compare` made to play two versions (made_by = compare)")
    p.add_argument("--json", action="store_true", help="print the run_summary rows as JSON (with short_id)")
    add_store(p)
    p.set_defaults(handler=run)


def _policy(row: dict) -> str | None:
    if row["policy"]:
        return os.path.basename(row["policy"])
    # no file: the game's scaffold (games/scaffolds/), which a replay starts from as its original did
    return "scaffold" if row["kind"] in ("optimize", "replay", "serve") else None


def _best(row: dict) -> float | str | None:
    """The run's best score (an eval run's: its score), or ``no score`` where it has none because of a forfeit (an
    eval run that forfeited an episode; an optimization whose starter forfeited and nothing played out beat it):
    the one rule of store/scores.py, read from run_summary, where such a score is NULL. A served run's says what
    picked it (run_summary.best_by): ``8.5 validation`` once finalized, ``12 training`` before."""
    served = f" {row['best_by']}" if row.get("best_by") in ("validation", "training") else ""
    if row["best_score"] is not None:
        return f"{score_text(row['best_score'])}{served}" if served else round(row["best_score"], 2)
    return f"no score{served}" if row.get("forfeits") or served == " validation" else None


def _audit(row: dict) -> str | None:
    """The best version's held-out score (standard protocol), beside the tuning score: ``11.5 OVERFIT``; ``11.5 no
    reference`` when the starter forfeited its audit games (``store.scores.overfit`` None); ``stale (iteration 3)``
    when the audit played an earlier best than the run's of now (it went on after it: run_summary.audit_stale)."""
    if row.get("audit_stale"):
        return f"stale (iteration {row['audit_iteration']})"
    if row.get("audit_score") is None and row.get("overfit") is None:
        return None
    score = "forfeit" if row["audit_score"] is None else score_text(row["audit_score"])
    return score + (" OVERFIT" if row.get("overfit") else " no reference" if row.get("overfit") is None else "")


def _repairs(row: dict) -> str | None:
    """Repair calls and the updates they saved: ``3 (2 saved)``."""
    if not row.get("repair_calls"):
        return None
    return f"{row['repair_calls']} ({row.get('saved_by_repair') or 0} saved)"


COLUMNS = (  # (heading, value of a run_summary row); a column no listed run has a value in is left out
    ("run", lambda r: r["short_id"]),
    ("name", lambda r: r["name"]),
    ("created (UTC)", lambda r: r["created_at"].strftime("%Y-%m-%d %H:%M")),
    ("kind", lambda r: r["kind"] + (" (compare)" if r["made_by"] == "compare" else "")),
    ("game", lambda r: r["game"]),
    ("policy", _policy),
    # a served run's agent searches as it likes and reads what it asks for, on instances drawn in secret: the loop's
    # strategy, feedback and seed settings, stored with its config, are not what it ran with
    ("strategy", lambda r: None if r["kind"] == "serve" else r["strategy"]),
    ("feedback", lambda r: None if r["kind"] == "serve" else r["feedback"]),
    ("seed", lambda r: None if r["kind"] == "serve" else r["seed"]),
    ("batch", lambda r: r["batch"]),
    ("model", lambda r: r["model"]),
    ("status", lambda r: r["status"]),
    ("iterations", lambda r: None if r["kind"] == "eval"
     else str(r["iterations_done"]) if r["kind"] == "serve"  # submissions: a served run plans none
     else f"{r['iterations_done']}/{'?' if r['iterations_planned'] is None else r['iterations_planned']}"),
    ("best", lambda r: _best(r)),
    ("forfeits", lambda r: r.get("forfeits") or None),
    ("audit", lambda r: _audit(r)),
    ("episodes", lambda r: r["episodes"]),
    ("tokens", lambda r: r["total_tokens"] or None),
    ("repairs", lambda r: _repairs(r)),
    ("models", lambda r: _models(r)),
    ("choice", lambda r: _choice(r)),
)


def _choice(row: dict) -> str | None:
    """An ensemble's latest choice of model and why (``llm_calls.model_choice``), ``ucb per call: gpt-4o 0.97 >
    gpt-4o-mini 0.102``."""
    from viewers.model_choices import short

    return short(row.get("last_choice"))


def _models(row: dict) -> str | None:
    """An ensemble's models: each one's calls, improvements and cost (view model_stats), ``gpt-4o 7c 3i $0.0049``."""
    from viewers.tables import money

    if not row.get("models"):
        return None
    return "; ".join(f"{m['model'].rsplit('/', 1)[-1]} {m['calls']}c {m['improvements']}i"
                     + (f" ${money(m['cost_usd'])}" if m["cost_usd"] is not None else "") for m in row["models"])


def run(args: argparse.Namespace) -> int:
    from store.runs import list_runs
    from viewers.tables import format_table

    store = open_store(args)
    game = args.game
    if game is not None:  # spelt as eval takes it (space-invaders, SpaceInvaders): the name runs are stored under
        from games import UnknownGameError, get_game

        try:
            game = get_game(game).name
        except UnknownGameError:
            pass  # a game no longer known may still have runs; none found is said below
    with store.read() as con:
        runs = list_runs(con, store.path, game=game, kind=args.kind, status=args.status, limit=args.limit,
                         everything=args.everything)
    if args.json:
        show_json(runs, default=str)
        return EXIT_OK
    if not runs and args.game:  # a misspelt game matches nothing: say so, with the name it may have meant
        from games import UnknownGameError, get_game

        try:
            get_game(args.game)
        except UnknownGameError as exc:
            raise CliError(f"--game: {exc}") from None
    if not runs:
        filtered = args.game or args.kind or args.status
        show(f"no runs{' match' if filtered else ''} in {store.path}"
             + ("" if filtered else ": `codearcade eval` or `codearcade optimize` makes one"))
        return EXIT_OK
    table = [[value(r) for _, value in COLUMNS] for r in runs]
    kept = [k for k, (heading, _) in enumerate(COLUMNS)
            if heading in ("run", "status") or any(row[k] is not None for row in table)]
    show(format_table(tuple(COLUMNS[k][0] for k in kept), [tuple(row[k] for k in kept) for row in table],
                      max_width=32, null="-"), multiline=True)  # labels, models, policy files: cells made safe
    return EXIT_OK
