"""Cost of logging an evaluation episode to Rerun live, against the episode's own environment time.

For each game it plays one evaluation episode (``run_episode``, in this process) twice, with the same seed: once
plain and once with a live recording to a .rrd file (``EpisodeSpec.rerun``: boxes and series of every step,
a PNG frame every 4th step with the boxes drawn on it logged again on that step and a label naming the step,
the file written and closed). Reported, per game (median of ``--repeats``):

- ``log/env``: seconds spent in the recorder (per-step frame capture, chunked sends, the final flush that waits
  until the file is written) over the seconds inside ``env.step`` of the same episode. Target: <= 0.25.
- ``cpu/env``: extra CPU seconds of the whole process (Rerun's own encoder threads included) over env time.
- the one-time costs a fresh worker process pays on top: importing the SDK and opening the stream.

    .venv/bin/python bench/rerun_logging.py [--games pong breakout space_invaders] [--repeats 3] [--frames-every 4]

Pong plays tests/policies/pong_competent.py (a long game: the 4000-step cap); the others play their examples.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from games import GAMES  # noqa: E402
from pipeline.play.rollout import run_episode  # noqa: E402
from pipeline.play.spec import EpisodeSpec  # noqa: E402

TARGET = 0.25
POLICIES = {"pong": ROOT / "tests" / "policies" / "pong_competent.py"}


def policy_path(game: str) -> Path:
    return POLICIES.get(game, ROOT / "games" / "scaffolds" / f"{game}.py")


def measure(spec: EpisodeSpec) -> tuple[dict, float]:
    cpu = time.process_time()
    outcome = run_episode(spec)
    return outcome.episode, time.process_time() - cpu


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--games", nargs="+", default=list(GAMES), choices=list(GAMES),
                        help="games to play (default: all three)")
    parser.add_argument("--repeats", type=int, default=3, help="episodes per configuration (default: 3)")
    parser.add_argument("--max-steps", type=int, default=4000, help="steps per episode at most (default: 4000)")
    parser.add_argument("--frames-every", type=int, default=4,
                        help="log the screen every this many steps, 0 for none (default: 4)")
    args = parser.parse_args()

    t0 = time.perf_counter()
    import viewers.rerun_live as live  # the SDK import: paid once per worker process

    import_s = time.perf_counter() - t0
    worst = 0.0
    with tempfile.TemporaryDirectory() as out:
        print(f"{'game':<15} {'steps':>6} {'env s':>7} {'log s':>7} {'log/env':>8} {'cpu/env':>8} {'frames':>7} "
              f"{'KB/rrd':>7}")
        setups = []
        for game in args.games:
            text = policy_path(game).read_text()
            base = EpisodeSpec(episode_id=f"BENCH.0.eval.{game}", run_id="BENCH", game=game, policy_text=text,
                               policy_version_id="bench", max_steps=args.max_steps, rerun_frames_every=args.frames_every)
            logged = replace(base, rerun=out)
            run_episode(replace(logged, max_steps=50))  # warm-up: first-use costs of the SDK are not per episode
            ratios, cpu_ratios, rows = [], [], []
            for _ in range(args.repeats):
                plain, plain_cpu = measure(base)
                episode, cpu = measure(logged)
                stats = dict(live.last_stats)
                assert episode["length"] == plain["length"] and episode["return"] == plain["return"], \
                    "the recording changed the episode"
                ratios.append(stats["log_s"] / episode["env_s"])
                cpu_ratios.append((cpu - plain_cpu) / plain["env_s"])
                setups.append(stats["setup_s"])
                rows.append((episode, stats))
            episode, stats = rows[len(rows) // 2]
            ratio = statistics.median(ratios)
            worst = max(worst, ratio)
            size = Path(out, f"{logged.episode_id}.rrd").stat().st_size / 1024
            print(f"{game:<15} {episode['length']:>6} {episode['env_s']:>7.2f} {stats['log_s']:>7.3f} {ratio:>8.3f} "
                  f"{statistics.median(cpu_ratios):>8.3f} {int(stats['frames']):>7} {size:>7.0f}")
    print(f"one-time per worker process: SDK import {import_s:.2f} s, stream setup {statistics.median(setups) * 1000:.0f} ms")
    verdict = "OK" if worst <= TARGET else "ABOVE TARGET"
    print(f"worst log/env ratio {worst:.3f} (target <= {TARGET}): {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
