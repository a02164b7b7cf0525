"""Environment steps of a 20-iteration greedy run with and without cascade evaluation and the evaluation cache.

The same run twice against a scripted model whose replies are a seeded choice from candidate policies of mixed
quality (the competent Pong policy, always-up, a worse dead zone, a reply that raises, a reply that is not code;
tests/test_strategies.py ``POOL``), so both runs get the same replies in the same order:

- baseline: ``--no-eval-cache``, no screening: every iteration plays its training rollout and evaluation;
- cheap: the evaluation cache on and ``--screen-steps`` (default 300).

It counts each run's environment steps with SQL (``steps`` rows of its episodes) and prints the ratio, with the
best-so-far curve of both (the cheap run must reach the same best scores).

    .venv/bin/python bench/cascade_steps.py [--iterations 20] [--screen-steps 300] [--eval-max-steps 2000]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
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

STEPS_SQL = "SELECT count(*) FROM steps s JOIN episodes e USING (episode_id) WHERE e.run_id = ?"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--screen-steps", type=int, default=300)
    parser.add_argument("--eval-max-steps", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=4, help="seed of the scripted model's choices")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="codearcade-bench-"))
    store = Store(work / "cascade.duckdb")
    common = dict(game="pong", iterations=args.iterations, eval_max_steps=args.eval_max_steps, workers=2)
    results = {}
    for name, extra in (("baseline", dict(eval_cache=False)), ("cheap", dict(screen_steps=args.screen_steps))):
        with ScriptedModel([{"pool": POOL, "seed": args.seed}], work / name) as model:
            client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
            result = optimize(OptimizeConfig(**common, **extra), store, client)
        steps = store.query(STEPS_SQL, [result.run_id])[0][0]
        kinds = dict(store.query("SELECT evaluation, count(*) FROM candidates WHERE run_id = ? GROUP BY ALL",
                                 [result.run_id]))
        results[name] = (result, steps, kinds)
        print(f"{name:<9} {result.status}: {steps:,} environment steps; candidates by evaluation: {kinds}")
    (base, base_steps, _), (cheap, cheap_steps, _) = results["baseline"], results["cheap"]
    base_best = [i.best_score for i in base.iterations]
    cheap_best = [i.best_score for i in cheap.iterations]
    print(f"best so far, baseline: {base_best}")
    print(f"best so far, cheap:    {cheap_best}")
    print(f"steps cheap / baseline = {cheap_steps / base_steps:.2f}; same best-so-far curve: {base_best == cheap_best}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
