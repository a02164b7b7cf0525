"""Latency of writing one episode to a growing store: codearcade's row-group size against DuckDB's default.

Plays one Space Invaders episode of the example policy (every step with its ~36 objects), then appends it
again and again, under new episode ids, to two fresh stores through the real write path (``Store.write`` +
``write_episode``: attach, insert, commit, detach with its checkpoint), alternating between them. One store
is written with ``store.hub.WRITE_ROW_GROUP_SIZE`` (codearcade's setting), the other with DuckDB's default
row groups (122,880 rows), the baseline. It prints the median, 95th percentile and worst write of each and
their ratios; then the time of a whole-table and a one-episode query on each, so that the smaller row groups
are seen not to slow reading down.

    .venv/bin/python bench/store_writes.py [--episodes 120]

Every commit checkpoints the table's last, partly filled row group: the bigger the row groups, the more
a write rewrites, and from time to time DuckDB rewrites far more (the spikes of the baseline).
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

import store.hub as hub  # noqa: E402
from pipeline.play.rollout import run_episode  # noqa: E402
from pipeline.play.spec import EpisodeSpec  # noqa: E402
from store import Store  # noqa: E402
from store.writer import write_episode  # noqa: E402

DUCKDB_DEFAULT_ROW_GROUP_SIZE = 122_880


def timed_queries(store: Store, episode_id: str, repeats: int = 5) -> tuple[float, float]:
    """Best seconds of a scan of every step's objects, and of reading one episode's steps."""
    scan, one = [], []
    with store.read() as con:
        for _ in range(repeats):
            start = time.perf_counter()
            con.execute("SELECT count(*), sum(len(objects)) FROM steps").fetchall()
            middle = time.perf_counter()
            con.execute("SELECT * FROM steps WHERE episode_id = ? ORDER BY step", [episode_id]).fetchall()
            scan.append(middle - start)
            one.append(time.perf_counter() - middle)
    return min(scan), min(one)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=120, help="episodes appended to each store (default: 120)")
    args = parser.parse_args()

    policy = (ROOT / "games" / "scaffolds" / "space_invaders.py").read_text()
    outcome = run_episode(EpisodeSpec(episode_id="bench.0.eval.0", run_id="bench", game="space_invaders",
                                      policy_text=policy, policy_version_id="bench", memory_limit_mb=None))
    objects = sum(len(v) for v in outcome.steps.column("objects").to_pylist())
    tmp = Path(tempfile.mkdtemp(prefix="codearcade-bench-"))
    sizes = {"codearcade": hub.WRITE_ROW_GROUP_SIZE, "DuckDB default": DUCKDB_DEFAULT_ROW_GROUP_SIZE}
    stores = {name: Store(tmp / f"{size}.duckdb") for name, size in sizes.items()}
    seconds: dict[str, list[float]] = {name: [] for name in sizes}
    for i in range(args.episodes):
        episode = {**outcome.episode, "episode_id": f"bench.0.eval.{i}"}
        for name, store in stores.items():
            hub.WRITE_ROW_GROUP_SIZE = sizes[name]  # read at every attach, and each write attaches anew
            start = time.perf_counter()
            with store.write() as con:
                write_episode(con, episode, outcome.steps, None)
            seconds[name].append(time.perf_counter() - start)
    hub.WRITE_ROW_GROUP_SIZE = sizes["codearcade"]

    print(f"{args.episodes} writes of a {outcome.steps.num_rows}-step Space Invaders episode ({objects} objects) "
          "to each store")
    print(f"{'row groups':<28} {'median':>9} {'p95':>9} {'worst':>9} {'all steps':>10} {'one episode':>12}")
    stats = {}
    for name, times in seconds.items():
        ordered = sorted(times)
        p95 = ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))]
        scan, one = timed_queries(stores[name], f"bench.0.eval.{args.episodes // 2}")
        stats[name] = (statistics.median(times), p95, max(times), scan, one)
        label = f"{name} ({sizes[name]:,} rows)"
        print(f"{label:<28} " + " ".join(f"{1000 * v:>7.1f}ms" for v in stats[name][:3])
              + f" {1000 * scan:>8.1f}ms {1000 * one:>10.1f}ms")
    ours, base = stats["codearcade"], stats["DuckDB default"]
    print("ratio (codearcade / default): " + ", ".join(
        f"{label} {o / b:.2f}" for label, o, b in zip(("median", "p95", "worst", "all steps", "one episode"),
                                                        ours, base)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
