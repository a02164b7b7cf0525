"""Bytes a step costs in the store file: untraced and traced evaluation, per game, and where they go.

For each game the starter policy (``games/scaffolds/``) plays ``evaluate`` (``codearcade eval``, every default on:
the episode writer's grouped transactions, each attaching, committing and checkpointing the file) into a fresh
store, untraced, then with ``--trace`` (a node per bundled call) into another; each twice, with codearcade's
row-group and block sizes (``store/hub.py``) and with those of before issue 40 (2,048-row groups, DuckDB's 256 KiB
blocks): the baseline, measured in the same run. Each store is made empty here (schema and migrations), then gets a
first evaluation of ``--warmup`` episodes (every table it writes then has its first blocks: a DuckDB file grows
by whole blocks, and each table claims blocks of its own), then the measured one of ``--episodes`` episodes.

The headline is the **growth of the file over the measured evaluation's steps** (bytes per step), against the
targets of issue 40 (untraced <= 50, traced <= 120) and the baseline; beside it, the growth over all steps from
the empty store (what a small store pays, its first blocks included), the growth of the used blocks (the file
less its free blocks, which later writes reuse: a checkpoint frees the blocks of the row group it rewrites)
and the empty store's size. Then where the bytes go: each column of ``steps`` and ``nodes`` as DuckDB placed
its segments in the file, and the rest of the growth (metadata, the unfilled ends of blocks, the other tables).

    .venv/bin/python bench/store_bytes.py [--games pong breakout space_invaders] [--episodes 24] [--warmup 2]

The steps stored are the same on every run (a pinned random stream, the paper's deterministic protocol). The
bytes depend a little on speed: how many episodes each grouped write holds depends on how fast they play (one
write a second at most, ``store.writer.EpisodeWriter``), and each write leaves its own partly filled blocks; two
runs of the same code moved by up to 30% (docs/benchmarks.md). A measurement that could not be made (no steps stored) makes the run
exit 1; a target missed is printed (``ABOVE TARGET``), not failed.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import store.hub as hub  # noqa: E402
from games import GAMES  # noqa: E402
from pipeline.play.evaluate import EvalConfig, evaluate  # noqa: E402
from store import Store  # noqa: E402

TARGETS = {"untraced": 50.0, "traced": 120.0}
"""Bytes per step of issue 40, item 4."""
SETTINGS = {"codearcade": (hub.WRITE_ROW_GROUP_SIZE, hub.NEW_STORE_BLOCK_SIZE),
            "before (2,048-row groups, 256 KiB blocks)": (2048, 262144)}
"""Row-group and block size of each store written: codearcade's (``store/hub.py``) and those of before issue 40
(DuckDB's default block size), the baseline measured in the same run."""


def step_count(store: Store) -> int:
    return int(store.query("SELECT count(*) FROM steps")[0][0])


def used_bytes(store: Store) -> int:
    """Bytes of the file's used blocks: its size less the free blocks a later write reuses (a checkpoint frees
    the blocks of the row group it rewrites)."""
    size, used = store.query("SELECT block_size, used_blocks FROM pragma_database_size() "
                             "WHERE database_name = current_database()")[0]
    return int(size) * int(used)


def play(store: Store, game: str, episodes: int, trace: bool, max_steps: int, seed: int) -> None:
    policy = ROOT / "games" / "scaffolds" / f"{game}.py"
    # a pinned random stream: the starters move at random at times, and each run must store the same steps
    config = EvalConfig(episodes=episodes, trace=trace, max_steps=max_steps, seed=seed, rng_key="store-bytes")
    evaluate(policy, config, store)


def segment_bytes(path: Path, tables: tuple[str, ...]) -> dict[str, dict[str, float]]:
    """Estimated bytes of each column of ``tables`` in the file at ``path``, from where DuckDB placed its segments:
    a segment runs to the next one in its block; the last of a block, whose end DuckDB does not say, fills it when
    it is alone there (a segment too big to share a block) and else counts as the median segment of its column.
    What the file holds beyond these is metadata, free blocks and the unfilled ends of blocks."""
    import duckdb

    con = duckdb.connect(str(path), read_only=True)
    try:
        block_size = con.execute("SELECT block_size FROM pragma_database_size()").fetchone()[0]
        segments = []
        for table in tables:
            segments += [(table, *row) for row in con.execute(
                "SELECT column_name, block_id, block_offset, len(additional_block_ids) "
                "FROM pragma_storage_info(?) WHERE persistent AND block_id >= 0", [table]).fetchall()]
    finally:
        con.close()
    by_block: dict[int, list] = {}
    for segment in segments:
        by_block.setdefault(segment[2], []).append(segment)
    known: dict[tuple[str, str], list[int]] = {}
    last = []
    for block in by_block.values():
        block.sort(key=lambda seg: seg[3])
        for this, after in itertools.pairwise(block):
            known.setdefault(this[:2], []).append(after[3] - this[3] + this[4] * block_size)
        last.append(block[-1])
    sizes: dict[str, dict[str, float]] = {table: {} for table in tables}
    for (table, column), values in known.items():
        sizes[table][column] = sizes[table].get(column, 0) + sum(values)
    for table, column, block, offset, extra in last:
        values = known.get((table, column))
        alone = len(by_block[block]) == 1
        guess = statistics.median(values) if values and not alone else block_size - offset
        sizes[table][column] = sizes[table].get(column, 0) + guess + extra * block_size
    return sizes


def measure(game: str, trace: bool, args: argparse.Namespace, scratch: Path, setting: str) -> dict:
    """One store, made empty, warmed up, then the measured evaluation, under ``setting`` (a key of SETTINGS)."""
    hub.WRITE_ROW_GROUP_SIZE, hub.NEW_STORE_BLOCK_SIZE = SETTINGS[setting]  # read at every writable attach
    path = scratch / f"{game}-{'traced' if trace else 'untraced'}-{setting.split()[0]}.duckdb"
    store = Store(path)
    with store.write():  # the empty store: schema and migrations
        pass
    empty = os.path.getsize(path)
    play(store, game, args.warmup, trace, args.max_steps, seed=1000)
    warm, warm_used, warm_steps = os.path.getsize(path), used_bytes(store), step_count(store)
    play(store, game, args.episodes, trace, args.max_steps, seed=0)
    size, used, steps = os.path.getsize(path), used_bytes(store), step_count(store)
    nodes = int(store.query("SELECT count(*) FROM nodes")[0][0])
    measured = steps - warm_steps
    return {"game": game, "mode": "traced" if trace else "untraced", "setting": setting, "steps": measured,
            "all_steps": steps, "nodes": nodes, "empty": empty, "growth": size - empty,
            "per_step": (size - warm) / measured if measured else None,
            "used_per_step": (used - warm_used) / measured if measured else None,
            "from_empty": (size - empty) / steps if steps else None,
            "columns": segment_bytes(path, ("steps", "nodes") if trace else ("steps",))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--games", nargs="+", default=["pong", "breakout", "space_invaders"], choices=sorted(GAMES),
                        help="curated games (default: pong breakout space_invaders)")
    parser.add_argument("--episodes", type=int, default=24, help="episodes of the measured evaluation (default: 24)")
    parser.add_argument("--warmup", type=int, default=2, help="episodes played first, not counted (default: 2)")
    parser.add_argument("--max-steps", type=int, default=4000, help="step cap of an episode (default: 4000)")
    args = parser.parse_args()

    ours, before = list(SETTINGS)
    results: dict[tuple[str, str], dict[str, dict]] = {}
    with tempfile.TemporaryDirectory(prefix="codearcade-store-bytes-") as tmp:
        for game in args.games:
            for trace in (False, True):
                for setting in SETTINGS:  # alternating, so that both see the machine alike
                    r = measure(game, trace, args, Path(tmp), setting)
                    results.setdefault((game, r["mode"]), {})[setting] = r
    hub.WRITE_ROW_GROUP_SIZE, hub.NEW_STORE_BLOCK_SIZE = SETTINGS[ours]

    print(f"bytes of store file per step: codearcade ({SETTINGS[ours][0]:,}-row groups, "
          f"{SETTINGS[ours][1] // 1024} KiB blocks) against {before}")
    print(f"{'game':<15} {'mode':<9} {'steps':>7} {'nodes/step':>10} {'bytes/step':>10} {'before':>7} "
          f"{'after/before':>12} {'target':>6} {'/target':>7} {'used':>6} {'before':>7} {'from empty':>10} {'before':>7} "
          f"{'empty store':>12}")
    absent = []
    for (game, mode), pair in results.items():
        r, b = pair[ours], pair[before]
        label = f"{game:<15} {mode:<9}"
        if r["per_step"] is None or b["per_step"] is None:
            absent.append(f"{game} {mode}")
            print(f"{label} no steps stored")
            continue
        target = TARGETS[mode]
        print(f"{label} {r['steps']:>7,} {r['nodes'] / r['all_steps']:>10.2f} {r['per_step']:>10.1f} "
              f"{b['per_step']:>7.1f} {r['per_step'] / b['per_step']:>12.2f} {target:>6.0f} "
              f"{r['per_step'] / target:>7.2f} {r['used_per_step']:>6.1f} {b['used_per_step']:>7.1f} "
              f"{r['from_empty']:>10.1f} {b['from_empty']:>7.1f} "
              f"{r['empty'] / 1024:>7.0f} KiB" + ("   ABOVE TARGET" if r["per_step"] > target else ""))
    print(f"targets: untraced <= {TARGETS['untraced']:.0f} bytes a step, traced <= {TARGETS['traced']:.0f} "
          "(/target <= 1 meets it); bytes/step: the file's growth over the measured evaluation's steps; used: the "
          "growth of its used blocks (free blocks left out); from empty: the file's growth over all steps from the "
          "empty store")

    print("\nwhere the bytes go (codearcade's settings; bytes per step, estimated from the segments' places in the "
          "file): the largest columns, and what else the growth holds (metadata, unfilled ends of blocks, the "
          "other tables)")
    for (game, mode), pair in results.items():
        r = pair[ours]
        if not r["all_steps"]:
            continue
        n, counted = r["all_steps"], 0.0
        parts = []
        for table, columns in r["columns"].items():
            total = sum(columns.values())
            counted += total
            top = sorted(columns.items(), key=lambda cb: -cb[1])[:6]
            parts.append(f"{table} {total / n:.1f} (" + ", ".join(f"{c} {b / n:.1f}" for c, b in top) + ")")
        print(f"{game:<15} {mode:<9} " + "; ".join(parts) + f"; rest {(r['growth'] - counted) / n:.1f}")
    if absent:
        print(f"not measured: {', '.join(absent)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
