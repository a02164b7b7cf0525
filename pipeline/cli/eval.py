"""``codearcade eval POLICY.py``: play a policy file and store every step (and, traced, every call)."""

from __future__ import annotations

import argparse
import os
import sys

from pipeline.cli.common import (EXIT_EPISODE_FAILED, EXIT_OK, FAILED_END_REASONS, EpisodeProgress, add_name,
                                 add_rerun, add_settings, add_store, open_store, rerun_target, short_id, show,
                                 show_json, warn_if_named)
from pipeline.play.config import EvalConfig
from pipeline.settings import declarations

EVAL_OPTIONS = tuple(n for n, (_, s) in declarations(EvalConfig).items() if s.cli)
"""The ``eval`` flags that are :class:`~pipeline.play.config.EvalConfig` fields (declared there)."""


def add_parser(verbs) -> None:
    """Add ``eval`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "eval",
        help="evaluate a policy file and store every step",
        description="Play a policy file (a Python file defining class Policy) and write the run, its episodes, "
        "every step and, with --trace, every call of its bundled methods to the store.",
    )
    p.add_argument("policy", metavar="POLICY.py", help="policy file; may declare GAME = 'pong'")
    add_settings(p, EvalConfig, defaults=True)
    add_name(p, "run")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    add_rerun(p)
    add_store(p)
    p.set_defaults(handler=run)


PAPER_PROTOCOL_NOTE = ("(the paper's protocol: sticky actions 0, no no-op starts, so every seed is the same game and "
                       "the episodes are that one game again; the interval measures only the policy's own random "
                       "draws. --sticky 0.25 --noop-max 30 plays different games)")
"""What ``eval`` adds under the paper's protocol: repeated episodes of it are one game (``store/scores.py``)."""


def run(args: argparse.Namespace) -> int:
    import time

    from pipeline.play.evaluate import evaluate

    given = {name: getattr(args, name) for name in EVAL_OPTIONS}
    if given["workers"] is None:
        given["workers"] = min(args.episodes, os.cpu_count() or 1)
    config = EvalConfig(**given, rerun=rerun_target(args.rerun))
    store = open_store(args, announce=args.json)  # without --json the start line names the store and why
    warn_if_named(store, args.name)
    bar = EpisodeProgress(args.episodes, f"eval {os.path.basename(args.policy)}")
    label = f" '{args.name}'" if args.name else ""

    def started(run_id: str) -> None:  # the run's row is stored: its id can be given to other verbs from now on
        if not args.json:
            # above the bar; made terminal-safe as show() does (the label is the person's text)
            bar.write(f"run {short_id(store, run_id)}{label} started: eval {os.path.basename(args.policy)}, "
                      f"{args.episodes} episode(s); {store.location.describe()}")

    began = time.monotonic()
    try:
        result = evaluate(args.policy, config, store, progress=bar.update, on_episode=bar.finished,
                          run_name=args.name, on_start=started)
    finally:
        bar.close()
    elapsed = time.monotonic() - began
    summary = result.summary()
    short = short_id(store, result.run_id)
    steps = sum(e["length"] for e in summary["episodes"])
    summary.update(short_id=short, name=args.name, elapsed_s=round(elapsed, 3), steps=steps,
                   steps_per_s=round(steps / elapsed, 1) if elapsed > 0 else None)
    failed = [e for e in summary["episodes"] if e["end_reason"] in FAILED_END_REASONS]
    if args.json:
        show_json(summary)
    else:
        show(f"run {short}{label}  game {result.game}  policy {result.policy_version_id}  store {store.path}")
        show(f"{'episode':>7}  {'seed':>5}  {'return':>8}  {'length':>6}  end reason")
        for i, e in enumerate(summary["episodes"]):
            show(f"{i:>7}  {e['seed']:>5}  {e['return']:>8.1f}  {e['length']:>6}  {e['end_reason']}")
        # the one rule (store/scores.py): with any forfeit there is no score ("no score: 5 of 8 episodes
        # forfeited ..."), and the mean of the episodes played out is labelled as not one
        show(f"{result.score.summary()}; {steps:,} steps in {elapsed:.1f} s "
             f"({summary['steps_per_s'] or 0:,.0f} steps/s, setup and checks included)")
        # (not under --one-life-continue: its episodes are the lives of one game, not that game again)
        if result.score.played > 1 and not config.sticky and not config.noop_max and config.one_life != "continue":
            show(PAPER_PROTOCOL_NOTE)
    for e in failed:  # the error is the policy's exception: escape sequences in it must not reach the terminal
        show(f"codearcade: episode {e['episode_id']} ended with {e['end_reason']}: {e['error']}", file=sys.stderr)
    return EXIT_EPISODE_FAILED if failed else EXIT_OK
