"""``codearcade audit RUN``: the held-out audit of a stored run (``pipeline/optimizer/audit.py``), played again.

A run is audited when it finishes (``--audit-episodes``, default 3); this plays the audit of any stored
optimization run on demand (a run made before audits existed, one that stopped early, or with more games) and
replaces the run's earlier audit. A served run's audit is its finalize's (``codearcade serve --finalize``), shown as
stored: nothing is played for it, and a served run without one is refused with the command that goes on.
"""

from __future__ import annotations

import argparse
import sys

from pipeline.cli.common import (EXIT_BAD_INPUT, EXIT_OK, CliError, EpisodeProgress, add_run, add_store, command_text,
                                 open_store, positive_int, resolve_run, short_id, show, show_json, whole_number_within)
from pipeline.play.config import MAX_EPISODES


def add_parser(verbs) -> None:
    """Add ``audit`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "audit",
        help="play a run's best version and its starting policy on sealed held-out games the loop never saw",
        description="The held-out audit of an optimization run: its best version and its starting policy play N "
        "games each on audit seeds drawn now from the OS's entropy (from 1,000,000 up: never played by the loop, "
        "never shown to the model, unknowable to a policy in advance), under the standard protocol (sticky actions "
        "0.25, up to 30 no-op starts; held out) and under the run's own (the tuning game again). The scores, with "
        "their intervals, are stored beside the tuning scores (table audits, with the seeds; runs, report) and the "
        "run is flagged overfit when less than half of its best version's gain over the starter holds up.",
        epilog="examples: codearcade audit last   |   codearcade audit my-run --episodes 10 --json   |   "
               "codearcade audit my-run --seeds 1234567,7654321 (an earlier audit's games again)",
    )
    add_run(p)
    # at most an evaluation's episodes: --episodes 99999999999999999999 said "Sample larger than population"
    p.add_argument("--episodes", type=whole_number_within(1, MAX_EPISODES), metavar="N",
                   help="games per version and protocol (default: the run's --audit-episodes, or 3)")
    p.add_argument("--seeds", type=_seeds, metavar="S,S,...",
                   help="play these audit seeds instead of drawing new ones (an earlier audit's, from its audits row "
                        "or episodes, to reproduce it); their number is the number of games")
    p.add_argument("--workers", type=positive_int, metavar="N", help="episodes played at once (default: the run's)")
    p.add_argument("--json", action="store_true", help="print the audit's rows as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def _seeds(text: str) -> list[int]:
    from pipeline.optimizer.audit import check_audit_seeds

    try:
        return check_audit_seeds((int(part) for part in text.split(",") if part.strip()), one_game=None)
    except ValueError as err:
        message = str(err) if "--seeds" in str(err) else f"{text!r} is not a list of whole numbers"
        raise argparse.ArgumentTypeError(message.removeprefix("--seeds: ")) from None


def run(args: argparse.Namespace) -> int:
    from pipeline.optimizer.audit import audit_run

    if args.seeds is not None and args.episodes is not None and args.episodes != len(args.seeds):
        show(f"codearcade audit: --episodes {args.episodes} and {len(args.seeds)} --seeds disagree: leave out "
             f"--episodes (the seeds are the games)", file=sys.stderr)
        return EXIT_BAD_INPUT
    store = open_store(args)
    run_id = resolve_run(store, args.run_id, kinds=("optimize", "serve"), verb="audit")
    if _served(store, run_id):
        return _served_audit(store, run_id, args)
    from store.locks import run_is_live

    if run_is_live(store.path, run_id):
        show(f"codearcade: run {short_id(store, run_id)} is still running: this audits its best version so far",
             file=sys.stderr)
    progress: list[EpisodeProgress] = []

    def playing(total: int) -> None:
        progress.append(EpisodeProgress(total, f"audit of {short_id(store, run_id)}"))

    try:
        try:
            result = audit_run(store, run_id, episodes=args.episodes, workers=args.workers, on_demand=True,
                               seeds=args.seeds, on_play=playing,
                               progress=lambda i, played: progress and progress[0].update(i, played),
                               on_episode=lambda i, length: progress and progress[0].finished(i, length))
        finally:
            for bar in progress:
                bar.close()
    except KeyboardInterrupt:
        show(f"codearcade audit: stopped before its end: run {short_id(store, run_id)} keeps the audit it had "
             "(this one's games are not kept); run the command again to audit it", file=sys.stderr)
        raise
    if not result.rows:
        raise CliError(f"run {short_id(store, run_id)} has no iteration to audit: it stopped before its starting "
                       "policy was assessed")
    if args.json:
        show_json({"run_id": run_id, "overfit": result.overfit, "audits": result.rows}, default=str)
    else:
        for line in result.lines():
            show(line)
    return EXIT_OK


def _served(store, run_id: str) -> bool:
    from store.readers import get_run

    with store.read() as con:
        return get_run(con, run_id)["kind"] == "serve"


def _served_audit(store, run_id: str, args: argparse.Namespace) -> int:
    """A served run's audit is its finalize (``pipeline/serve/protocol.py``): its validation pool and the held-out
    pool of the best by validation, shown as stored (``codearcade serve --finalize RUN`` plays them). A served run
    without them is refused in one line with the command that makes them: this plays nothing for a served run."""
    from pipeline.cli.serve import served_lines
    from pipeline.optimizer.audit import AuditResult
    from store.readers import audits
    from store.runs import unsubmitted

    with store.read() as con:
        rows = audits(con, run_id)
        empty = not rows and unsubmitted(con, run_id)
    short = short_id(store, run_id)
    if empty:  # nothing played, nothing to play: not a success (finalize refuses such a run too)
        raise CliError(f"run {short} is served and holds no submission: there is nothing to audit; "
                       f"`{command_text(store, 'serve', '--resume', short)}` serves it again")
    if not rows:  # its pools are played by its finalize, which changes the run: the person asks for that by name
        raise CliError(f"run {short} is served and not finalized yet: its validation and held-out pools are not "
                       f"played; `{command_text(store, 'serve', '--finalize', short)}` plays them")
    if args.json:
        show_json({"run_id": run_id, "overfit": AuditResult(run_id, rows).overfit, "audits": rows}, default=str)
    else:
        for line in served_lines(rows):
            show(line)
    return EXIT_OK
