"""The ``codearcade`` command line: one verb per job, each with ``--store`` and ``--help``.

Exit codes: 0 success; 1 the job ran but an episode ended in a policy error, time-out or crash; 2 bad input
(unknown game, missing or broken policy file, unusable store), with a one-line message on stderr; 130
interrupted.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Callable, Sequence

from pipeline.games import GAMES

EXIT_OK, EXIT_EPISODE_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
FAILED_END_REASONS = ("policy_error", "timeout", "crashed")


class CliError(Exception):
    """A user error with a one-line message; exits with code 2."""


def _add_store(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--store",
        default=None,
        metavar="PATH",
        help="DuckDB store file (default: $CODEARCADE_STORE or ./codearcade.duckdb)",
    )


def _store(args: argparse.Namespace):
    from store import Store

    return Store(args.store) if args.store else Store()


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be within [0, 1], got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="codearcade",
        description="Game-playing agents whose policies are Python programs, improved by an LLM; "
        "every step and call in a DuckDB store.",
        epilog="Run `codearcade VERB --help` for a verb's options.",
    )
    verbs = parser.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True

    p = verbs.add_parser(
        "eval",
        help="evaluate a policy file and store every step",
        description="Play a policy file (a Python file defining class Policy) and write the run, its episodes, "
        "every step and, with --trace, every call of its bundled methods to the store.",
    )
    p.add_argument("policy", metavar="POLICY.py", help="policy file; may declare GAME = 'pong'")
    p.add_argument("--game", help=f"game to play: {', '.join(GAMES)} (default: the file's GAME)")
    p.add_argument("--episodes", type=_positive_int, default=1, help="evaluation episodes (default: 1)")
    p.add_argument("--max-steps", type=_positive_int, default=4000,
                   help="cut an episode off after this many steps, reported as truncated (default: 4000, the paper's)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode; episode i uses seed+i (default: 0)")
    p.add_argument("--trace", action="store_true", help="record a node for every call of a bundled method")
    p.add_argument("--sticky", type=_probability, default=0.0,
                   help="sticky-action probability (default: 0.0, the paper's; 0.25 with --noop-max 30 is the "
                   "standard stochastic protocol)")
    p.add_argument("--noop-max", type=_non_negative_int, default=0,
                   help="up to this many random NOOPs after reset (default: 0)")
    p.add_argument("--workers", type=_non_negative_int, default=None,
                   help="episodes played at once in worker processes (default: min(episodes, cores)); "
                   "0 plays in this process without isolation, for debugging")
    p.add_argument("--call-time-limit", type=float, default=1.0, metavar="SECONDS",
                   help="time limit of one policy call (default: 1.0)")
    p.add_argument("--episode-time-limit", type=float, default=900.0, metavar="SECONDS",
                   help="wall-clock limit of one episode (default: 900)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    _add_store(p)
    p.set_defaults(handler=cmd_eval)
    return parser


def _progress_bar(total: int, description: str, per_episode: int):
    """A tqdm bar over all episodes' steps, and the callback the executor reports to."""
    from tqdm import tqdm

    tqdm.monitor_interval = 0  # no monitor thread: episode workers are forked from this process
    bar = tqdm(total=total, desc=description, unit="step", disable=None, dynamic_ncols=True, leave=False)
    seen: dict[int, int] = {}

    def update(index: int, steps: int) -> None:
        bar.update(steps - seen.get(index, 0))
        seen[index] = steps

    def finish(index: int) -> None:
        bar.update(per_episode - seen.get(index, 0))
        seen[index] = per_episode

    return bar, update, finish


def cmd_eval(args: argparse.Namespace) -> int:
    from pipeline.evaluate import EvalConfig, evaluate

    workers = args.workers if args.workers is not None else min(args.episodes, os.cpu_count() or 1)
    config = EvalConfig(
        game=args.game, episodes=args.episodes, max_steps=args.max_steps, seed=args.seed, trace=args.trace,
        sticky=args.sticky, noop_max=args.noop_max, workers=workers, call_time_limit_s=args.call_time_limit,
        episode_time_limit_s=args.episode_time_limit,
    )
    store = _store(args)
    bar, update, _ = _progress_bar(args.episodes * args.max_steps, f"eval {os.path.basename(args.policy)}",
                                   args.max_steps)
    try:
        result = evaluate(args.policy, config, store, progress=update)
    finally:
        bar.close()
    summary = result.summary()
    failed = [e for e in summary["episodes"] if e["end_reason"] in FAILED_END_REASONS]
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"run {result.run_id}  game {result.game}  policy {result.policy_version_id}  store {store.path}")
        print(f"{'episode':>7}  {'seed':>5}  {'return':>8}  {'length':>6}  end reason")
        for i, e in enumerate(summary["episodes"]):
            print(f"{i:>7}  {e['seed']:>5}  {e['return']:>8.1f}  {e['length']:>6}  {e['end_reason']}")
        returns = [e["return"] for e in summary["episodes"]]
        print(f"mean return {sum(returns) / len(returns):.2f} over {len(returns)} episode(s)")
    for e in failed:
        print(f"codearcade: episode {e['episode_id']} ended with {e['end_reason']}: {e['error']}", file=sys.stderr)
    return EXIT_EPISODE_FAILED if failed else EXIT_OK


def _user_errors() -> tuple[type[BaseException], ...]:
    from pipeline.games import UnknownGameError
    from store import StoreError
    from tracing.policy_file import PolicyLoadError

    return (CliError, PolicyLoadError, UnknownGameError, StoreError, ValueError)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] = args.handler
    try:
        return handler(args)
    except KeyboardInterrupt:
        print("codearcade: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except _user_errors() as exc:
        print(f"codearcade: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
