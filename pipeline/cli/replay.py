"""``codearcade replay RUN``: re-run an optimization from its stored replies and report where it diverges."""

from __future__ import annotations

import argparse
import sys

from pipeline.cli.common import (EXIT_EPISODE_FAILED, EXIT_OK, CliError, add_run, add_store, open_store, resolve_run,
                                 short_ids, show, show_json)


def add_parser(verbs) -> None:
    """Add ``replay`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "replay",
        help="re-run an optimization from its stored LLM replies and report divergence",
        description="Re-run an optimization run as a new run (kind replay), answering each LLM call with the "
        "reply stored for the same prompt. Reports per iteration whether prompts and scores match the original, "
        "and stops where they diverge (exit 1), or, for a run that stopped before its end, where its record ends "
        "(exit 0).",
    )
    add_run(p)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from store.recorded import read_recorded
    from pipeline.optimizer.replay import replay
    from store.locks import run_is_live
    from store.readers import get_run
    from store.scores import score_text

    store = open_store(args)
    run_id = resolve_run(store, args.run_id, kinds=("optimize",), verb="replay")
    if run_is_live(store.path, run_id):  # its record still grows: a replay would stop where it is now, "interrupted"
        raise CliError(f"run {short_ids(store).get(run_id, run_id)} is still running: replay it once it has "
                       "finished or stopped")
    with store.read() as con:
        iterations = read_recorded(get_run(con, run_id)["config"], run_id).get("iterations")

    def replayed(item) -> None:  # progress: a long run replays for minutes (its episodes are played again)
        score = "forfeit" if item.score is None else score_text(item.score)
        show(f"replayed iteration {item.iteration} of {iterations}: score {score}, update {item.update_status}",
             file=sys.stderr, flush=True)

    report = replay(store, run_id, log=lambda line: show(line, file=sys.stderr), on_iteration=replayed)
    if args.json:
        show_json(report.as_dict())
    else:
        short = short_ids(store)
        show(f"replay of {short.get(report.original_run_id, report.original_run_id)} as "
             f"{short.get(report.replay_run_id, report.replay_run_id)}: {report.status}")
        show(f"{'iteration':>9}  {'prompt':<14} {'original':>9} {'replay':>9}")
        for r in report.rows:
            same = "same" if r.original_prompt == r.replay_prompt else "not recorded" if r.original_prompt is None \
                else "not replayed" if r.replay_prompt is None else "DIFFERENT"
            o = "-" if r.original_score is None else f"{r.original_score:.1f}"
            n = "-" if r.replay_score is None else f"{r.replay_score:.1f}"
            show(f"{r.iteration:>9}  {same:<14} {o:>9} {n:>9}")
        if report.diverged_at is not None:
            show(f"first divergence at iteration {report.diverged_at}")
        elif report.record_ends is not None:  # an unfinished run: replayed as far as it goes, nothing diverged
            show(f"{report.record_ends}: replayed up to there, nothing diverged" if report.status == "incomplete"
                 else f"{report.record_ends}: the replay went on past it, nothing diverged")
    return EXIT_OK if report.diverged_at is None else EXIT_EPISODE_FAILED
