"""Steps of the training rollout a prompt covers per 1k prompt tokens, with and without collapsing repeated steps.

For each policy (the game's scaffold and its competent policy from tests/policies/) it plays iteration 0 of an
optimization run into a temporary store (the traced training rollout: 400 steps for Pong), then builds the first
update's prompt at several token budgets both ways and prints steps covered / (prompt tokens / 1000) and the
ratio after / before. Collapsing (``OptimizeConfig.collapse_repeats``, on for new runs) shows a run of steps
whose calls, action and reward repeat as one line.

    .venv/bin/python bench/prompt_density.py [--game pong] [--budgets 4000 16000]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.optimizer.config import OptimizeConfig  # noqa: E402

from pipeline.llm.tokens import TokenCounter  # noqa: E402
from pipeline.optimizer.context import read_context  # noqa: E402
from pipeline.optimizer.loop import load_state, run_loop, start_run  # noqa: E402
from pipeline.optimizer.prompt import build_prompt  # noqa: E402
from store import Store  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--game", default="pong")
    parser.add_argument("--budgets", type=int, nargs="+", default=[4000, 8000, 16000])
    args = parser.parse_args()
    counter = TokenCounter("openai/gpt-4o")
    store = Store(Path(tempfile.mkdtemp(prefix="codearcade-bench-")) / "density.duckdb")
    competent = ROOT / "tests" / "policies" / f"{args.game}_competent.py"
    policies = {"scaffold": None, "competent": str(competent) if competent.exists() else None}
    print(f"{'policy':<10} {'budget':>7} {'steps/1k before':>16} {'steps/1k after':>15} {'ratio':>6}  steps shown")
    for name, policy in policies.items():
        if name == "competent" and policy is None:
            continue
        run_id = start_run(OptimizeConfig(game=args.game, policy=policy, iterations=0, eval_max_steps=300), store,
                           "openai/gpt-4o")
        run_loop(store, load_state(store, run_id), None)
        with store.read() as con:
            plain = read_context(con, run_id, 1, memory=5)
            collapsed = read_context(con, run_id, 1, memory=5, collapse_repeats=True)
        for budget in args.budgets:
            before, after = build_prompt(plain, budget, counter), build_prompt(collapsed, budget, counter)
            a = len(before.steps_shown) / before.tokens * 1000
            b = len(after.steps_shown) / after.tokens * 1000
            print(f"{name:<10} {budget:>7} {a:>16.1f} {b:>15.1f} {b / a:>6.2f}  "
                  f"{len(before.steps_shown)} -> {len(after.steps_shown)} of {len(plain.train_steps)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
