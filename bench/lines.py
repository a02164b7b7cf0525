"""What recording the lines that ran (``nodes.lines_run``) adds to a traced evaluation, measured in one run.

For each policy it plays ``codearcade eval --trace`` (one worker process, every step and node written to a real
DuckDB store) with line recording off (the baseline: today's ``--trace``) and on, interleaved, several times,
and prints steps/s of each and the ratio of their best times (traced+lines / traced). Line recording stays on
with ``--trace`` while the ratio stays under 1.3; above that it would have to become an opt-in flag.

    .venv/bin/python bench/lines.py [--policies tests/policies/pong_competent.py ...] [--episodes 1] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.play.evaluate import EvalConfig, evaluate  # noqa: E402
from store import Store  # noqa: E402

DEFAULT_POLICIES = ["tests/policies/pong_competent.py", "games/scaffolds/breakout.py",
                    "games/scaffolds/space_invaders.py"]
LIMIT = 1.3


def timed(policy: Path, store: Store, episodes: int, lines: bool, max_steps: int) -> tuple[float, float, int]:
    """Seconds for a traced evaluation, seconds of it inside the policy (``episodes.policy_s``: the traced
    calls, where line recording adds its cost), and the steps it played."""
    config = EvalConfig(episodes=episodes, trace=True, trace_lines=lines, workers=1, max_steps=max_steps)
    start = time.perf_counter()
    result = evaluate(policy, config, store)
    seconds = time.perf_counter() - start
    [(steps, policy_s)] = store.query("SELECT sum(length), sum(policy_s) FROM episodes WHERE run_id = ?",
                                      [result.run_id])
    return seconds, float(policy_s), int(steps)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policies", nargs="+", default=DEFAULT_POLICIES)
    parser.add_argument("--episodes", type=int, default=1, help="episodes per measurement (default: 1)")
    parser.add_argument("--max-steps", type=int, default=4000)
    parser.add_argument("--repeats", type=int, default=5, help="measurements per configuration (best taken)")
    args = parser.parse_args()

    store = Store(Path(tempfile.mkdtemp(prefix="codearcade-bench-")) / "bench.duckdb")
    evaluate(ROOT / "games" / "scaffolds" / "pong.py", EvalConfig(episodes=1, max_steps=50), store)  # forkserver up
    print(f"{'policy':<36} {'steps':>6} {'--trace':>11} {'+ lines':>11} {'ratio':>6} {'policy us/step':>17}   "
          "(median of paired ratios)")
    worst = 0.0
    for name in args.policies:
        policy = ROOT / name
        seconds: dict[bool, list[float]] = {False: [], True: []}
        inside: dict[bool, list[float]] = {False: [], True: []}
        steps = 0
        order = [False, True]
        for _ in range(args.repeats):
            for lines in order:
                elapsed, policy_s, steps = timed(policy, store, args.episodes, lines, args.max_steps)
                seconds[lines].append(elapsed)
                inside[lines].append(policy_s)
            order.reverse()  # neither configuration always runs first
        best = {k: min(v) for k, v in seconds.items()}
        ratio = best[True] / best[False]
        paired = statistics.median(w / wo for w, wo in zip(seconds[True], seconds[False]))
        worst = max(worst, ratio)
        per_step = {k: 1e6 * min(v) / steps for k, v in inside.items()}
        print(f"{Path(name).name:<36} {steps:>6} {steps / best[False]:>7.0f} st/s {steps / best[True]:>7.0f} st/s "
              f"{ratio:>6.2f} {per_step[False]:>7.0f} -> {per_step[True]:>5.0f}   ({paired:.2f})")
    verdict = "on with --trace" if worst <= LIMIT else "should be opt-in (--lines)"
    print(f"time ratio traced+lines / traced, best of {args.repeats}: worst {worst:.2f} (limit {LIMIT}): {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
