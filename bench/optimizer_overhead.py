"""The optimizer's own overhead per iteration: everything but the LLM call and the environment.

A 20-iteration Pong run against a scripted model that takes ``--delay`` seconds per call (default 2) and
answers with a seeded choice from candidate policies of mixed quality (tests/scripted_llm.py), through litellm
over real HTTP, into a real store. From the store, per iteration:

- LLM: the wall time during which at least one call was in flight (``llm_calls``: each ran for ``latency_s``
  up to ``created_at``): calls made at once count once, a repair turn after its proposal adds its own time;
- environment: the time playing its episodes, verification included (``iterations.eval_s``; 0 when every
  candidate reused stored episodes);
- overhead: the rest of the iterations' wall time — reading the store, building the prompt, parsing, validating
  the candidate in a worker, deciding and writing.

The iterations' wall time is the span from the start of iteration 1 to the end of the last one (so what
happens between two iterations counts too). It prints each part's share of it; the target is overhead < 5%.

    .venv/bin/python bench/optimizer_overhead.py [--iterations 20] [--delay 2] [--strategy greedy]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("LITELLM_LOCAL_MODEL_COST_MAP", "True")

from pipeline.llm.client import LiteLLMClient  # noqa: E402
from pipeline.optimizer.config import OptimizeConfig  # noqa: E402
from pipeline.optimizer.loop import optimize  # noqa: E402
from store import Store  # noqa: E402
from tests.scripted_llm import ScriptedModel  # noqa: E402
from tests.test_strategies import POOL  # noqa: E402

TARGET = 0.05


def waiting_on_calls(calls: list[tuple[float, float]]) -> float:
    """Seconds during which at least one LLM call was in flight, from ``(start, end)`` rows: calls made at once
    count once (the longest), calls made one after the other (a repair turn after its proposal) add up."""
    total, reach = 0.0, -math.inf
    for start, end in sorted(calls):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--delay", type=float, default=2.0, help="seconds the scripted model takes per call")
    parser.add_argument("--strategy", default="greedy")
    parser.add_argument("--candidates", type=int, default=None)
    parser.add_argument("--eval-max-steps", type=int, default=1000)
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="codearcade-bench-"))
    store = Store(work / "overhead.duckdb")
    config = OptimizeConfig(game="pong", iterations=args.iterations, eval_max_steps=args.eval_max_steps,
                            strategy=args.strategy, candidates=args.candidates, temperature=1.0, workers=2)
    with ScriptedModel([{"pool": POOL, "seed": 1, "sleep": args.delay}], work) as model:
        client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
        started = time.monotonic()
        result = optimize(config, store, client)
        total = time.monotonic() - started
    rows = store.query("SELECT iteration, eval_s FROM iterations WHERE run_id = ? AND iteration > 0 "
                       "ORDER BY iteration", [result.run_id])
    (wall,) = store.query("SELECT epoch(max(finished_at) - min(started_at)) FROM iterations "
                          "WHERE run_id = ? AND iteration > 0", [result.run_id])[0]
    # a call's row is stored when it ends (created_at): it ran over [created_at - latency_s, created_at]
    calls = store.query("SELECT epoch(created_at) - latency_s, epoch(created_at) FROM llm_calls "
                        "WHERE run_id = ? AND iteration > 0 AND latency_s IS NOT NULL", [result.run_id])
    env = sum(r[1] or 0.0 for r in rows)
    llm = waiting_on_calls(calls)
    overhead = wall - env - llm
    cached = store.query("SELECT count(*) FROM candidates WHERE run_id = ? AND evaluation = 'cached'",
                         [result.run_id])[0][0]
    print(f"{args.strategy}: {len(rows)} iterations after the first evaluation, {result.status}; "
          f"{cached} candidates reused stored episodes; whole command {total:.1f} s (model start-up and "
          f"iteration 0 included)")
    print(f"{'part':<12} {'seconds':>8} {'share':>7}")
    for name, seconds in (("LLM calls", llm), ("environment", env), ("overhead", overhead)):
        print(f"{name:<12} {seconds:>8.1f} {seconds / wall:>7.1%}")
    print(f"{'iterations':<12} {wall:>8.1f} {1:>7.0%}")
    phase = store.query("SELECT avg(llm_s) FROM iterations WHERE run_id = ? AND iteration > 0", [result.run_id])[0][0]
    print(f"{len(calls) / len(rows):.1f} calls per iteration (its proposals at once, a repair turn after its "
          f"proposal), {llm / len(rows):.2f} s of them in flight: the proposal phase (prompts, calls, validation) "
          f"took {phase:.2f} s per iteration = {phase / args.delay:.2f} x one call's {args.delay:g} s")
    share = overhead / wall
    print(f"overhead per iteration: {overhead / len(rows) * 1000:.0f} ms; overhead / wall = {share:.3f} "
          f"(target < {TARGET}) -> {'OK' if share < TARGET else 'ABOVE TARGET'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
