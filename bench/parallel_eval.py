"""Evaluation throughput with 1 against 2 worker processes, measured in the same run (target: >= 1.7x).

Plays the same evaluation (the example Breakout policy, several full episodes, every step stored) with
``workers=1`` and ``workers=2`` in alternation, and prints the steps/s of each and the median ratio of the
pairs. On a 2-core machine the parent's store writes share the cores with the workers.

    .venv/bin/python bench/parallel_eval.py [--game breakout] [--episodes 4] [--repeats 3]
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

from pipeline.evaluate import EvalConfig, evaluate  # noqa: E402
from store import Store  # noqa: E402

TARGET = 1.7


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--game", default="breakout")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    store = Store(Path(tempfile.mkdtemp(prefix="codearcade-bench-")) / "parallel.duckdb")
    policy = ROOT / "examples" / f"{args.game}.py"
    evaluate(policy, EvalConfig(episodes=1, max_steps=50), store)  # warm caches and the store

    rates: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(args.repeats):
        for workers in (1, 2):
            start = time.perf_counter()
            result = evaluate(policy, EvalConfig(episodes=args.episodes, workers=workers, seed=0), store)
            elapsed = time.perf_counter() - start
            rates[workers].append(sum(o.episode["length"] for o in result.outcomes) / elapsed)
    ratio = statistics.median(b / a for a, b in zip(rates[1], rates[2]))
    print(f"{args.game}: {args.episodes} episodes per measurement, {args.repeats} repeats")
    print(f"1 worker  {statistics.median(rates[1]):8.0f} steps/s")
    print(f"2 workers {statistics.median(rates[2]):8.0f} steps/s")
    print(f"ratio     {ratio:8.2f}x  (target >= {TARGET}x){'' if ratio >= TARGET else '  BELOW TARGET'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
