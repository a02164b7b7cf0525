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
OFFLINE_TOKEN_BUDGET = 3_000
OFFLINE_MAX_TOKENS = 512
"""The offline model reads ~100-200 prompt tokens/s on two cores: small prompts keep an iteration near a minute."""


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

    p = verbs.add_parser(
        "optimize",
        help="improve a policy with an LLM (the paper's loop), every step stored",
        description="Run the optimization loop: iteration 0 evaluates the starting policy; each further iteration "
        "builds a prompt from the store, asks the LLM for new code, validates it, and evaluates the result. "
        "Without --model a small local model (SmolLM2-135M) is started: it exercises the pipeline offline but "
        "cannot really improve code.",
    )
    p.add_argument("policy", metavar="POLICY.py", nargs="?",
                   help="starting policy file (default: the game's scaffold in examples/)")
    p.add_argument("--game", help=f"game: {', '.join(GAMES)} (default: the file's GAME)")
    p.add_argument("--model", help="litellm model, e.g. anthropic/claude-3-5-sonnet-20241022, openai/gpt-4o "
                   "(default: the offline SmolLM2 server)")
    p.add_argument("--api-base", metavar="URL", help="OpenAI-compatible server, with --model openai/NAME")
    p.add_argument("--iterations", type=_non_negative_int, default=None,
                   help="LLM updates after evaluating the starting policy (default: 20; with --resume, a larger "
                   "number extends the run)")
    p.add_argument("--memory", type=_non_negative_int, default=5, help="earlier iterations in the prompt (default: 5)")
    p.add_argument("--token-budget", type=_positive_int, default=None,
                   help="hard limit on prompt tokens (default: 16000; 3000 with the offline model)")
    p.add_argument("--eval-episodes", type=_positive_int, default=1,
                   help="evaluation episodes per iteration, in parallel (default: 1)")
    p.add_argument("--feedback", choices=["staged", "rollout"], default="staged",
                   help="staged: from the evaluation score (paper); rollout: rollout reward only (ablation)")
    p.add_argument("--no-rollback", action="store_true", help="never go back to the best version after a regression")
    p.add_argument("--rollback-fraction", type=_probability, default=0.5,
                   help="roll back below best - (1-F)*max(|best|,1) (default: 0.5)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: 0)")
    p.add_argument("--temperature", type=float, default=0.0, help="LLM temperature (default: 0)")
    p.add_argument("--max-tokens", type=_positive_int, default=None, help="longest reply (default: 4096; 512 with the offline model)")
    p.add_argument("--rollout-steps", type=_positive_int, help="training rollout horizon (default: the task's)")
    p.add_argument("--eval-max-steps", type=_positive_int, help="evaluation cap (default: the task's, 4000)")
    p.add_argument("--workers", type=_positive_int, default=None, help="episode worker processes (default: cores)")
    p.add_argument("--call-time-limit", type=float, default=1.0, metavar="SECONDS", help="per policy call (default: 1)")
    p.add_argument("--resume", metavar="RUN_ID", help="continue a run that was interrupted or killed")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    _add_store(p)
    p.set_defaults(handler=cmd_optimize)

    p = verbs.add_parser(
        "replay",
        help="re-run an optimization from its stored LLM replies and report divergence",
        description="Re-run an optimization run as a new run (kind replay), answering each LLM call with the "
        "reply stored for the same prompt. Reports per iteration whether prompts and scores match the original, "
        "and stops where they diverge.",
    )
    p.add_argument("run_id", metavar="RUN_ID")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    _add_store(p)
    p.set_defaults(handler=cmd_replay)
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


def _print_iteration(item) -> None:
    tokens = f"prompt {item.prompt_tokens} tok" if item.prompt_tokens else ""
    note = f"  ({item.detail})" if item.detail and item.update_status != "accepted" else ""
    back = "  rolled back" if item.rolled_back else ""
    print(f"iteration {item.iteration:>3}  score {item.score:>8.1f}  best {item.best_score:>8.1f} (it {item.best_iteration})"
          f"  update {item.update_status:<9} {tokens}{back}{note[:160]}", flush=True)


def _client_for(model: str | None, api_base: str | None, temperature: float, max_tokens: int | None, seed: int):
    """(client, server or None, max_tokens, context budget cap) for --model / the offline default."""
    from pipeline.llm import LiteLLMClient

    if model:
        return LiteLLMClient(model, api_base=api_base, temperature=temperature, max_tokens=max_tokens or 4096,
                             seed=seed), None, None
    from pipeline.local_llm import LocalModelServer, show_offline_model_notice

    show_offline_model_notice()
    server = LocalModelServer()
    server.start()
    max_tokens = max_tokens or OFFLINE_MAX_TOKENS
    client = LiteLLMClient(server.model, api_base=server.api_base, temperature=temperature, max_tokens=max_tokens,
                           seed=seed)
    return client, server, server.context_tokens - max_tokens


def cmd_optimize(args: argparse.Namespace) -> int:
    from pipeline.optimize import OptimizeConfig, load_state, optimize

    store = _store(args)
    offline = args.model is None
    if args.resume:
        state = load_state(store, args.resume)
        config = state.config
        config.model = args.model or config.model  # a resumed run may be pointed at another endpoint
        config.api_base = args.api_base or config.api_base
        offline = config.model is None
        client, server, cap = _client_for(config.model, config.api_base, config.temperature, config.max_tokens,
                                          config.seed)
        if args.iterations is not None:
            config.iterations = args.iterations
    else:
        client, server, cap = _client_for(args.model, args.api_base, args.temperature, args.max_tokens, args.seed)
        budget = args.token_budget or (16_000 if cap is None else OFFLINE_TOKEN_BUDGET)
        if cap is not None:
            budget = min(budget, cap)
        config = OptimizeConfig(
            game=args.game, policy=args.policy, model=args.model, api_base=args.api_base,
            iterations=20 if args.iterations is None else args.iterations,
            memory=args.memory, token_budget=budget, eval_episodes=args.eval_episodes, feedback=args.feedback,
            rollback=not args.no_rollback, rollback_fraction=args.rollback_fraction, seed=args.seed,
            temperature=args.temperature, max_tokens=client.max_tokens, rollout_steps=args.rollout_steps,
            eval_max_steps=args.eval_max_steps, workers=args.workers or (os.cpu_count() or 1),
            call_time_limit_s=args.call_time_limit,
        )
    try:
        if not args.json:
            print(f"store {store.path}  model {client.model}{' (offline default)' if offline else ''}", flush=True)
        result = optimize(config, store, client, resume=args.resume, on_iteration=None if args.json else _print_iteration,
                          log=lambda line: print(line, file=sys.stderr))
    finally:
        if server is not None:
            server.stop()
    if args.json:
        print(json.dumps({
            "run_id": result.run_id, "status": result.status, "error": result.error,
            "iterations": [dict(iteration=i.iteration, policy_version_id=i.policy_version_id, score=i.score,
                                best_score=i.best_score, update_status=i.update_status, rolled_back=i.rolled_back)
                           for i in result.iterations],
        }, indent=2))
    else:
        print(f"run {result.run_id} {result.status}" + (f": {result.error}" if result.error else ""))
    if result.status != "finished":
        print(f"codearcade: run {result.run_id} {result.status}: {result.error}; continue it with "
              f"`codearcade optimize --resume {result.run_id}`", file=sys.stderr)
        return EXIT_EPISODE_FAILED
    return EXIT_OK


def cmd_replay(args: argparse.Namespace) -> int:
    from pipeline.replay import replay

    report = replay(_store(args), args.run_id, log=lambda line: print(line, file=sys.stderr))
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
    else:
        print(f"replay of {report.original_run_id} as {report.replay_run_id}: {report.status}")
        print(f"{'iteration':>9}  {'prompt':<14} {'original':>9} {'replay':>9}")
        for r in report.rows:
            same = "same" if r.original_prompt == r.replay_prompt else "DIFFERENT"
            o = "-" if r.original_score is None else f"{r.original_score:.1f}"
            n = "-" if r.replay_score is None else f"{r.replay_score:.1f}"
            print(f"{r.iteration:>9}  {same:<14} {o:>9} {n:>9}")
        if report.diverged_at is not None:
            print(f"first divergence at iteration {report.diverged_at}")
    return EXIT_OK if report.diverged_at is None else EXIT_EPISODE_FAILED


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
