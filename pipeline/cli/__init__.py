"""The ``codearcade`` command line: one verb per job, each with ``--store`` and ``--help``.

Exit codes: 0 success; 1 the job ran but an episode ended in a policy error, time-out, crash or score
tampering; 2 bad input (unknown game, missing or broken policy file, unusable or damaged store), with a
one-line message on stderr; 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any, Callable, Sequence

from games import GAMES
from pipeline.optimizer.strategies import STRATEGIES

EXIT_OK, EXIT_EPISODE_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
FAILED_END_REASONS = ("policy_error", "timeout", "crashed", "tampered")


class CliError(Exception):
    """A user error with a one-line message; exits with code 2."""


def _add_store(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--store",
        default=None,
        metavar="PATH",
        help="DuckDB store file (default: $CODEARCADE_STORE or ./codearcade.duckdb)",
    )


def _add_rerun(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rerun", default="off", metavar="DIR|spawn|off",
                   help="live Rerun recordings: DIR writes DIR/<episode_id>.rrd per episode (and DIR/<run_id>.rrd "
                   "for optimize), spawn streams to a Rerun viewer on 127.0.0.1 (started if none runs), "
                   "a rerun+http://HOST:PORT/proxy url streams there; off (default) records nothing")


def _store(args: argparse.Namespace):
    from store import Store

    return Store(args.store) if args.store else Store()


def _run_id(store, text: str) -> str:
    """The run whose id is ``text`` or starts with it (every verb that takes a run accepts a unique prefix)."""
    from store.views import resolve_run_id

    with store.read() as con:
        return resolve_run_id(con, text, store)


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
    p.add_argument("--game", help=f"game to play: {', '.join(GAMES)}, or any game OCAtari reads (`codearcade "
                   "games` lists them) (default: the file's GAME)")
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
    p.add_argument("--one-life", action="store_true",
                   help="end each episode at the first lost life, as the authors' follow-up evaluates Asterix, "
                   "Breakout, Q*bert and Seaquest (default: whole games, the paper's)")
    p.add_argument("--workers", type=_non_negative_int, default=None,
                   help="episodes played at once in worker processes (default: min(episodes, cores)); "
                   "0 plays in this process without isolation, for debugging")
    p.add_argument("--call-time-limit", type=float, default=1.0, metavar="SECONDS",
                   help="time limit of one policy call (default: 1.0)")
    p.add_argument("--episode-time-limit", type=float, default=900.0, metavar="SECONDS",
                   help="wall-clock limit of one episode (default: 900)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    _add_rerun(p)
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
                   help="starting policy file (default: the game's scaffold in games/scaffolds/)")
    p.add_argument("--game", help=f"game: {', '.join(GAMES)}, or any game OCAtari reads (default: the file's GAME)")
    p.add_argument("--model", help="litellm model: anthropic/claude-sonnet-4-5 (ANTHROPIC_API_KEY), openai/gpt-4o "
                   "(OPENAI_API_KEY), gemini/..., mistral/..., ollama_chat/NAME (a local Ollama), hosted_vllm/NAME "
                   "or openai/NAME with --api-base (your own server) (default: the offline SmolLM2 server)")
    p.add_argument("--api-base", metavar="URL", help="the provider's endpoint: your own OpenAI-compatible, vLLM or "
                   "Ollama server, or a proxy")
    p.add_argument("--iterations", type=_non_negative_int, default=None,
                   help="LLM updates after evaluating the starting policy (default: 20; with --resume, a larger "
                   "number extends the run)")
    p.add_argument("--memory", type=_non_negative_int, help="earlier iterations in the prompt (default: 5)")
    p.add_argument("--token-budget", type=_positive_int, default=None,
                   help="hard limit on prompt tokens (default: 16000; 3000 with the offline model)")
    p.add_argument("--eval-episodes", type=_positive_int, help="evaluation episodes per iteration, in parallel "
                   "(default: 1)")
    p.add_argument("--feedback", choices=["staged", "rollout"],
                   help="staged: from the evaluation score (paper, default); rollout: rollout reward only (ablation)")
    p.add_argument("--no-rollback", action="store_const", const=False, dest="rollback",
                   help="never go back to the best version after a regression")
    p.add_argument("--rollback-fraction", type=_probability,
                   help="roll back below best - (1-F)*max(|best|,1) (default: 0.5)")
    p.add_argument("--seed", type=int, help="seed (default: 0)")
    p.add_argument("--temperature", type=float, help="LLM temperature (default: 0; not sent to models that "
                   "take none)")
    p.add_argument("--max-tokens", type=_positive_int, default=None,
                   help="longest reply (default: 4096; 512 with the offline model)")
    p.add_argument("--rollout-steps", type=_positive_int, help="training rollout horizon (default: the task's)")
    p.add_argument("--eval-max-steps", type=_positive_int, help="evaluation cap (default: the task's, 4000)")
    p.add_argument("--workers", type=_positive_int, default=None, help="episode worker processes (default: cores)")
    p.add_argument("--call-time-limit", type=float, dest="call_time_limit_s", metavar="SECONDS",
                   help="per policy call (default: 1)")
    search = p.add_argument_group("search", "how versions are chosen for improvement (pipeline/optimizer/strategies.py)")
    search.add_argument("--strategy", choices=STRATEGIES,
                        help="greedy: the paper's loop, one proposal from the last version, rollback after a "
                        "regression (default); best-of-n: N proposals from the best version, keep the best; beam: "
                        "expand the --beam-width best versions; map-elites: improve random elites of an archive "
                        "over code complexity x game length, with other elites as inspirations")
    search.add_argument("--candidates", type=_positive_int, metavar="N",
                        help="proposals per iteration (best-of-n, map-elites: default 4) or per beam member (beam: "
                        "default 1)")
    search.add_argument("--beam-width", type=_positive_int, metavar="K", help="beam: versions kept (default: 3)")
    search.add_argument("--max-concurrent-calls", type=_positive_int, metavar="N",
                        help="LLM calls in flight at once (default: 4)")
    search.add_argument("--robust-episodes", type=_non_negative_int, metavar="N",
                        help="also evaluate every version in N games under the standard protocol (sticky actions "
                        "0.25, up to 30 no-op starts; seeded), beside the paper's deterministic one (default: 0)")
    search.add_argument("--optimize-for", choices=("deterministic", "standard"), dest="optimize_protocol",
                        help="the score the strategy optimizes: deterministic (the paper's protocol, default) or "
                        "standard (needs --robust-episodes)")
    search.add_argument("--screen-steps", type=_positive_int, metavar="N",
                        help="cascade evaluation: a new version first plays N steps of the first evaluation game, "
                        "and is assessed fully only if it keeps up with its parent there (default: off)")
    search.add_argument("--screen-margin", type=float, metavar="POINTS",
                        help="how far behind its parent a screened version may be (default: 0)")
    search.add_argument("--one-life", action="store_const", const=True, dest="one_life",
                        help="the authors' protocol for Asterix, Breakout, Q*bert and Seaquest: every episode, "
                        "training rollouts included, ends at the first lost life (default: whole games)")
    search.add_argument("--no-eval-cache", action="store_const", const=False, dest="eval_cache",
                        help="play every version's episodes again instead of reusing those of an earlier assessment")
    budgets = p.add_argument_group("budgets", "the run stops with status 'budget' before it would exceed one; "
                                   "--resume with a larger budget continues it")
    budgets.add_argument("--max-cost", type=float, dest="max_cost_usd", metavar="USD",
                         help="LLM cost, at litellm's price for the model (each call counted at its worst case: "
                         "the prompt plus a reply of --max-tokens)")
    budgets.add_argument("--max-total-tokens", type=_positive_int, dest="max_total_tokens", metavar="N",
                         help="LLM input + output tokens")
    budgets.add_argument("--max-llm-calls", type=_positive_int, dest="max_llm_calls", metavar="N",
                         help="LLM calls (an equal budget for comparing strategies)")
    budgets.add_argument("--max-wall", type=float, dest="max_wall_minutes", metavar="MINUTES",
                         help="wall-clock time of the run's iterations")
    p.add_argument("--resume", metavar="RUN_ID", help="continue a run that was interrupted, failed or stopped by a "
                   "budget (an id or a unique prefix); budgets, limits, --model/--api-base and a larger "
                   "--iterations may be given again")
    p.add_argument("--dry-run", action="store_true",
                   help="evaluate the starting policy into a temporary store, build the first prompt, and print its "
                   "tokens and the estimated cost of one update and of the whole run; calls no model")
    p.add_argument("--show-prompt", action="store_true", help="with --dry-run: print the prompt too")
    p.add_argument("--stream", action="store_true",
                   help="stream each reply, showing the tokens as they arrive (the result is the same)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    _add_rerun(p)
    _add_store(p)
    p.set_defaults(handler=cmd_optimize)

    p = verbs.add_parser(
        "batch",
        help="run a matrix of optimizations headless (resumable)",
        description="Run every optimization an experiment file declares, in parallel, into one store. Running "
        "the same command again skips finished runs and resumes interrupted ones. See pipeline/jobs/batch.py and "
        "examples/ablation.toml for the file format.",
    )
    p.add_argument("experiments", metavar="EXPERIMENTS.toml")
    p.add_argument("--workers", type=_positive_int, default=None, help="runs at once (default: cores)")
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="local processes (default) or a Ray cluster")
    p.add_argument("--address", help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--dry-run", action="store_true", help="list what would run, and do nothing")
    p.add_argument("--log", metavar="FILE", help="plain log file (default: <store>.<batch>.log beside the store)")
    _add_store(p)
    p.set_defaults(handler=cmd_batch)

    p = verbs.add_parser(
        "doctor",
        help="check a store's integrity",
        description="Check references, uniqueness and completeness of everything in the store (see store/doctor.py). "
        "Exit 0 when sound (warnings allowed), 1 when damage is found.",
    )
    p.add_argument("--json", action="store_true", help="print the findings as JSON")
    _add_store(p)
    p.set_defaults(handler=cmd_doctor)

    p = verbs.add_parser(
        "replay",
        help="re-run an optimization from its stored LLM replies and report divergence",
        description="Re-run an optimization run as a new run (kind replay), answering each LLM call with the "
        "reply stored for the same prompt. Reports per iteration whether prompts and scores match the original, "
        "and stops where they diverge.",
    )
    p.add_argument("run_id", metavar="RUN", help="run id, or a unique prefix of one")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    _add_store(p)
    p.set_defaults(handler=cmd_replay)

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
    p.add_argument("--max-width", type=_non_negative_int, default=40, metavar="N",
                   help="table mode: cut cells longer than N characters (default: 40; 0: never)")
    p.add_argument("--max-rows", type=_non_negative_int, default=1000, metavar="N",
                   help="table mode: print at most N rows (default: 1000; 0: all)")
    _add_store(p)
    p.set_defaults(handler=cmd_sql)

    p = verbs.add_parser(
        "runs",
        help="list the runs in the store",
        description="List the runs in the store, oldest first: kind, game, model, status, iterations done of "
        "those planned, best score (the mean return for eval runs), episodes and LLM tokens (view run_summary).",
    )
    p.add_argument("--json", action="store_true", help="print the run_summary rows as JSON")
    _add_store(p)
    p.set_defaults(handler=cmd_runs)

    p = verbs.add_parser(
        "report",
        help="write PNG plots and a Markdown summary of a run",
        description="Write a report of one run: score per iteration with the best so far (return per episode "
        "for eval runs), code size and complexity per iteration, LLM tokens per iteration, as PNG files, and "
        "README.md showing them with the run's settings and a table of its iterations.",
    )
    p.add_argument("run_id", metavar="RUN", help="run id, or a unique prefix of one")
    p.add_argument("--out", metavar="DIR", help="output directory (default: ./reports/RUN_ID)")
    _add_store(p)
    p.set_defaults(handler=cmd_report)

    p = verbs.add_parser(
        "blame",
        help="show a policy version's code with the iteration and LLM call that wrote each line",
        description="Print the trainable methods of a policy version of a run, each line annotated with the "
        "iteration that introduced it, that version's short id and the LLM call that wrote it, carried across "
        "versions like `git blame` (table policy_lines, view line_blame). The version is the run's best unless "
        "--version or --iteration names another.",
    )
    p.add_argument("run_id", metavar="RUN", help="run id, or a unique prefix of one")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--version", metavar="V", help="policy version id, or a unique prefix of one (default: the best)")
    which.add_argument("--iteration", type=_non_negative_int, metavar="I", help="the version evaluated in iteration I")
    p.add_argument("--json", action="store_true", help="print the annotated lines as JSON")
    _add_store(p)
    p.set_defaults(handler=cmd_blame)

    p = verbs.add_parser(
        "games",
        help="list the games: curated ones and every game OCAtari reads",
        description="List the games codearcade plays: the curated ones (a module in games/ with the authors' "
        "observation conventions, task and scaffold) and every other game OCAtari reads from RAM, played "
        "generically (objects by category, ALE's actions; `codearcade new` writes a scaffold).",
    )
    p.add_argument("--curated", action="store_true", help="only the curated games")
    p.add_argument("--json", action="store_true", help="print the games and their settings as JSON")
    p.set_defaults(handler=cmd_games)

    p = verbs.add_parser(
        "new",
        help="write a policy scaffold for a game",
        description="Write a policy file to start from: a curated game's scaffold, or, for any other game, one "
        "written from the object categories seen in a few hundred random steps and ALE's action meanings, with "
        "one trainable method.",
    )
    p.add_argument("policy", metavar="POLICY.py", help="file to write")
    p.add_argument("--game", required=True, help="the game (`codearcade games` lists them)")
    p.add_argument("--force", action="store_true", help="overwrite POLICY.py if it exists")
    p.set_defaults(handler=cmd_new)

    p = verbs.add_parser(
        "view",
        help="rebuild a Rerun recording of a run or an episode from the store",
        description="Rebuild a Rerun recording from the store: with no --iteration/--episode, the run recording "
        "of an optimization (score, code, prompts and replies per iteration) or the first episode of an eval run; "
        "--iteration I alone shows that iteration's training rollout. Frames are regenerated by replaying the "
        "stored actions (checked against the stored objects). Without --spawn/--serve-web/--connect the "
        "recording is saved to a file (default ./<recording id>.rrd).",
    )
    p.add_argument("run_id", metavar="RUN", help="run id, or a unique prefix of one")
    p.add_argument("--iteration", type=_non_negative_int, metavar="I", help="optimizer iteration (default: 0)")
    p.add_argument("--episode", metavar="E",
                   help="evaluation episode index within the iteration, 'train' for its training rollout, or an episode id")
    sink = p.add_mutually_exclusive_group()
    sink.add_argument("--save", metavar="FILE.rrd", help="write the recording to this file")
    sink.add_argument("--serve-web", action="store_true",
                      help="serve the web viewer on 127.0.0.1 and print its URL; Ctrl-C stops it")
    sink.add_argument("--spawn", action="store_true", help="send it to a native Rerun viewer (started if none runs)")
    sink.add_argument("--connect", metavar="URL", help="send it to a viewer or server at rerun+http://HOST:PORT/proxy")
    p.add_argument("--frames-every", type=_non_negative_int, default=4, metavar="K",
                   help="episodes: regenerate the screen every K steps by replaying the actions (default: 4; 0: none)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    _add_store(p)
    p.set_defaults(handler=cmd_view)

    p = verbs.add_parser(
        "export",
        help="send a run to an OpenTelemetry receiver as traces (OTLP)",
        description="Send a stored run as one OpenTelemetry trace: a span for the run, one per iteration (score, "
        "best score, update status, policy version, rolled back), under it the LLM call(s) named and attributed "
        "after the gen_ai semantic conventions, the training rollout and the evaluation episodes (return, "
        "length, end reason), all with their stored times. Opens in Arize Phoenix, Langfuse, Jaeger, Grafana "
        "Tempo or any OTLP receiver. Ids come from the run id, so exporting again sends the same spans "
        "(viewers/otlp_export.py says what receivers do with them).",
    )
    p.add_argument("run_id", metavar="RUN", help="run id, or a unique prefix of one")
    p.add_argument("--otlp", required=True, metavar="URL",
                   help="the receiver: for http/protobuf its base URL (e.g. http://127.0.0.1:4318, Phoenix "
                   "http://127.0.0.1:6006; /v1/traces is appended unless the URL ends with it), for grpc its "
                   "address (e.g. http://127.0.0.1:4317)")
    p.add_argument("--protocol", choices=["http/protobuf", "grpc"], default="http/protobuf",
                   help="OTLP transport (default: http/protobuf)")
    p.add_argument("--header", action="append", default=[], metavar="KEY=VALUE",
                   help="a header to send with every request, e.g. Authorization=Bearer... (repeatable; "
                   "OTEL_EXPORTER_OTLP_HEADERS is read when none is given)")
    p.add_argument("--service-name", default="codearcade", metavar="NAME",
                   help="service.name of the spans, also Phoenix's project (default: codearcade)")
    p.add_argument("--max-text-chars", type=_non_negative_int, default=None, metavar="N",
                   help="characters kept of each prompt message, reply and feedback text (default: 32000; 0 sends "
                   "no texts, only numbers and names)")
    p.add_argument("--timeout", type=float, default=10.0, metavar="SECONDS",
                   help="per request, retries included (default: 10)")
    p.add_argument("--json", action="store_true", help="print what was sent as JSON")
    _add_store(p)
    p.set_defaults(handler=cmd_export)

    p = verbs.add_parser(
        "compare",
        help="compare two runs, or play two policy versions on the same seeds and find where they part",
        description="Two runs (ids or unique prefixes): their learning curves on one plot, the best score each "
        "reached within the same LLM calls, tokens and wall seconds, and the diff of their best versions. Two "
        "versions of one game (policy files, or RUN:VERSION for a version stored in a run: an id, a unique "
        "prefix of one, or 'best'): both play the same seeds, traced, into the store (two eval runs), and the "
        "report names the first step where their actions differ, with both sides' observations and node "
        "outputs around it.",
        epilog="examples: codearcade compare 01JDA 01JDB --out cmp/   |   codearcade compare pong_a.py pong_b.py "
        "--max-steps 600 --rerun side_by_side.rrd   |   codearcade compare 01JDA:best 01JDB:best",
    )
    p.add_argument("a", metavar="A", help="a run id, a policy file or RUN:VERSION")
    p.add_argument("b", metavar="B", help="the same kind as A")
    p.add_argument("--out", metavar="DIR", help="write README.md there (and curves.png for two runs); default for "
                   "two runs: ./reports/compare-A-B; two versions: no files")
    p.add_argument("--game", help="versions: the game both play (default: their runs' or files' GAME)")
    p.add_argument("--episodes", type=_positive_int, default=1,
                   help="versions: seeds to play, from --seed on (default: 1)")
    p.add_argument("--seed", type=int, default=0, help="versions: the first seed (default: 0)")
    p.add_argument("--max-steps", type=_positive_int, default=4000, help="versions: step cap (default: 4000)")
    p.add_argument("--context", type=_non_negative_int, default=3,
                   help="versions: steps shown before and after the first divergent step (default: 3)")
    p.add_argument("--workers", type=_non_negative_int, default=None,
                   help="versions: episode worker processes (default: min(episodes, cores))")
    p.add_argument("--rerun", metavar="FILE.rrd|URL",
                   help="versions: write a side-by-side Rerun recording of the two episodes of the first seed "
                   "where they part (a .rrd file, or a rerun+http://HOST:PORT/proxy viewer)")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON")
    _add_store(p)
    p.set_defaults(handler=cmd_compare)
    return parser


def _progress_bar(episodes: int, description: str):
    """A tqdm bar that counts finished episodes and shows the steps played so far (episodes end at unknown
    lengths, so a bar over ``episodes x max_steps`` would jump); the executor's progress callback and the
    per-episode callback that feed it."""
    from tqdm import tqdm

    tqdm.monitor_interval = 0  # no monitor thread: episode workers are forked from this process
    bar = tqdm(total=episodes, desc=description, unit="episode", disable=None, dynamic_ncols=True, leave=False)
    steps: dict[int, int] = {}

    def show_steps() -> None:
        bar.set_postfix_str(f"{sum(steps.values()):,} steps", refresh=True)

    def update(index: int, played: int) -> None:
        steps[index] = played
        show_steps()

    def finished(index: int, length: int) -> None:
        steps[index] = length
        bar.update(1)
        show_steps()

    return bar, update, finished


def cmd_eval(args: argparse.Namespace) -> int:
    from pipeline.play.evaluate import EvalConfig, evaluate

    workers = args.workers if args.workers is not None else min(args.episodes, os.cpu_count() or 1)
    config = EvalConfig(
        game=args.game, episodes=args.episodes, max_steps=args.max_steps, seed=args.seed, trace=args.trace,
        sticky=args.sticky, noop_max=args.noop_max, one_life=args.one_life, workers=workers,
        call_time_limit_s=args.call_time_limit, episode_time_limit_s=args.episode_time_limit,
        rerun=_rerun_target(args.rerun),
    )
    store = _store(args)
    bar, update, finished = _progress_bar(args.episodes, f"eval {os.path.basename(args.policy)}")
    try:
        result = evaluate(args.policy, config, store, progress=update, on_episode=finished)
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


def _rerun_target(value: str | None) -> str | None:
    """``--rerun`` as a live target for the episode workers (Rerun itself is never loaded in this process)."""
    from viewers.rerun_sinks import ViewerError, resolve_live_target

    try:
        return resolve_live_target(value)
    except ViewerError as exc:
        raise CliError(str(exc)) from None


def _print_iteration(item) -> None:
    tokens = f"prompt {item.prompt_tokens} tok" if item.prompt_tokens else ""
    note = f"  ({item.detail})" if item.detail and item.update_status != "accepted" else ""
    back = "  rolled back" if item.rolled_back else ""
    if item.candidates > 1:
        tokens = f"best of {item.candidates} candidates  " + tokens
    if item.standard_score is not None:
        tokens = f"standard protocol {item.standard_score:g}  " + tokens
    print(f"iteration {item.iteration:>3}  score {item.score:>8.1f}  best {item.best_score:>8.1f} (it {item.best_iteration})"
          f"  update {item.update_status:<9} {tokens}{back}{note[:160]}", flush=True)


OPTIMIZE_OPTIONS = ("game", "policy", "model", "api_base", "iterations", "memory", "token_budget", "eval_episodes",
                    "feedback", "rollback", "rollback_fraction", "seed", "temperature", "max_tokens", "rollout_steps",
                    "eval_max_steps", "workers", "call_time_limit_s", "max_cost_usd", "max_total_tokens",
                    "max_llm_calls", "max_wall_minutes", "strategy", "candidates", "beam_width", "max_concurrent_calls", "eval_cache",
                    "robust_episodes", "optimize_protocol", "screen_steps", "screen_margin", "one_life")
"""The ``optimize`` flags that are :class:`~pipeline.optimizer.config.OptimizeConfig` fields (defaults live there)."""


def _llm_waiting(stream=None):
    """The optimizer's ``waiting`` hook: while an LLM call is in flight, a terminal shows for how long it has
    waited and, when the reply is streamed, how much of it has arrived (one line, redrawn each second); a log
    gets one line per call. It yields the callback the client feeds streamed text to."""
    import threading
    import time
    from contextlib import contextmanager

    stream = stream or sys.stderr

    @contextmanager
    def waiting(iteration: int, label: str):
        started = time.monotonic()
        received = {"pieces": 0, "chars": 0}

        def on_text(piece: str) -> None:
            received["pieces"] += 1
            received["chars"] += len(piece)

        if not stream.isatty():
            print(f"iteration {iteration}: waiting for {label}", file=stream, flush=True)
            yield on_text
            return
        stop = threading.Event()

        def line() -> str:
            text = f"iteration {iteration}: waiting for {label} ... {time.monotonic() - started:.0f} s"
            if received["pieces"]:
                text += f", receiving: {received['pieces']:,} tokens ({received['chars']:,} characters)"
            return text

        def tick() -> None:
            while not stop.wait(0.5):
                stream.write("\r\033[K" + line())
                stream.flush()

        ticker = threading.Thread(target=tick, name="codearcade-llm-wait", daemon=True)
        ticker.start()
        try:
            yield on_text
        finally:
            stop.set()
            ticker.join()
            stream.write("\r\033[K")
            stream.flush()

    return waiting


def cmd_optimize(args: argparse.Namespace) -> int:
    given = {k: getattr(args, k) for k in OPTIMIZE_OPTIONS if getattr(args, k) is not None}
    if args.model and not args.dry_run:
        from pipeline.llm.providers import check_credentials  # no litellm import: a missing key is reported at once

        check_credentials(args.model, args.api_base)
    if args.show_prompt and not args.dry_run:
        raise CliError("--show-prompt goes with --dry-run")
    from pipeline.llm.client import OFFLINE_MAX_TOKENS, OFFLINE_TOKEN_BUDGET, open_client
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.loop import optimize, plan_resume

    store = _store(args)
    if args.resume:
        if args.dry_run:
            raise CliError("--dry-run starts a new run; it cannot go with --resume")
        plan = plan_resume(store, args.resume, given)
        if plan.nothing_to_do:
            print(json.dumps({"run_id": plan.run_id, "status": plan.status, "error": None, "iterations": [],
                              "note": plan.nothing_to_do}, indent=2) if args.json else plan.nothing_to_do)
            return EXIT_OK
        config, run_id = plan.config, plan.run_id
        if config.model and "model" not in given:
            from pipeline.llm.providers import check_credentials

            check_credentials(config.model, config.api_base)
    else:
        given.setdefault("workers", os.cpu_count() or 1)
        if args.model is None:
            given.setdefault("max_tokens", OFFLINE_MAX_TOKENS)
            given.setdefault("token_budget", OFFLINE_TOKEN_BUDGET)
        config, run_id = OptimizeConfig(**given), None
    if args.dry_run:
        return _dry_run(config, args)
    offline = config.model is None
    client, server, cap = open_client(config.model, config.api_base, config.temperature, config.max_tokens,
                                      config.seed, stream=args.stream)
    if cap is not None and config.token_budget > cap:
        config.token_budget = cap
    for name in getattr(client, "dropped", ()):
        print(f"codearcade: {client.label} takes no '{name}' parameter; it is not sent", file=sys.stderr)
    rerun = _rerun_target(args.rerun)
    on_iteration, recordings = _run_recordings(store, rerun, None if args.json else _print_iteration)
    try:
        if not args.json:
            print(f"store {store.path}  model {client.label}{' (offline default)' if offline else ''}", flush=True)
        result = optimize(config, store, client, resume=run_id, on_iteration=on_iteration,
                          log=lambda line: print(line, file=sys.stderr), rerun=rerun, waiting=_llm_waiting())
    finally:
        if server is not None:
            server.stop()
        if recordings is not None:
            recordings.close()
    if args.json:
        print(json.dumps({
            "run_id": result.run_id, "status": result.status, "error": result.error,
            "iterations": [dict(iteration=i.iteration, policy_version_id=i.policy_version_id, score=i.score,
                                best_score=i.best_score, update_status=i.update_status, rolled_back=i.rolled_back)
                           for i in result.iterations],
        }, indent=2))
    else:
        print(f"run {result.run_id} {result.status}" + (f": {result.error}" if result.error else ""))
    if result.status == "budget":
        print(f"codearcade: run {result.run_id} stopped by its budget; continue it with a larger one: "
              f"`codearcade optimize --resume {result.run_id} --max-...`", file=sys.stderr)
        return EXIT_OK
    if result.status != "finished":
        print(f"codearcade: run {result.run_id} {result.status}: {result.error}; fix the cause, then continue it "
              f"with `codearcade optimize --resume {result.run_id}`", file=sys.stderr)
        return EXIT_EPISODE_FAILED
    return EXIT_OK


def _dry_run(config, args: argparse.Namespace) -> int:
    from pipeline.optimizer.estimate import estimate_run

    report = estimate_run(config, progress_log=lambda line: print(line, file=sys.stderr))
    if args.json:
        print(json.dumps(report.as_dict(include_prompt=args.show_prompt), indent=2))
        return EXIT_OK
    if args.show_prompt:
        for message in report.prompt.messages:
            print(f"----- {message['role']} -----")
            print(message["content"])
        print("-----")
    for line in report.lines():
        print(line)
    return EXIT_OK


def _batch_display():
    """A live table on a terminal (rich), nothing otherwise (the log lines tell the story)."""
    if not sys.stdout.isatty():
        return (lambda progress: None), (lambda: None)
    from rich.live import Live
    from rich.table import Table

    live = Live(refresh_per_second=2, transient=False)
    live.start()

    def show(progress) -> None:
        table = Table(title="codearcade batch", expand=False)
        for column in ("run", "state", "iteration", "best", "run id"):
            table.add_column(column)
        for p in progress:
            it = "-" if p.iteration is None else f"{p.iteration}/{p.iterations}"
            best = "-" if p.best is None else f"{p.best:g}"
            table.add_row(p.label, p.state, it, best, p.run_id or "")
        counts = {s: sum(1 for p in progress if p.state == s)
                  for s in ("finished", "budget", "running", "failed", "skipped")}
        table.caption = "  ".join(f"{k} {v}" for k, v in counts.items())
        live.update(table)

    return show, live.stop


def _run_recordings(store, target: str | None, then: Callable | None):
    """With ``--rerun``: an on_iteration callback that also has the run's Rerun recording rebuilt, in a separate
    process, after every iteration; and the updater to close at the end (None without ``--rerun``)."""
    if target is None:
        return then, None
    from viewers.rerun_sinks import RunRecordingUpdater

    updater = RunRecordingUpdater(store.path, target)

    def on_iteration(item) -> None:
        if then is not None:
            then(item)
        updater.update(item.run_id)

    return on_iteration, updater


def cmd_games(args: argparse.Namespace) -> int:
    from games import GAMES, get_game
    from games.generic import generic_names
    from viewers.tables import format_table

    names = list(GAMES) + ([] if args.curated else [n for n in generic_names() if n not in GAMES])
    rows = []
    for name in names:
        game = get_game(name)
        task = game.task
        rows.append({"game": game.name, "status": game.status, "env_id": game.env_id, "actions": game.n_actions,
                     "lives": game.lives, "rollout_steps": task.rollout_steps, "eval_max_steps": task.eval_max_steps,
                     "one_life": task.one_life_episodes if game.status == "curated" else None,
                     "feedback_high": task.feedback["high"] if game.status == "curated" else None,
                     "feedback_low": task.feedback["low"] if game.status == "curated" else None,
                     "scaffold": str(game.scaffold.relative_to(game.scaffold.parents[2])) if game.scaffold else None})
    if args.json:
        print(json.dumps(rows, indent=2))
        return EXIT_OK
    print(format_table(tuple(rows[0]), [tuple(r.values()) for r in rows], max_width=40, null="-"))
    print(f"({sum(r['status'] == 'curated' for r in rows)} curated, {sum(r['status'] == 'generic' for r in rows)} "
          "generic; `codearcade new POLICY.py --game G` writes a scaffold for any of them)")
    return EXIT_OK


def cmd_new(args: argparse.Namespace) -> int:
    from pathlib import Path

    from games import get_game
    from games.scaffolding import SURVEY_STEPS, scaffold_text

    path = Path(args.policy)
    if path.exists() and not args.force:
        raise CliError(f"{path} exists; pass --force to overwrite it")
    game = get_game(args.game)
    if game.scaffold is None:
        print(f"surveying {game.name}: {SURVEY_STEPS} random steps...", file=sys.stderr, flush=True)
    path.write_text(scaffold_text(game))
    print(f"wrote {path} ({game.status} game {game.name}); evaluate it with `codearcade eval {path}`, improve it "
          f"with `codearcade optimize {path}`")
    return EXIT_OK


def cmd_view(args: argparse.Namespace) -> int:
    from viewers.rerun_sinks import ViewerError
    from viewers.rerun_view import view

    def out(line: str) -> None:
        if not args.quiet:
            print(line, flush=True)

    store = _store(args)
    try:
        view(store, _run_id(store, args.run_id), iteration=args.iteration, episode=args.episode, save=args.save,
             connect=args.connect, spawn=args.spawn, serve_web=args.serve_web, frames_every=args.frames_every,
             out=out, warn=lambda line: print(line, file=sys.stderr))
    except ViewerError as exc:
        raise CliError(str(exc)) from None
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    from viewers.otlp_export import DEFAULT_TEXT_LIMIT, export_run

    headers = {}
    for item in args.header:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise CliError(f"--header {item!r} is not KEY=VALUE; e.g. --header 'Authorization=Bearer TOKEN'")
        headers[key.strip()] = value.strip()
    store = _store(args)
    report = export_run(store, _run_id(store, args.run_id), args.otlp, protocol=args.protocol,
                        timeout_s=args.timeout, headers=headers or None, service_name=args.service_name,
                        text_limit=DEFAULT_TEXT_LIMIT if args.max_text_chars is None else args.max_text_chars)
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
    else:
        names = {"run": ("run", "runs"), "iteration": ("iteration", "iterations"), "llm_call": ("LLM call", "LLM calls"),
                 "episode": ("episode", "episodes")}
        kinds = ", ".join(f"{n} {names.get(kind, (kind, kind))[n != 1]}" for kind, n in report.spans.items())
        print(f"run {report.run_id}: {sum(report.spans.values())} spans ({kinds}) sent to {report.endpoint} "
              f"({report.protocol}); trace id {report.trace_id}")
    return EXIT_OK


def cmd_compare(args: argparse.Namespace) -> int:
    from pathlib import Path

    from pipeline.play.versus import CompareConfig
    from viewers.compare_report import text_lines, write_report

    if args.rerun and not args.rerun.endswith(".rrd") and not args.rerun.startswith(("rerun://", "rerun+http")):
        raise CliError(f"--rerun {args.rerun}: give a FILE.rrd or a rerun+http://HOST:PORT/proxy url")
    store = _store(args)
    workers = args.workers if args.workers is not None else min(args.episodes, os.cpu_count() or 1)
    config = CompareConfig(game=args.game, episodes=args.episodes, seed=args.seed, max_steps=args.max_steps,
                           context=args.context, workers=workers)
    result = compare(store, args.a, args.b, config, progress=lambda line: print(line, file=sys.stderr, flush=True))
    data = result.as_dict()
    if args.rerun:
        if data["mode"] != "versions":
            raise CliError("--rerun shows two played episodes: it goes with two versions (files or RUN:VERSION)")
        data["rerun"] = _compare_recording(store, data, args.rerun)
    out = Path(args.out) if args.out else (
        Path("reports") / f"compare-{data['runs'][0]['run_id']}-{data['runs'][1]['run_id']}"
        if data["mode"] == "runs" else None)
    if out is not None:
        data["report"] = str(write_report(data, out))
    if args.json:
        print(json.dumps(data, indent=2, default=str))
        return EXIT_OK
    for line in text_lines(data):
        print(line)
    if data.get("rerun"):
        print(f"side-by-side recording: {data['rerun']}")
    if data.get("report"):
        print(f"report: {data['report']}")
    return EXIT_OK


def is_version_ref(text: str) -> bool:
    """A policy file that exists, or ``RUN:VERSION``; anything else is taken for a run id."""
    from pathlib import Path

    return Path(text).is_file() or ":" in text


def compare(store, a: str, b: str, config=None, progress: Callable[[str], None] | None = None):
    """Compare ``a`` and ``b``: two runs (``pipeline/optimizer/runs.py``), or two versions
    (``pipeline/play/versus.py``)."""
    from pathlib import Path

    from pipeline.optimizer.runs import compare_runs
    from pipeline.play.versus import CompareConfig, compare_versions
    from tracing.policy_file import PolicyLoadError

    config = config or CompareConfig()
    for ref in (a, b):
        if ref.endswith(".py") and not Path(ref).is_file():
            raise PolicyLoadError(f"policy file '{ref}' does not exist")
    kinds = [is_version_ref(x) for x in (a, b)]
    if all(kinds):
        return compare_versions(store, a, b, config, progress)
    if not any(kinds):
        return compare_runs(store, a, b)
    run, other = (a, b) if not kinds[0] else (b, a)
    raise ValueError(f"{other!r} is a policy version but {run!r} is not (no such file): compare two runs "
                     f"(two run ids) or two versions (policy files or RUN:VERSION, e.g. {run}:best)")


def _compare_recording(store, data: dict, target: str) -> str:
    """Write the side-by-side recording of the first seed whose episodes part (else the first seed), in a
    separate process (this one forks episode workers: Rerun is never loaded here)."""
    import subprocess
    import tempfile
    from pathlib import Path

    episode = next((e for e in data["episodes"] if e["first_divergent_step"] is not None), data["episodes"][0])
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    to = target if target.startswith(("rerun://", "rerun+http")) else str(Path(target).resolve())
    with tempfile.NamedTemporaryFile("w", suffix=".diff") as diff:
        diff.write(data["diff"])
        diff.flush()
        command = [sys.executable, "-m", "viewers.rerun_compare", "--store", str(store.path.resolve()),
                   "--a", episode["A"]["episode_id"], "--b", episode["B"]["episode_id"], "--to", to,
                   "--diff", diff.name]
        if episode["first_divergent_step"] is not None:
            command += ["--divergent-step", str(episode["first_divergent_step"])]
        done = subprocess.run(command, capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise CliError(f"the side-by-side recording could not be written to {target}: {last}")
    return to


def cmd_batch(args: argparse.Namespace) -> int:
    from datetime import datetime
    from pathlib import Path

    from pipeline.jobs.batch import load_experiments, plan, run_local, run_ray
    from store import Store

    batch = load_experiments(args.experiments)
    if args.store:
        store = Store(args.store)
    elif batch.store:
        store = Store(Path(batch.store))  # relative to where the user runs it, like --store
    else:
        store = Store()
    planned = plan(batch, store)
    if not args.dry_run:  # a missing key stops the batch before any run starts
        from pipeline.llm.providers import check_credentials

        for item in planned:
            if item.action != "skip" and item.run.config.model:
                check_credentials(item.run.config.model, item.run.config.api_base)
    if args.dry_run:
        print(f"batch {batch.name}: {len(planned)} runs into {store.path}")
        for p in planned:
            print(f"  {p.action:<6} {p.run.label}" + (f"  (run {p.run_id}, {p.status})" if p.run_id else ""))
        return EXIT_OK
    log_path = Path(args.log) if args.log else store.path.with_name(f"{store.path.name}.{batch.name}.log")
    log_file = open(log_path, "a")
    show, stop = _batch_display()
    quiet = sys.stdout.isatty()

    def log(line: str) -> None:
        stamped = f"{datetime.now().isoformat(timespec='seconds')} {line}"
        log_file.write(stamped + "\n")
        log_file.flush()
        if not quiet:
            print(stamped, flush=True)

    log(f"batch {batch.name}: {len(planned)} runs ({sum(p.action == 'skip' for p in planned)} finished already), "
        f"executor {args.executor}, store {store.path}")
    try:
        if args.executor == "ray":
            result = run_ray(batch, store, planned, args.address, log, show)
        else:
            workers = args.workers or (os.cpu_count() or 1)
            result = run_local(batch, store, planned, workers, log, show,
                               log_dir=log_path.with_name(log_path.name + ".runs"))
    finally:
        stop()
    failed = result.failed
    log(f"batch {batch.name} done: {sum(p.state == 'finished' for p in result.progress)} finished, "
        f"{sum(p.state == 'skipped' for p in result.progress)} skipped, {len(failed)} failed")
    log_file.close()
    for p in failed:
        print(f"codearcade: {p.label} failed: {p.note}; rerun the same command to resume it", file=sys.stderr)
    return EXIT_EPISODE_FAILED if failed else EXIT_OK


def cmd_doctor(args: argparse.Namespace) -> int:
    from store.doctor import check_store, table_counts

    store = _store(args)
    with store.read(check=False) as con:  # a damaged store is the doctor's business: findings, not an error
        findings = check_store(con, store.path)
        counts = table_counts(con)
    errors = [f for f in findings if not f.warning]
    if args.json:
        print(json.dumps({"store": str(store.path), "ok": not errors, "counts": counts,
                          "findings": [{"check": f.check, "warning": f.warning, "rows": [list(map(str, r)) for r in f.rows]}
                                       for f in findings]}, indent=2))
    else:
        shown = (f"{'?' if n is None else format(n, ',')} {t}" for t, n in counts.items())
        print(f"{store.path}: " + ", ".join(shown))
        for f in findings:
            print(("warning: " if f.warning else "PROBLEM: ") + f.summary())
        print("ok: no damage found" if not errors else f"{len(errors)} kind(s) of damage found")
    return EXIT_OK if not errors else EXIT_EPISODE_FAILED


def cmd_replay(args: argparse.Namespace) -> int:
    from pipeline.optimizer.replay import replay

    store = _store(args)
    report = replay(store, _run_id(store, args.run_id), log=lambda line: print(line, file=sys.stderr))
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


def cmd_sql(args: argparse.Namespace) -> int:
    from store.views import run_user_query
    from viewers.tables import format_table, records, write_csv

    query = sys.stdin.read() if args.query == "-" else args.query
    if not query.strip():
        raise CliError("empty query; give a SQL statement, e.g. codearcade sql \"SELECT * FROM run_summary\"")
    store = _store(args)
    result = run_user_query(store, query)  # read-only for real; every row is fetched and the file let go first
    if args.json:
        print(json.dumps(records(result.columns, result.types, result.rows), indent=2, ensure_ascii=False))
    elif args.csv:
        write_csv(sys.stdout, result.columns, result.rows)
    elif result.columns:
        shown = result.rows[: args.max_rows] if args.max_rows else result.rows
        print(format_table(result.columns, shown, args.max_width))
        more = len(result.rows) - len(shown)
        print(f"({len(result.rows)} row{'s' * (len(result.rows) != 1)}"
              + (f", {more} not shown: use --max-rows 0, --csv or --json)" if more else ")"))
    return EXIT_OK


def cmd_runs(args: argparse.Namespace) -> int:
    from store.locks import run_is_live
    from store.views import run_query
    from viewers.tables import format_table, records

    store = _store(args)
    result = run_query(store, "SELECT * FROM run_summary ORDER BY created_at, run_id")
    runs = records(result.columns, result.types, result.rows)
    for r, row in zip(runs, result.rows):
        r["_created"] = row[result.columns.index("created_at")]
        if r["status"] == "running" and not run_is_live(store.path, r["run_id"]):
            r["status"] = "interrupted"  # killed: no process holds its lock (`doctor` says the same)
    if args.json:
        print(json.dumps([{k: v for k, v in r.items() if k != "_created"} for r in runs], indent=2))
        return EXIT_OK
    if not runs:
        print(f"no runs in {store.path}")
        return EXIT_OK
    rows = []
    for r in runs:
        done = "-" if r["kind"] == "eval" else f"{r['iterations_done']}/{r['iterations_planned'] or '?'}"
        rows.append((r["run_id"], r["_created"].strftime("%Y-%m-%d %H:%M"), r["kind"], r["game"],
                     r["model"], r["status"], done, None if r["best_score"] is None else round(r["best_score"], 2),
                     r["episodes"], r["total_tokens"]))
    print(format_table(("run", "created (UTC)", "kind", "game", "model", "status", "iterations", "best", "episodes",
                        "tokens"), rows, max_width=32, null="-"))
    return EXIT_OK


# Flags of `codearcade optimize` whose name is not the config field's with dashes.
_FLAG_NAMES = {"call_time_limit_s": "--call-time-limit", "max_cost_usd": "--max-cost",
               "max_wall_minutes": "--max-wall", "episode_time_limit_s": None, "workers": None, "policy": None,
               "game": "--game", "rollback": None}


def reproduce_command(run: dict[str, Any], config: dict[str, Any]) -> str:
    """The ``codearcade`` command line that starts a run with ``run``'s settings (defaults left out)."""
    import shlex

    if run["kind"] == "eval":
        parts = ["codearcade", "eval", config.get("policy") or "POLICY.py", "--game", run["game"]]
        for key, flag, default in (("episodes", "--episodes", 1), ("max_steps", "--max-steps", 4000),
                                   ("seed", "--seed", 0), ("sticky", "--sticky", 0.0),
                                   ("noop_max", "--noop-max", 0)):
            if config.get(key) not in (None, default):
                parts += [flag, str(config[key])]
        if config.get("trace"):
            parts.append("--trace")
        return shlex.join(parts)
    from pipeline.optimizer.config import OptimizeConfig

    defaults = OptimizeConfig()
    parts = ["codearcade", "optimize"] + ([config["policy"]] if config.get("policy") else [])
    parts += ["--game", run["game"]]
    for key in OptimizeConfig.__dataclass_fields__:
        flag = _FLAG_NAMES.get(key, "--" + key.replace("_", "-"))
        value = config.get(key)
        if flag is None or key == "game" or value is None or value == getattr(defaults, key):
            continue
        parts += [flag, f"{value:g}" if isinstance(value, float) else str(value)]
    if config.get("rollback") is False:
        parts.append("--no-rollback")
    return shlex.join(parts)


def cmd_report(args: argparse.Namespace) -> int:
    from pipeline.llm.providers import price
    from viewers.report import write_report

    path = write_report(_store(args), args.run_id, args.out, reproduce=reproduce_command, price=price)
    print(path)
    return EXIT_OK


def cmd_blame(args: argparse.Namespace) -> int:
    from viewers.blame import blame, format_blame

    report = blame(_store(args), args.run_id, args.version, args.iteration)
    print(json.dumps(report, indent=2, default=str) if args.json else format_blame(report))
    return EXIT_OK


def _user_errors() -> tuple[type[BaseException], ...]:
    from games import UnknownGameError
    from pipeline.llm.local import LocalModelError
    from store import StoreError
    from store.locks import RunBusyError
    from tracing.policy_file import PolicyLoadError

    return (CliError, PolicyLoadError, UnknownGameError, StoreError, RunBusyError, LocalModelError, ValueError)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] = args.handler
    try:
        return handler(args)
    except BrokenPipeError:  # `codearcade sql ... | head`: the reader has what it wanted; say nothing more
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so the interpreter's final flush does not fail again
        return EXIT_OK
    except KeyboardInterrupt:
        print("codearcade: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except _user_errors() as exc:
        print(f"codearcade: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except _store_damage_errors() as exc:  # a store damaged beyond what the checks on opening see
        from store.views import one_line

        print(f"codearcade: error: cannot use the store ({one_line(exc)[:300]}); it may be damaged: "
              "`codearcade doctor` reports what is left", file=sys.stderr)
        return EXIT_BAD_INPUT


def _store_damage_errors() -> tuple[type[BaseException], ...]:
    import duckdb

    return (duckdb.IOException, duckdb.SerializationException, duckdb.InternalException)

