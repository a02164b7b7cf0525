"""The asynchronous proposal pool against the barrier loop: the best score reached per call and per minute (anytime
curves), beside the candidates assessed per minute, at the same call budget.

Best-of-n (4 candidates an iteration) on Freeway against a scripted model that improves the code it is given by one
rung (tests/scripted_llm.py, ``climb``): the starter moves the chicken up with probability 0.2, and each rung
raises it (0.3, 0.4, 0.7, 0.8, 0.9, 1.0: 500 steps of the run's random stream score 0, 1, 2, 3, 4, 5, 7, strictly
better each rung). The model answers a prompt one way (a stale prompt gets the reply it got before: the worst case
for prompts built from old code), and every call takes a seeded log-normal time (median ``--latency`` seconds,
``--sigma`` 0.6: most calls near the median, a few several times longer, as hosted models are). Through litellm
over real HTTP, into a real store, with real episodes. Both loops get the same call budget (``--max-llm-calls``)
and keep at most ``--in-flight`` calls at once; repair turns are off so that a call is a proposal on both sides.
Each seed (``--repeats``) runs both loops against a fresh model with the same latencies, request by request.

- barrier: each iteration's 4 calls together, then its candidates played, then the next iteration;
- pool (``--pool``): a call starts whenever a slot frees, prompted from every candidate assessed so far (committed
  or not), and each candidate is played when its reply is in.

Printed, median over the seeds:

- per call: the best score among the candidates of the first k calls (calls in the order they started);
- per minute: the best score committed by t seconds after iteration 0 (what the run reports as its best so far);
- throughput: candidates assessed in committed iterations per minute, from the end of iteration 0 to the last
  commit (target pool / barrier >= 1.5);
- the rung the best candidate reached after all the calls (issue 39: the pool at most two rungs below).

A second table times greedy (the paper's loop, which keeps its strict order): its wall time per update beside the
call's latency plus what the next prompt needs of its episodes (the training rollout and, with staged feedback, the
evaluation score): the ratio is what the loop itself adds; no worse than 1.1.

    .venv/bin/python bench/proposal_pool.py [--calls 24] [--latency 2] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
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
from store.readers import policy_text  # noqa: E402
from tests.conftest import json_reply, random_policy  # noqa: E402
from tests.scripted_llm import ScriptedModel  # noqa: E402
from tests.test_strategies import POOL  # noqa: E402

TARGET = 1.5
GREEDY_LIMIT = 1.1
CANDIDATES = 4
RUNGS = ("0.2", "0.3", "0.4", "0.7", "0.8", "0.9", "1.0")
"""The chance the chicken moves up, rung by rung (the first is the starter's)."""
MARKS = [f"random.random() < {p}" for p in RUNGS]
CLIMB = [json_reply({"act": f"def act(self, obs):\n    return 1 if {mark} else 0\n"}) for mark in MARKS]


def throughput(store: Store, run_id: str) -> tuple[float, int, float]:
    """(assessed candidates per minute, candidates, seconds) from the end of iteration 0 to the last commit."""
    count, seconds = store.query(
        """SELECT (SELECT count(*) FROM candidates WHERE run_id = $1 AND iteration > 0),
                  epoch(max(finished_at) FILTER (WHERE iteration > 0) - max(finished_at) FILTER (WHERE iteration = 0))
           FROM iterations WHERE run_id = $1""", [run_id])[0]
    return count / (seconds / 60), count, seconds


def rung(text: str) -> int:
    return max(i for i, mark in enumerate(MARKS) if mark in text)


def anytime(store: Store, run_id: str) -> dict:
    """The run's anytime curves: the best score (and rung) after each call, in the order the calls started, and
    the best score committed over time (seconds after iteration 0's commit)."""
    starter = store.query("SELECT score FROM iterations WHERE run_id = ? AND iteration = 0", [run_id])[0][0]
    made = store.query(
        """SELECT c.score, c.policy_version_id FROM candidates c JOIN llm_calls l ON l.call_id = c.llm_call_id
           WHERE c.run_id = ? ORDER BY epoch(l.created_at) - l.latency_s, l.call_id""",
        [run_id])
    with store.read() as con:
        texts = {v: policy_text(con, run_id, v) for _, v in made}
    per_call, best, best_rung = [], starter, 0
    for score, version in made:
        if score is not None and score > best:
            best = score
        best_rung = max(best_rung, rung(texts[version]))
        per_call.append((best, best_rung))
    committed = store.query(
        """SELECT epoch(finished_at - min(finished_at) OVER ()), best_score FROM iterations WHERE run_id = ?
           ORDER BY iteration""", [run_id])
    return {"per_call": per_call, "committed": committed}


def best_at(committed: list[tuple[float, float]], seconds: float) -> float:
    return max(score for at, score in committed if at <= seconds)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=24, help="the call budget of each run (default: 24)")
    parser.add_argument("--latency", type=float, default=2.0, help="median seconds per call (default: 2)")
    parser.add_argument("--sigma", type=float, default=0.6, help="log-normal spread of the latency (default: 0.6)")
    parser.add_argument("--in-flight", type=int, default=4, help="calls in flight at most (default: 4)")
    parser.add_argument("--repeats", type=int, default=5, help="seeds of the latencies (default: 5)")
    parser.add_argument("--greedy-iterations", type=int, default=4)
    parser.add_argument("--eval-max-steps", type=int, default=500)
    parser.add_argument("--json", type=Path, help="also write every run's curves to this file")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="codearcade-bench-"))
    store = Store(work / "pool.duckdb")
    starter = work / "freeway.py"
    starter.write_text(random_policy("freeway", f"1 if {MARKS[0]} else 0"))
    common = dict(policy=str(starter), game="freeway", strategy="best-of-n", candidates=CANDIDATES,
                  iterations=args.calls // CANDIDATES + 1, max_llm_calls=args.calls,
                  max_concurrent_calls=args.in_flight, eval_max_steps=args.eval_max_steps, rollout_steps=40,
                  temperature=1.0, workers=2, repairs=0, audit_episodes=0, rng_key="bench")
    found: dict[str, list[tuple[float, int, float]]] = {"barrier": [], "pool": []}
    curves: dict[str, list[dict]] = {"barrier": [], "pool": []}
    for repeat in range(args.repeats):
        for name in ("barrier", "pool"):
            script = [{"climb": CLIMB, "marks": MARKS, "latency": [args.latency, args.sigma, repeat]}]
            with ScriptedModel(script, work / f"model-{repeat}-{name}") as model:
                client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
                result = optimize(OptimizeConfig(**common, pool=name == "pool"), store, client)
            found[name].append(throughput(store, result.run_id))
            curves[name].append(anytime(store, result.run_id))
            rate, count, seconds = found[name][-1]
            best, top = curves[name][-1]["per_call"][-1]
            print(f"seed {repeat} {name:<8} {count:>3} candidates in {seconds:6.1f} s = {rate:6.1f} per minute; "
                  f"best {best:g} (rung {top} of {len(RUNGS) - 1}) ({result.status}"
                  f"{': ' + result.error if result.error else ''})", flush=True)

    print(f"\nbest-of-n, {CANDIDATES} candidates an iteration, {args.calls} calls each, at most {args.in_flight} in "
          f"flight; latency log-normal, median {args.latency:g} s, sigma {args.sigma:g}; median of {args.repeats} "
          f"seeds")
    print("best score after k calls (rung in brackets):")
    print(f"{'calls':>6} {'barrier':>12} {'pool':>12}")
    calls = min(len(c["per_call"]) for runs in curves.values() for c in runs)
    for k in sorted({*range(CANDIDATES, calls + 1, CANDIDATES), calls}):
        cells = []
        for name in ("barrier", "pool"):
            score = statistics.median(c["per_call"][k - 1][0] for c in curves[name])
            level = statistics.median(c["per_call"][k - 1][1] for c in curves[name])
            cells.append(f"{score:g} [{level:g}]")
        print(f"{k:>6} {cells[0]:>12} {cells[1]:>12}")
    longest = max(c["committed"][-1][0] for runs in curves.values() for c in runs)
    step = max(5, round(longest / 8 / 5) * 5)
    print("best score committed after t seconds:")
    print(f"{'t (s)':>6} {'barrier':>12} {'pool':>12}")
    for t in range(step, int(longest) + step, step):
        cells = [f"{statistics.median(best_at(c['committed'], t) for c in curves[name]):g}"
                 for name in ("barrier", "pool")]
        print(f"{t:>6} {cells[0]:>12} {cells[1]:>12}")
    ends = {name: statistics.median(c["per_call"][-1][1] for c in curves[name]) for name in curves}
    print(f"rung after {calls} calls: barrier {ends['barrier']:g}, pool {ends['pool']:g} (issue 39: the pool at most "
          f"2 below) -> {'OK' if ends['pool'] >= ends['barrier'] - 2 else 'MORE THAN 2 BELOW'}")
    print(f"{'loop':<8} {'candidates/min':>15}")
    best = {name: max(rate for rate, _, _ in runs) for name, runs in found.items()}
    for name in found:
        print(f"{name:<8} {best[name]:>15.1f}")
    paired = statistics.median(p[0] / b[0] for b, p in zip(found["barrier"], found["pool"]))
    ratio = best["pool"] / best["barrier"]
    print(f"pool / barrier = {ratio:.2f} (median of paired ratios {paired:.2f}; target >= {TARGET}) -> "
          f"{'OK' if ratio >= TARGET else 'BELOW TARGET'}")
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "curves": curves,
                                         "throughput": found}, indent=1))

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
