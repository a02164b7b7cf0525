"""Where the microseconds of an ``eval`` step go: the game host, the policy process and the parent, per stage.

The host is this very process (the same code a forked game host runs: ``pipeline/play/rollout.py``'s
``prepare_episode`` and ``play_episode`` with a :class:`~pipeline.play.channels.RemotePolicy`), its policy process a
real confined one from the policy zygote, the pair pinned to one CPU as ``eval`` pins them. Each stage's functions
are wrapped with a timer for the run (a wrapper costs ~0.3 µs a call; the untimed total is printed beside):

- **emulator**: ALE's environment step (``AtariEnv.step``: four frames and the RAM read);
- **object extraction**: OCAtari's RAM extractor (``detect_objects_ram``, or the game's own ``detect``);
- **observation build**: the objects turned into the observation dict (``objects_to_dict``, ``derive``);
- **env wrappers**: the rest of ``env.step`` (Gymnasium's wrappers, AutoFire, the int64 copy of the RAM);
- **frame**: the observation marshalled;
- **round trip**: the frame sent and the answer awaited. The pair shares one CPU, so the policy process mostly
  runs inside the host's ``send`` (the wake-up switches to it at once): send and wait are one stage. The policy
  process's own part of it (decoding the observation, the call, node capture, encoding the action) is measured
  below, replayed in this process on the observations of the run; the rest is the boundary itself (two
  wake-ups and context switches, the pipes' system calls);
- **action**: the answer checked;
- **step record**: ``StepLog.observe`` / ``outcome`` and, at the end, the Arrow table, per step;
- **loop**: the rest of the host's loop (timers, lives, the time limit);
- **parent**: the step (and node) rows decoded and checked (``wire.parse_arrow``, ``episode_from_worker``: the
  node rows read within bounds) and written to a real DuckDB store (``store.writer.write_episode``), per step.

Beside them, bare OCAtari's stepping alone (``bench/throughput.py``'s baseline: the same actions, its resets left
out), measured interleaved with the host's runs.

Then the fixed costs of a four-game command, ``codearcade eval POLICY --episodes 4`` (:func:`start_up`): Python,
the imports, a new store, the two zygotes, the ROM load and four one-step episodes, each in a fresh process.

    .venv/bin/python bench/step_profile.py [--games pong breakout space_invaders] [--repeats 3] [--max-steps 2000]
                                           [--skip-start-up | --start-up]
"""

from __future__ import annotations

import argparse
import marshal as _marshal
import os
import socket
import sys
import tempfile
import time
import types
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Iterator

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.throughput import BareOCAtari  # noqa: E402
from games import get_game  # noqa: E402
from games import envs  # noqa: E402
from pipeline.boundary import wire  # noqa: E402
from pipeline.boundary.policy import ACTION, Channel, coerce_action  # noqa: E402
from pipeline.boundary.zygotes import zygote  # noqa: E402
from pipeline.play import channels  # noqa: E402
from pipeline.play.episodes import episode_from_worker, episode_to_json  # noqa: E402
from pipeline.play.channels import RemotePolicy  # noqa: E402
from pipeline.play.rollout import play_episode, prepare_episode  # noqa: E402
from pipeline.play.spec import EpisodeSpec  # noqa: E402
from store import Store  # noqa: E402
from store.writer import write_episode  # noqa: E402
from tracing.capture import NodeRecorder  # noqa: E402
from tracing.policy_file import load_policy  # noqa: E402
from tracing.sandbox import EpisodeTimer  # noqa: E402
from tracing.steps import STEP_SCHEMA, StepLog  # noqa: E402

HOST_STAGES = ("emulator", "object extraction", "observation build", "env wrappers", "frame", "round trip",
               "action", "step record", "loop")
POLICY_STAGES = ("decode observation", "policy", "node capture", "encode action", "boundary (wake-ups, pipes)")
PARENT_STAGES = ("decode + check rows", "store write")
DEFAULT_GAMES = ("pong", "breakout", "space_invaders")


class Timers:
    """Inclusive seconds per stage, gathered by wrapping functions for the length of a ``with`` block."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    def timed(self, stage: str, fn: Callable) -> Callable:
        seconds, clock = self.seconds, time.perf_counter

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            start = clock()
            try:
                return fn(*args, **kwargs)
            finally:
                seconds[stage] += clock() - start

        return wrapper

    @contextmanager
    def patched(self, patches: list[tuple[Any, str, str]]) -> Iterator[None]:
        """``(owner, attribute, stage)``: time ``owner.attribute`` as ``stage`` inside the block."""
        saved = [(owner, name, owner.__dict__.get(name, _MISSING)) for owner, name, _ in patches]
        for owner, name, stage in patches:
            setattr(owner, name, self.timed(stage, getattr(owner, name)))
        try:
            yield
        finally:
            for owner, name, value in reversed(saved):
                if value is _MISSING:
                    delattr(owner, name)
                else:
                    setattr(owner, name, value)


_MISSING = object()


def _spec(game: str, trace: bool, max_steps: int, n: int) -> EpisodeSpec:
    policy_text = get_game(game).scaffold.read_text()
    return EpisodeSpec(episode_id=f"profile-{game}-{trace}-{n}", run_id="profile", game=game,
                       policy_text=policy_text, policy_version_id="profile", seed=0, max_steps=max_steps,
                       trace=trace, rng_key="profile")


def host_episode(game: str, trace: bool, max_steps: int, n: int, cpu: int, timers: Timers | None
                 ) -> tuple[Any, float, list[bytes]]:
    """One episode with this process as its game host (timed by ``timers``, or not at all); the outcome, the
    seconds of its play (the preparation left out) and the observations it sent, marshalled."""
    spec = _spec(game, trace, max_steps, n)
    host_end, policy_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    zygote("policy").attach("policy", policy_end, dict(memory_mb=spec.memory_limit_mb))
    policy = RemotePolicy(host_end, spec, get_game(game).n_actions)
    prepared = prepare_episode(spec, policy)
    sent: list[bytes] = []
    if timers is None:
        start = time.perf_counter()
        outcome = play_episode(prepared, cpu=cpu)
        played = time.perf_counter() - start
        policy.close()
        return outcome, played, sent
    env = prepared.env
    inner = env.unwrapped
    observer = env
    while not isinstance(observer, envs.ObjectObservation):
        observer = observer.env
    game_spec = observer.game
    if game_spec.detect is not None or game_spec.derive is not None:
        observer.game = replace(game_spec, **{name: timers.timed(stage, getattr(game_spec, name))
                                              for name, stage in (("detect", "object extraction"),
                                                                  ("derive", "observation build"))
                                              if getattr(game_spec, name) is not None})

    def dumps(obs: Any) -> bytes:
        data = _marshal.dumps(obs)
        sent.append(data)
        return data

    marshal_shim = types.SimpleNamespace(dumps=timers.timed("frame", dumps))
    patches = [(inner, "step", "emulator"), (envs.extract_ram_info, "detect_objects_ram", "object extraction"),
               (envs, "objects_to_dict", "observation build"), (env, "step", "env.step"),
               (Channel, "send", "round trip"), (RemotePolicy, "_receive", "round trip"), (RemotePolicy, "act", "act"),
               (StepLog, "observe", "step record"), (StepLog, "outcome", "step record"),
               (StepLog, "table", "step record"), (RemotePolicy, "finish", "finish")]
    finish = RemotePolicy.finish

    def untimed_finish(self: RemotePolicy, *args: Any, **kwargs: Any) -> Any:
        # the end's waits (the node rows) are the episode's end, not a step's policy call
        waited = timers.seconds["round trip"]
        try:
            return finish(self, *args, **kwargs)
        finally:
            timers.seconds["round trip"] = waited

    RemotePolicy.finish = untimed_finish
    saved_marshal = channels.marshal
    channels.marshal = marshal_shim
    try:
        with timers.patched(patches):
            start = time.perf_counter()
            outcome = play_episode(prepared, cpu=cpu)
            played = time.perf_counter() - start
    finally:
        channels.marshal = saved_marshal
        RemotePolicy.finish = finish
        observer.game = game_spec
        policy.close()
    return outcome, played, sent


def host_stages(timers: Timers, played: float, steps: int) -> dict[str, float]:
    """Exclusive µs per step of each host stage."""
    s = {k: v / steps * 1e6 for k, v in timers.seconds.items()}
    out = {
        "emulator": s.get("emulator", 0.0),
        "object extraction": s.get("object extraction", 0.0),
        "observation build": s.get("observation build", 0.0),
        "frame": s.get("frame", 0.0),
        "round trip": s.get("round trip", 0.0),
        "step record": s.get("step record", 0.0),
    }
    out["env wrappers"] = s.get("env.step", 0.0) - out["emulator"] - out["object extraction"] - \
        out["observation build"]
    out["action"] = s.get("act", 0.0) - out["frame"] - out["round trip"]
    out["loop"] = played / steps * 1e6 - s.get("env.step", 0.0) - s.get("act", 0.0) - out["step record"] - \
        s.get("finish", 0.0)
    return out


def policy_side(game: str, trace: bool, observations: list[bytes]) -> dict[str, float]:
    """µs per step of the policy process's own work, replayed here on the observations the host sent: what a
    ``PolicySide`` does between receiving a frame and sending the answer (the pipes left out)."""
    spec = _spec(game, trace, len(observations), 0)
    n_actions = get_game(game).n_actions
    clock = time.perf_counter
    out: dict[str, float] = {}
    loaded = load_policy(spec.policy_text, spec.policy_name).policy
    start = clock()
    decoded = [_marshal.loads(data) for data in observations]
    out["decode observation"] = clock() - start
    actions = []
    import random

    import numpy as np
    random.seed(spec.policy_seed)
    np.random.seed(spec.policy_seed % 2**32)
    with EpisodeTimer(spec.call_time_limit_s) as timer:
        start = clock()
        for obs in decoded:
            actions.append(timer.call(loaded, obs))
        out["policy"] = clock() - start
    if trace:
        random.seed(spec.policy_seed)
        np.random.seed(spec.policy_seed % 2**32)
        with EpisodeTimer(spec.call_time_limit_s) as timer, NodeRecorder(lines=spec.trace_lines) as recorder:
            start = clock()
            for step, obs in enumerate(decoded):
                recorder.begin_step(step, obs)
                timer.call(loaded, obs)
            wire.arrow_frame(recorder.table())
            out["node capture"] = clock() - start - out["policy"]
    start = clock()
    for action in actions:
        ACTION.pack(coerce_action(action, n_actions))
    out["encode action"] = clock() - start
    return {k: v / len(observations) * 1e6 for k, v in out.items()}


def parent_side(outcome: Any, spec: EpisodeSpec, store: Store) -> dict[str, float]:
    """µs per step of the parent's work on an episode: its frames decoded and checked, then stored."""
    steps_bytes = wire.arrow_frame(outcome.steps)[wire.HEADER.size:]
    row = episode_to_json(outcome.episode)
    nodes = outcome.nodes
    n = max(outcome.steps.num_rows, 1)
    clock = time.perf_counter
    start = clock()
    steps = wire.parse_arrow(steps_bytes, STEP_SCHEMA, max_rows=spec.max_steps)
    checked = episode_from_worker(spec, row, steps, nodes)
    decoded = clock() - start
    start = clock()
    with store.write() as con:
        write_episode(con, checked.episode, checked.steps, checked.nodes)
    written = clock() - start
    return {"decode + check rows": decoded / n * 1e6, "store write": written / n * 1e6}


def profile(game: str, trace: bool, repeats: int, max_steps: int, store: Store, cpu: int
            ) -> tuple[dict[str, float], dict[str, float], dict[str, float], float, float, int]:
    """Per-stage µs per step (host, policy process, parent; each stage's best over the repeats), the untimed
    host's µs per step, bare OCAtari's stepping µs per step, and the steps."""
    host: dict[str, list[float]] = defaultdict(list)
    side: dict[str, list[float]] = defaultdict(list)
    parent: dict[str, list[float]] = defaultdict(list)
    untimed, bare_us = [], []
    bare = BareOCAtari(game)
    steps = 0
    warm, _, _ = host_episode(game, trace, 50, -1, cpu, None)  # the zygote, the environment, the store's first write
    warm_spec = _spec(game, trace, 50, -1)
    warm_spec.episode_id = warm.episode["episode_id"] = f"warm-{time.time_ns()}"
    parent_side(warm, warm_spec, store)
    for r in range(repeats):
        outcome, played, _ = host_episode(game, trace, max_steps, 2 * r, cpu, None)
        steps = outcome.steps.num_rows
        untimed.append(played / steps * 1e6)
        actions = [a for a in outcome.steps.column("action").to_pylist() if a is not None]
        seconds = bare.play([actions], [0])
        bare_us.append((seconds - bare.reset_s) / len(actions) * 1e6)
        timers = Timers()
        outcome, played, sent = host_episode(game, trace, max_steps, 2 * r + 1, cpu, timers)
        for k, v in host_stages(timers, played, outcome.steps.num_rows).items():
            host[k].append(v)
        for k, v in policy_side(game, trace, sent).items():
            side[k].append(v)
        spec = _spec(game, trace, max_steps, 2 * r + 1)
        spec.episode_id = f"{spec.episode_id}-{time.time_ns()}"
        outcome.episode["episode_id"] = spec.episode_id
        for k, v in parent_side(outcome, spec, store).items():
            parent[k].append(v)
    best = {k: min(v) for k, v in host.items()}
    own = {k: min(v) for k, v in side.items()}
    own.setdefault("node capture", 0.0)
    own["boundary (wake-ups, pipes)"] = best["round trip"] - sum(own.values())
    return best, own, {k: min(v) for k, v in parent.items()}, min(untimed), min(bare_us), steps


START_UP_SCRIPT = r"""
import json, sys, time
began = time.perf_counter()
sys.path.insert(0, {root!r})
import pipeline.cli  # the command line's imports (a verb imports its handler's modules when it runs)
from pipeline.play.evaluate import EvalConfig, evaluate
from store import Store
out = {{"imports": time.perf_counter() - began}}
t = time.perf_counter()
store = Store({store!r})
with store.write():  # a new store: its schema and migrations
    pass
out["store"] = time.perf_counter() - t
from pipeline.boundary.zygotes import zygote
t = time.perf_counter()
zygote("game")
out["game zygote"] = time.perf_counter() - t
t = time.perf_counter()
zygote("policy")
out["policy zygote"] = time.perf_counter() - t
t = time.perf_counter()
from games.envs import make_env  # what the game zygote imports when it prepares the environments
out["emulator imports"] = time.perf_counter() - t
t = time.perf_counter()
make_env({game!r}).close()  # what the game zygote's prepare does once for the command (the ROM load)
out["ROM load"] = time.perf_counter() - t
t = time.perf_counter()
evaluate({policy!r}, EvalConfig(episodes={episodes}, max_steps=1), store)
out["4 episodes of 1 step"] = time.perf_counter() - t
print(json.dumps(out))
"""
START_UP_STAGES = ("python", "imports", "store", "game zygote", "policy zygote", "emulator imports", "ROM load",
                   "4 episodes of 1 step")
"""The rows of the start-up table; ``emulator imports`` and ``ROM load`` are marked: see :func:`print_start_up`."""


def start_up(game: str, repeats: int, tmp: Path) -> dict[str, float]:
    """Seconds of each fixed cost of a four-game ``codearcade eval`` of ``game``, in a fresh process each time
    (best of ``repeats``): Python itself, the command's imports, a new store, the two zygotes, the emulator's
    imports and the ROM load (the game zygote's, when it prepares the environments: timed here in this process),
    and then four episodes of one step each (run rows, four host and policy process pairs forked and confined, the policy
    loaded, each reset, the store writes)."""
    import json
    import subprocess

    best: dict[str, float] = {}
    policy = str(ROOT / "tests" / "policies" / f"{game}_competent.py")
    for i in range(repeats):
        script = START_UP_SCRIPT.format(root=str(ROOT), store=str(tmp / f"start_up_{i}.duckdb"), game=game,
                                        policy=policy, episodes=4)
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True, cwd=tmp)
        whole = time.perf_counter() - start
        seconds = json.loads(done.stdout.strip().splitlines()[-1])
        seconds["python"] = whole - sum(seconds.values())  # the interpreter's own start and end
        for stage, value in seconds.items():
            best[stage] = min(best.get(stage, value), value)
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--games", nargs="+", default=list(DEFAULT_GAMES))
    parser.add_argument("--repeats", type=int, default=3, help="episodes per configuration (best taken per stage)")
    parser.add_argument("--max-steps", type=int, default=2000, help="step cap of each episode (default: 2000)")
    parser.add_argument("--start-up", action="store_true", help="only the fixed costs of a four-game command")
    parser.add_argument("--skip-start-up", action="store_true", help="only the profile of a step")
    args = parser.parse_args()
    if args.start_up:
        return print_start_up(args.games, args.repeats)
    cpu = sorted(os.sched_getaffinity(0))[0]
    os.sched_setaffinity(0, {cpu})  # the host's CPU, which its policy process joins (``go``), as in ``eval``
    tmp = Path(tempfile.mkdtemp(prefix="codearcade-profile-"))
    store = Store(tmp / "profile.duckdb")
    columns, results = [], {}
    for game in args.games:
        get_game(game)
        for trace in (False, True):
            label = f"{game}{' --trace' if trace else ''}"
            columns.append(label)
            results[label] = profile(game, trace, args.repeats, args.max_steps, store, cpu)
    print(f"µs per step, best of {args.repeats} episodes of up to {args.max_steps} steps (seed 0, the starter "
          f"policies), host and policy process pinned to CPU {cpu}\n")
    print("| stage | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))

    def row(name: str, values: list[float], fmt: str = "{:.1f}") -> None:
        print(f"| {name} | " + " | ".join(fmt.format(v) for v in values) + " |")

    print("| **host** | " + " | " * len(columns))
    for stage in HOST_STAGES:
        row(stage, [results[c][0][stage] for c in columns])
    row("host total (timed)", [sum(results[c][0].values()) for c in columns])
    row("host total (untimed)", [results[c][3] for c in columns])
    print("| **policy process** (inside *round trip*) | " + " | " * len(columns))
    for stage in POLICY_STAGES:
        row(stage, [results[c][1].get(stage, 0.0) for c in columns])
    print("| **parent** | " + " | " * len(columns))
    for stage in PARENT_STAGES:
        row(stage, [results[c][2][stage] for c in columns])
    print("| **reference** | " + " | " * len(columns))
    row("bare OCAtari stepping", [results[c][4] for c in columns])
    row("not the emulator's nor the policy's", [results[c][3] - results[c][0]["emulator"]
                                                - results[c][1]["policy"] for c in columns])
    row("host (untimed) / bare stepping", [results[c][3] / results[c][4] for c in columns], "{:.2f}")
    row("steps", [results[c][5] for c in columns], "{:.0f}")
    print(f"\n(load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)\n")
    return 0 if args.skip_start_up else print_start_up(args.games, args.repeats)


def print_start_up(games: list[str], repeats: int) -> int:
    tmp = Path(tempfile.mkdtemp(prefix="codearcade-start-up-"))
    results = {game: start_up(game, repeats, tmp) for game in games}
    print(f"ms, the fixed costs of `codearcade eval POLICY --episodes 4` (a fresh process, a new store; best of "
          f"{repeats})\n")
    print("| cost | " + " | ".join(games) + " |")
    print("|---|" + "---|" * len(games))
    for stage in START_UP_STAGES:
        mark = "¹" if stage in ("emulator imports", "ROM load") else ""
        print(f"| {stage}{mark} | " + " | ".join(f"{results[g][stage] * 1e3:.0f}" for g in games) + " |")
    # a command's parent never imports the emulator: its game zygote does, inside the first episode's preparation
    apart = ("emulator imports", "ROM load")
    print("| **a command** (all but the rows marked ¹) | " + " | ".join(
        f"{sum(v for k, v in results[g].items() if k not in apart) * 1e3:.0f}" for g in games) + " |")
    print("\n¹ timed apart in this process; a command's game zygote pays them inside its first episode's "
          "preparation (in '4 episodes of 1 step')")
    print(f"\n(load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
