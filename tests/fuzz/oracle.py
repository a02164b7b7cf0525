"""The cost oracle: sends a recipe's bytes to the trusted side (tests/fuzz/server.py, a process of its own) and
judges what it cost.

An input passes when the trusted process neither raised nor died (the outcome is an accepted episode or a
recorded policy error / refused message), its peak RSS grew by at most :data:`GROWTH_FACTOR` x the bytes sent
plus :data:`GROWTH_SLACK` (what decoding a honest input costs: pools, first use of DuckDB and Rerun), and the store
grew by at most an honest episode's rows plus the episode's byte budget. ``CODEARCADE_FUZZ_TREE`` names the tree
whose trusted code is fuzzed (default: this checkout), e.g. a worktree of the commit before a fix.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from tests.fuzz import recipes

ROOT = Path(__file__).resolve().parents[2]
GROWTH_FACTOR = 4
"""Peak RSS a decode may add, per byte received (the budget's bound of every stage: docs/sandbox.md)."""
GROWTH_SLACK = {"frame": 16 * 2**20, "failure": 16 * 2**20, "nodes": 96 * 2**20, "rerun": 64 * 2**20}
"""Peak RSS a decode may add whatever it received, per target: what an honest 1-row episode costs there (Arrow's
pool: ~5 MB; DuckDB's first write into a store: ~50-55 MB; Rerun's first recording in a process: ~20-30 MB),
with room to spare."""
STORE_SLACK = 4 * 2**20
"""What the store may grow by for an honest fuzzed episode (its rows, and the blocks DuckDB writes them in)."""


@dataclass
class Verdict:
    target: str
    recipe: dict
    sent: int
    outcome: str
    detail: str
    growth: int | None
    store: int | None

    def problems(self, budget: int | None = None) -> list[str]:
        """What the oracle finds wrong: an exception or a death in the trusted process, memory over the bound,
        a store over the budget."""
        found = []
        if self.outcome not in ("accepted", "refused"):
            found.append(f"{self.outcome} in the trusted process: {self.detail.splitlines()[0][:300]}")
        bound = GROWTH_FACTOR * self.sent + GROWTH_SLACK[self.target]
        if self.growth is not None and self.growth > bound:
            found.append(f"peak RSS +{self.growth / 2**20:,.0f} MB for {self.sent:,} bytes sent (bound "
                         f"{bound / 2**20:,.0f} MB)")
        if self.store is not None and budget is not None and self.store > budget + STORE_SLACK:
            found.append(f"the store grew by {self.store / 2**20:,.1f} MB (honest + budget: "
                         f"{(budget + STORE_SLACK) / 2**20:,.1f} MB)")
        return found


def steps_of(recipe: dict) -> int:
    return recipe.get("steps", 1)


class Server:
    """The trusted side, in a process of its own (see tests/fuzz/server.py)."""

    def __init__(self, tree: str | os.PathLike | None = None):
        tree = Path(tree or os.environ.get("CODEARCADE_FUZZ_TREE") or ROOT)
        self.tmp = tempfile.TemporaryDirectory(prefix="fuzz-client-")
        honest = os.path.join(self.tmp.name, "honest.arrow")
        with open(honest, "wb") as f:
            f.write(recipes.build({"kind": "table", "steps": 2, "rows_per_step": 2, "value_kind": "plain",
                                   "value_size": 0, "lines": 3, "function": "long"}))
        env = dict(os.environ, PYTHONPATH=str(tree), OMP_WAIT_POLICY="PASSIVE")
        self.proc = subprocess.Popen([sys.executable, str(ROOT / "tests/fuzz/server.py")], cwd=tree, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self._send({"policy_text": recipes.POLICY, "honest": honest, "honest_steps": 2})
        ready = self.proc.stdout.readline()
        if not ready:
            raise RuntimeError("the fuzz server did not start")

    def _send(self, obj: dict) -> None:
        self.proc.stdin.write(json.dumps(obj) + "\n")
        self.proc.stdin.flush()

    def judge(self, target: str, recipe: dict) -> Verdict:
        payload = recipes.build(recipe)
        path = os.path.join(self.tmp.name, "input.bin")
        with open(path, "wb") as f:
            f.write(payload)
        self._send({"target": target, "path": path, "steps": steps_of(recipe)})
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the fuzz server died")
        answer = json.loads(line)
        growth = answer["growth_kb"]
        return Verdict(target, recipe, len(payload), answer["outcome"], answer["detail"],
                       None if growth is None else growth * 1024, answer["store_bytes"])

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(30)
        self.tmp.cleanup()
