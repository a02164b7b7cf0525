"""Run every fuzz target for many examples without stopping at the first failure, and print each class of
problem found (the recipe's shape, the target, what the oracle saw), with the worst example of each.

    .venv/bin/python -m tests.fuzz.survey [--tree DIR] [--examples N] [--targets frame,nodes,rerun,failure]

``--tree``: the tree whose trusted code is fuzzed (e.g. ``git worktree add /tmp/pre38 440c52b``: the code
before issue 38's fixes). The draws are derandomized: the same N examples every run. ``--json FILE`` writes
every problem found (target, recipe, what was wrong), the material for tests/fuzz/corpus.json.
"""

from __future__ import annotations

import argparse
import json

from hypothesis import HealthCheck, given, settings

from tests.fuzz.oracle import Server
from tests.fuzz.test_decoders import STRATEGIES, budget_of


def shape(recipe: dict) -> str:
    """The class of a recipe: its kind and the draw that matters for it."""
    kind = recipe["kind"]
    if kind == "table":
        lines = "lines" if recipe["lines"] >= 600 else "few lines"
        return f"table/{recipe['value_kind']}/{lines}"
    if kind in ("metadata", "fields"):
        return f"{kind}/{'shared' if recipe['shared'] else 'plain'}"
    if kind == "type":
        return f"type/{recipe['type']}"
    if kind == "failure":
        return f"failure/{recipe['shape']}"
    return kind


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree")
    parser.add_argument("--examples", type=int, default=150)
    parser.add_argument("--targets", default="frame,nodes,rerun,failure")
    parser.add_argument("--json")
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args()
    server = Server(args.tree)
    found: dict[tuple[str, str, str], tuple[int, dict, str]] = {}
    every: list[dict] = []
    try:
        def survey(target: str) -> None:
            @settings(max_examples=args.examples, derandomize=True, deadline=None, database=None,
                      suppress_health_check=list(HealthCheck))
            @given(STRATEGIES[target])
            def run(recipe: dict) -> None:
                verdict = server.judge(target, recipe)
                if args.verbose:
                    print(target, verdict.outcome, verdict.sent, verdict.growth, verdict.store, verdict.detail.splitlines()[0][:100] if verdict.detail else "", json.dumps(recipe)[:150], flush=True)
                for problem in verdict.problems(budget_of(recipe)):
                    what = problem.split(" ")[0] if not problem.startswith("peak") else "peak RSS"
                    if problem.startswith("the store"):
                        what = "store"
                    key = (target, shape(recipe), what)
                    cost = verdict.growth or 0
                    every.append({"target": target, "recipe": recipe, "problem": problem})
                    if key not in found or cost > found[key][0]:
                        found[key] = (cost, recipe, problem)
            run()

        for target in args.targets.split(","):
            survey(target)
    finally:
        server.close()
    for (target, kind, what), (_, recipe, problem) in sorted(found.items()):
        print(f"{target:8} {kind:28} {problem[:150]}")
        print(f"{'':8} {json.dumps(recipe)[:200]}")
    print(f"{len(found)} classes of problem, {len(every)} examples with a problem")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(every, f, indent=1)


if __name__ == "__main__":
    main()
