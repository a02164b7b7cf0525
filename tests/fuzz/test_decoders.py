"""Fuzzers with a cost oracle for every decoder of policy data (issue 38, item 4): the node stream's frame decoder,
the parent's node rows, values and store write, the game host's Rerun path, and the host's failure frame.

Hypothesis draws recipes (tests/fuzz/recipes.py) of structurally valid and invalid inputs: honest-shaped node
tables with hostile values (long, astral, one emoji among ASCII, ``[{},{},…]``, huge numbers, deep, escapes),
``lines_run`` of thousands of lines a call, schemas whose metadata or fields share flatbuffer offsets, wide
schemas, every Arrow type in place of a column, compression, many batches, flipped bytes, and failure frames.
Each input is decoded in a forked child of a server process (tests/fuzz/server.py) whose peak RSS is measured;
the oracle (tests/fuzz/oracle.py) asks for an accepted episode or a recorded policy error, never an exception,
peak RSS within the budget's bound of the bytes sent, and a store no larger than an honest episode plus the
budget.

The suite's run is derandomized and short (:data:`EXAMPLES` examples a target, a few seconds each) and replays
every attack found so far (tests/fuzz/corpus.json). A longer run is one command (docs/sandbox.md):

    CODEARCADE_FUZZ_EXAMPLES=2000 .venv/bin/python -m pytest -n 0 tests/fuzz
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings

from pipeline.boundary.nodes import node_budget
from tests.fuzz import recipes
from tests.fuzz.oracle import Server, steps_of

# every example is decoded in a forked child whose peak memory is read: seconds a target, not the quick lane's
pytestmark = pytest.mark.slow

EXAMPLES = int(os.environ.get("CODEARCADE_FUZZ_EXAMPLES", "25"))
CORPUS = json.loads((Path(__file__).parent / "corpus.json").read_text())
"""Every attack the fuzzers found (target, recipe, what it did before the fix)."""
STRATEGIES = {"frame": recipes.arrow_recipes(), "nodes": recipes.arrow_recipes(), "rerun": recipes.arrow_recipes(),
              "failure": recipes.failure_recipes()}


def budget_of(recipe: dict) -> int:
    """The store bytes an episode of the recipe's steps may add beyond an honest one."""
    return node_budget(steps_of(recipe))


@pytest.fixture(scope="module")
def server():
    server = Server()
    yield server
    server.close()


def _check(server: Server, target: str, recipe: dict) -> None:
    verdict = server.judge(target, recipe)
    problems = verdict.problems(budget_of(recipe))
    assert not problems, f"{target} {json.dumps(recipe)}: {'; '.join(problems)}"


FUZZ = settings(max_examples=EXAMPLES, derandomize=True, deadline=None, database=None,
                suppress_health_check=list(HealthCheck))


@pytest.mark.parametrize("target", sorted(STRATEGIES))
def test_fuzz(server, target):
    @FUZZ
    @given(STRATEGIES[target])
    def run(recipe):
        _check(server, target, recipe)

    run()


@pytest.mark.parametrize("case", CORPUS, ids=[f"{c['target']}-{c['name']}" for c in CORPUS])
def test_corpus(server, case):
    _check(server, case["target"], case["recipe"])
