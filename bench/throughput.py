"""Throughput of evaluation against the bare OCAtari environment, per game, measured in the same run.

For each game it plays the example starter policy with ``evaluate`` (one worker process, every step written
to a real DuckDB store), then again with ``--trace`` (a node per bundled call), and replays the very same
action sequences in OCAtari's own env class with its lean settings (the baseline: no policy, no logging).
It prints steps/s for each and the ratios to the baseline; targets: eval >= 0.85, eval --trace >= 0.60.

    .venv/bin/python bench/throughput.py [--games pong breakout] [--episodes 3] [--repeats 3]

OCAtari's class computes wrong Space Invaders objects under numpy 2 and then overflows; the baseline gets the
same int64-RAM fix codearcade uses, so both sides do the same extraction work.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.evaluate import EvalConfig, evaluate  # noqa: E402
from pipeline.games import GAMES, get_game  # noqa: E402
from store import Store  # noqa: E402

TARGETS = {"eval": 0.85, "eval --trace": 0.60}


def bare_ocatari(game: str, action_sequences: list[list[int]], seeds: list[int]) -> float:
    """Seconds to build OCAtari's env once, then reset and step it through the given action sequences
    (one env for all episodes, as codearcade's workers reuse theirs)."""
    from ocatari.core import OCAtari
    from ocatari.ram.extract_ram_info import detect_objects_ram

    spec = get_game(game)
    start = time.perf_counter()
    env = OCAtari(spec.env_id, mode="ram", hud=False, obs_mode="ori", create_buffer_stacks=[],
                  frameskip=4, repeat_action_probability=0.0)
    ale = env._env.unwrapped.ale
    env.detect_objects = lambda: detect_objects_ram(env.objects, ale.getRAM().astype(np.int64), env.game_name,
                                                    env.hud)
    for actions, seed in zip(action_sequences, seeds):
        env.reset(seed=seed)
        if spec.fire_on_life_loss:
            env.step(1)
        lives = env._env.unwrapped.ale.lives()
        for action in actions:
            _, _, _, _, info = env.step(action)
            if spec.fire_on_life_loss and info["lives"] < lives:
                env.step(1)
            lives = info["lives"]
    env.close()
    return time.perf_counter() - start


def timed_eval(policy: Path, store: Store, episodes: int, trace: bool) -> tuple[float, str]:
    config = EvalConfig(episodes=episodes, trace=trace, workers=1, max_steps=4000)
    start = time.perf_counter()
    result = evaluate(policy, config, store)
    return time.perf_counter() - start, result.run_id


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--games", nargs="+", default=list(GAMES), choices=list(GAMES))
    parser.add_argument("--episodes", type=int, default=3, help="episodes per measurement (default: 3)")
    parser.add_argument("--repeats", type=int, default=5, help="measurements per configuration (median taken)")
    args = parser.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="codearcade-bench-"))
    store = Store(tmp / "bench.duckdb")
    evaluate(ROOT / "examples" / "pong.py", EvalConfig(episodes=1, max_steps=50), store)  # start the forkserver

    print(f"{'game':<15} {'steps':>6} {'bare OCAtari':>13} {'eval':>13} {'eval --trace':>13} "
          f"{'eval/bare':>10} {'trace/bare':>11}")
    failures = []
    for game in args.games:
        policy = ROOT / "examples" / f"{game}.py"
        bare, plain, traced = [], [], []
        steps = 0
        for _ in range(args.repeats):
            t_eval, run_id = timed_eval(policy, store, args.episodes, trace=False)
            t_trace, _ = timed_eval(policy, store, args.episodes, trace=True)
            rows = store.query(
                "SELECT e.seed, list(s.action ORDER BY s.step) FROM episodes e JOIN steps s USING (episode_id) "
                "WHERE e.run_id = ? AND s.action IS NOT NULL GROUP BY e.episode_id, e.seed ORDER BY e.seed",
                [run_id],
            )
            seeds = [r[0] for r in rows]
            actions = [r[1] for r in rows]
            steps = sum(len(a) for a in actions)
            t_bare = bare_ocatari(game, actions, seeds)
            bare.append(steps / t_bare)
            plain.append(steps / t_eval)
            traced.append(steps / t_trace)
        b, p, t = (statistics.median(x) for x in (bare, plain, traced))
        # the ratio of each repeat's own pair, then the median: robust to the machine's speed drifting
        plain_ratio = statistics.median(x / y for x, y in zip(plain, bare))
        traced_ratio = statistics.median(x / y for x, y in zip(traced, bare))
        print(f"{game:<15} {steps:>6} {b:>9.0f} st/s {p:>9.0f} st/s {t:>9.0f} st/s "
              f"{plain_ratio:>10.2f} {traced_ratio:>11.2f}")
        for name, ratio in (("eval", plain_ratio), ("eval --trace", traced_ratio)):
            if ratio < TARGETS[name]:
                failures.append(f"{game}: {name} ratio {ratio:.2f} below target {TARGETS[name]}")
    print(f"targets: eval/bare >= 0.85, trace/bare >= 0.60 (median over {args.repeats} repeats of the ratio "
          f"within each repeat; {args.episodes} episodes per measurement)")
    for failure in failures:
        print("BELOW TARGET:", failure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
