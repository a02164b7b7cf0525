"""The asynchronous proposal pool against the barrier loop: assessed candidates per minute at the same call budget.

Best-of-n (4 candidates an iteration) on Pong against a scripted model whose every call takes a seeded log-normal
time (median ``--latency`` seconds, ``--sigma`` 0.6: most calls near the median, a few several times longer, as
hosted models are) and answers with a seeded choice from candidate policies of mixed quality (tests/scripted_llm.py),
through litellm over real HTTP, into a real store, with real episodes. Both loops get the same call budget
(``--max-llm-calls``) and keep at most ``--in-flight`` calls at once; repair turns are off so that a call budget is
the same number of proposals on both sides. The two configurations alternate, ``--repeats`` times each; each one's
best repeat counts (noise only adds time) and the median of the paired ratios is printed beside it.

- barrier: each iteration's 4 calls together, then its candidates played, then the next iteration;
- pool (``--pool``): a call starts whenever a slot frees, each candidate is played when its reply is in.

Throughput is the candidates assessed in committed iterations per minute, from the end of iteration 0 to the
last commit. Target: pool / barrier >= 1.5.

A second table times greedy (the paper's loop, which keeps its strict order): its wall time per update beside the
call's latency plus what the next prompt needs of its episodes (the training rollout and, with staged feedback, the
evaluation score): the ratio is what the loop itself adds; no worse than 1.1.

    .venv/bin/python bench/proposal_pool.py [--calls 24] [--latency 2] [--repeats 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
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

TARGET = 1.5
GREEDY_LIMIT = 1.1
CANDIDATES = 4


def throughput(store: Store, run_id: str) -> tuple[float, int, float]:
    """(assessed candidates per minute, candidates, seconds) from the end of iteration 0 to the last commit."""
    count, seconds = store.query(
        """SELECT (SELECT count(*) FROM candidates WHERE run_id = $1 AND iteration > 0),
                  epoch(max(finished_at) FILTER (WHERE iteration > 0) - max(finished_at) FILTER (WHERE iteration = 0))
           FROM iterations WHERE run_id = $1""", [run_id])[0]
    return count / (seconds / 60), count, seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=24, help="the call budget of each run (default: 24)")
    parser.add_argument("--latency", type=float, default=2.0, help="median seconds per call (default: 2)")
    parser.add_argument("--sigma", type=float, default=0.6, help="log-normal spread of the latency (default: 0.6)")
    parser.add_argument("--in-flight", type=int, default=4, help="calls in flight at most (default: 4)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--greedy-iterations", type=int, default=4)
    parser.add_argument("--eval-max-steps", type=int, default=600)
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="codearcade-bench-"))
    store = Store(work / "pool.duckdb")
    common = dict(game="pong", strategy="best-of-n", candidates=CANDIDATES, iterations=args.calls // CANDIDATES + 1,
                  max_llm_calls=args.calls, max_concurrent_calls=args.in_flight, eval_max_steps=args.eval_max_steps,
                  rollout_steps=50, temperature=1.0, workers=2, repairs=0, audit_episodes=0, rng_key="bench")
    found: dict[str, list[tuple[float, int, float]]] = {"barrier": [], "pool": []}
    script = [{"pool": POOL, "latency": [args.latency, args.sigma, 7]}]
    for repeat in range(args.repeats):
        for name in ("barrier", "pool"):
            # a fresh model for each run, seeded by the repeat: both loops of a repeat meet the same replies and
            # the same latencies, request by request
            script[0]["seed"] = script[0]["latency"][2] = repeat
            with ScriptedModel(script, work / f"model-{repeat}-{name}") as model:
                client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
                result = optimize(OptimizeConfig(**common, pool=name == "pool"), store, client)
            found[name].append(throughput(store, result.run_id))
            rate, count, seconds = found[name][-1]
            print(f"repeat {repeat + 1} {name:<8} {count:>3} candidates in {seconds:6.1f} s = {rate:6.1f} "
                  f"per minute ({result.status})", flush=True)
    print(f"\nbest-of-n, {CANDIDATES} candidates an iteration, {args.calls} calls each, at most {args.in_flight} "
          f"in flight; latency log-normal, median {args.latency:g} s, sigma {args.sigma:g}")
    print(f"{'loop':<8} {'candidates/min':>15}")
    best = {name: max(rate for rate, _, _ in runs) for name, runs in found.items()}
    for name in found:
        print(f"{name:<8} {best[name]:>15.1f}")
    paired = statistics.median(p[0] / b[0] for b, p in zip(found["barrier"], found["pool"]))
    ratio = best["pool"] / best["barrier"]
    print(f"pool / barrier = {ratio:.2f} (median of paired ratios {paired:.2f}; target >= {TARGET}) -> "
          f"{'OK' if ratio >= TARGET else 'BELOW TARGET'}")

    with ScriptedModel([{"pool": POOL, "seed": 1, "latency": [args.latency, args.sigma, 7]}], work / "model") as model:
        client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
        config = OptimizeConfig(game="pong", iterations=args.greedy_iterations, eval_max_steps=args.eval_max_steps,
                                rollout_steps=50, temperature=1.0, workers=2, repairs=0, audit_episodes=0,
                                rng_key="bench")
        started = time.monotonic()
        result = optimize(config, store, client)
        rows = store.query(
            """SELECT i.wall_s, i.train_s, i.eval_s,
                      (SELECT sum(c.latency_s) FROM llm_calls c WHERE c.run_id = i.run_id AND c.iteration = i.iteration)
               FROM iterations i WHERE i.run_id = ? AND i.iteration > 0 ORDER BY i.iteration""", [result.run_id])
        wall = statistics.fmean(r[0] for r in rows)
        call = statistics.fmean(r[3] or 0 for r in rows)
        needed = statistics.fmean(r[2] for r in rows)  # staged feedback: the next prompt needs the evaluation score
        greedy = wall / (call + needed)
        print(f"\ngreedy, {len(rows)} updates ({time.monotonic() - started:.0f} s): wall per update {wall:.2f} s; "
              f"the call {call:.2f} s + the episodes the next prompt needs {needed:.2f} s (training rollout and "
              f"evaluation) = {call + needed:.2f} s")
        print(f"greedy wall / (call + needed episodes) = {greedy:.2f} (no worse than {GREEDY_LIMIT}) -> "
              f"{'OK' if greedy <= GREEDY_LIMIT else 'ABOVE'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
