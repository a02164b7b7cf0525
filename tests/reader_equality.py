"""What the reader tests share: OCAtari's object list compared with a fast reader's, call after call.

Each ``tests/test_readers*.py`` plays real games (random actions, lives lost) and perturbs their RAMs, then runs
OCAtari's own reader and the game's reader from ``games/readers/`` on the same RAMs, each on its own object list
carried from call to call as an episode carries it, and counts the calls after which the two lists differ
(:func:`calls_that_differ`); and plays the game's environment with either reader (:func:`played_through_env`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from ocatari.ram import extract_ram_info

from games.base import Game
from games.envs import ObjectObservation, make_env


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


def env_objects(env) -> list:
    """OCAtari's object list the environment keeps (``games.envs.ObjectObservation``)."""
    while not isinstance(env, ObjectObservation):
        env = env.env
    return env._objects


def played_through_env(game: Game, seeds: Sequence[int] = (3, 3), max_steps: int = 1_000_000, sticky: float = 0.0,
                       state: Callable[[list], Any] = object_state,
                       choose: Callable[[dict], int] | None = None) -> list[tuple]:
    """Each step's observation and object-list ``state`` as the environment of ``game`` makes them, over one game
    per seed (each reset's first observation gives every slot a previous position, NoObjects included: what a reader
    that keeps its NoObjects must notice), each to its end or ``max_steps``. The actions are ``choose(observation)``,
    or random from a fixed stream (the same for both sides as long as their observations are). One environment at a
    time: a reader whose state is its module's (OCAtari's Q*bert) would share it between two.

    ``played_through_env(game) == played_through_env(dataclasses.replace(game, detect=None))``: the game's reader
    and OCAtari's give the same observations and object lists at every step."""
    env = make_env(game, sticky=sticky)
    rng = np.random.default_rng(5)
    played = []
    try:
        for seed in seeds:
            observation = env.reset(seed=seed)[0]
            for _ in range(max_steps):
                played.append((observation, state(env_objects(env))))
                action = choose(observation) if choose is not None else int(rng.integers(env.action_space.n))
                observation, _, terminated, truncated, _ = env.step(action)
                if terminated or truncated:
                    break
    finally:
        env.close()
    return played
