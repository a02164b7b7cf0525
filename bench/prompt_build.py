"""Time to build an optimizer prompt from a store holding 1M steps, against reading the same rows into Python.

It records a real iteration 0 of a Pong optimization (a 400-step traced training rollout and an evaluation),
then fills the store with copies of those rows under other episode ids until ``steps`` holds 1M rows (and
``nodes`` about as many as a traced run would), and times, each over several repeats (median):

- read: fetching the training rollout's step and node rows into Python (``fetchall``);
- prompt: ``read_context`` + ``build_prompt`` for the next update, at a 16k and a 4k token budget.

Target: prompt <= 0.2 s.

    .venv/bin/python bench/prompt_build.py [--steps 1000000] [--repeats 5]
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

from pipeline.optimizer.config import OptimizeConfig  # noqa: E402

from pipeline.llm.tokens import TokenCounter  # noqa: E402
from pipeline.optimizer.context import read_context  # noqa: E402
from pipeline.optimizer.loop import load_state, run_loop, start_run  # noqa: E402
from pipeline.optimizer.prompt import build_prompt  # noqa: E402
from store import Store  # noqa: E402

TARGET_S = 0.2


def fill(store: Store, target_steps: int) -> tuple[int, int]:
    """Copy the existing episodes' steps and nodes under new episode ids until ``steps`` has target rows."""
    with store.write() as con:
        existing = con.execute("SELECT count(*) FROM steps").fetchone()[0]
        copies = max(0, (target_steps - existing) // existing)
        con.execute(
            "INSERT INTO steps SELECT s.episode_id || '.copy' || n AS episode_id, s.* EXCLUDE (episode_id) "
            "FROM steps s, range(?) t(n)", [copies])
        con.execute(
            "INSERT INTO nodes SELECT s.episode_id || '.copy' || n AS episode_id, s.* EXCLUDE (episode_id) "
            "FROM nodes s, range(?) t(n)", [copies])
        return con.execute("SELECT count(*) FROM steps").fetchone()[0], con.execute("SELECT count(*) FROM nodes").fetchone()[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=1_000_000, help="rows the steps table is filled to (default: 1M)")
    parser.add_argument("--repeats", type=int, default=5, help="timings per measurement (median taken; default: 5)")
    args = parser.parse_args()

    store = Store(Path(tempfile.mkdtemp(prefix="codearcade-bench-")) / "prompt.duckdb")
    run_id = start_run(OptimizeConfig(game="pong", iterations=0, eval_max_steps=4000), store, "openai/gpt-4o")
    run_loop(store, load_state(store, run_id), None)
    steps, nodes = fill(store, args.steps)
    train_id = store.query("SELECT train_episode_id FROM iterations WHERE run_id = ?", [run_id])[0][0]
    counter = TokenCounter("openai/gpt-4o")
    print(f"store: {steps:,} steps, {nodes:,} nodes ({store.path.stat().st_size / 2**20:.0f} MB); "
          f"prompt tokens counted by {counter.method}")

    def read_rows() -> int:
        with store.read() as con:
            a = con.execute("SELECT * FROM steps WHERE episode_id = ? ORDER BY step", [train_id]).fetchall()
            b = con.execute("SELECT * FROM nodes WHERE episode_id = ? ORDER BY step, call_index", [train_id]).fetchall()
        return len(a) + len(b)

    def prompt(budget: int) -> int:
        with store.read() as con:
            ctx = read_context(con, run_id, 1, memory=5)
        return build_prompt(ctx, budget, counter).tokens

    timings: dict[str, list[float]] = {}
    for _ in range(args.repeats):
        for name, fn in (("read rows", read_rows), ("prompt 16k", lambda: prompt(16_000)),
                         ("prompt 4k", lambda: prompt(4_000))):
            start = time.perf_counter()
            fn()
            timings.setdefault(name, []).append(time.perf_counter() - start)
    base = statistics.median(timings["read rows"])
    for name, values in timings.items():
        median = statistics.median(values)
        verdict = "" if name == "read rows" else ("  ok" if median <= TARGET_S else f"  ABOVE the {TARGET_S} s target")
        print(f"{name:<11} {median * 1000:8.1f} ms   x{median / base:5.2f} of reading the rows{verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
