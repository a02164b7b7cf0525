"""What the reader tests share: OCAtari's object list compared with a fast reader's, call after call.

Each ``tests/test_readers*.py`` plays real games (random actions, lives lost) and perturbs their RAMs, then runs
OCAtari's own reader and the game's reader from ``games/readers/`` on the same RAMs, each on its own object list
carried from call to call as an episode carries it, and counts the calls after which the two lists differ.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from ocatari.ram import extract_ram_info

from games.envs import make_env


def object_state(objects: list) -> list[tuple]:
    """Everything of an object list a later call or the observation reads: class, position, size, colour, previous
    position and visibility, slot by slot."""
    return [(o.__class__.__name__, o._xy, o.wh, None if o.rgb is None else tuple(o.rgb), o._prev_xy, o._visible)
            for o in objects]


def played_rams(seed: int, steps: int, game: str = "breakout") -> list[np.ndarray]:
    """The RAM after each of ``steps`` random actions (the game reset with the same seed when it ends)."""
    env = make_env(game, objects=False)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    rams = []
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        rams.append(env.unwrapped.ale.getRAM().copy())
        if terminated or truncated:
            env.reset(seed=seed)
    env.close()
    return rams


def calls_that_differ(rams: list[np.ndarray], game: str, reader: Callable[[list, np.ndarray], None]) -> int:
    """Calls after which OCAtari's object list (``game``: OCAtari's name) and ``reader``'s differ."""
    theirs = extract_ram_info.init_objects(game, False)
    ours = extract_ram_info.init_objects(game, False)
    differ = 0
    for ram in rams:
        extract_ram_info.detect_objects_ram(theirs, ram.astype(np.int64), game, False)
        reader(ours, ram)
        differ += object_state(theirs) != object_state(ours)
    return differ
