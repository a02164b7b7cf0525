"""games/readers/seaquest.py leaves OCAtari's Seaquest object list exactly as OCAtari's own reader does.

Compared after every call, slot by slot: ``tests/reader_equality.object_state`` and, beyond it, every attribute
of every object (orientation, the oxygen bar's value and previous value, a ``NoObject``'s ``nslen``) and which
slots share one object (OCAtari's six first ``CollectedDiver`` slots do). On the RAMs of played games (random
actions over several seeds, and the competent policy's whole games, which reach the surface patrol) and on
thousands of RAMs whose every byte the reader reads is random (in and out of the game's ranges, at the edges of
OCAtari's tests), one call after another on the same object lists, with the first observation's previous
positions (``games.envs.ObjectObservation``) given to both lists now and then, as an episode's start does.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ocatari.ram import extract_ram_info
from ocatari.ram.game_objects import NoObject

from games import get_game
from games.envs import make_env
from games.readers.seaquest import detect_seaquest
from tests.conftest import POLICIES
from tests.reader_equality import object_state, played_rams, played_through_env
from tracing.policy_file import load_policy

READ = [30, 31, 32, 33, 36, 37, 38, 39, 60, 62, 70, 71, 72, 73, 74, 86, 89, 90, 91, 92, 93, 97, 102, 103, 105, 118]
"""Every RAM byte OCAtari's Seaquest reader reads."""
EDGES = {105: (0, 1, 14, 15), 102: (0, 1, 62, 63, 64, 255), 103: (0, 1, 159, 160), 118: (159, 160),
         60: (0, 1, 2, 3), 62: (0, 1, 5, 6, 7, 255), 86: (0, 8), 71: (0, 1, 159, 160), 74: (0, 1, 159, 160),
         30: (149, 150, 165, 166, 255), 33: (0, 133, 134, 149, 150)}
"""Values at the edges of OCAtari's tests, for some of them (lane x: the third enemy's x wraps past 165)."""


def full_state(objects: list) -> tuple:
    """:func:`object_state` plus every attribute of every slot and which slots share a (present) object."""
    ids: dict[int, int] = {}
    shared = [None if o.__class__ is NoObject else ids.setdefault(id(o), len(ids)) for o in objects]
    return object_state(objects), [sorted(vars(o).items()) for o in objects], shared


def calls_that_differ(rams: list[np.ndarray], first_every: int = 0, hide_every: int = 0) -> int:
    """:func:`tests.reader_equality.calls_that_differ` on :func:`full_state`; every ``first_every`` calls, both lists
    get what ``ObjectObservation``'s first observation does to them (every slot's previous position its own); every
    ``hide_every`` calls, the object in one slot (in turn) is made invisible in both, which no reader does but
    OCAtari's ``bool(obj)`` tests read."""
    theirs = extract_ram_info.init_objects("Seaquest", False)
    ours = extract_ram_info.init_objects("Seaquest", False)
    differ = 0
    for call, ram in enumerate(rams):
        extract_ram_info.detect_objects_ram(theirs, ram.astype(np.int64), "Seaquest", False)
        detect_seaquest(ours, ram)
        if first_every and call % first_every == 0:
            for o in theirs + ours:
                o._prev_xy = o._xy
        if hide_every and call % hide_every == 0:
            slot = call // hide_every % len(ours)
            if ours[slot].__class__ is not NoObject:
                theirs[slot]._visible = ours[slot]._visible = False
        differ += full_state(theirs) != full_state(ours)
    return differ


def competent_rams(seed: int, sticky: float) -> list[np.ndarray]:
    """The RAM after each step of a whole game of the competent policy (tests/policies/seaquest_competent.py)."""
    policy = load_policy((POLICIES / "seaquest_competent.py").read_text(), "seaquest_competent.py").policy
    env = make_env("seaquest", sticky=sticky)
    obs, _ = env.reset(seed=seed)
    rams = []
    try:
        for _ in range(4000):
            obs, _, terminated, truncated, _ = env.step(policy(obs))
            rams.append(env.unwrapped.ale.getRAM().copy())
            if terminated or truncated:
                break
    finally:
        env.close()
    return rams


def covered(rams: list[np.ndarray]) -> set[str]:
    """What OCAtari's reader made of ``rams``: the classes in its list, and its quirks seen."""
    objects = extract_ram_info.init_objects("Seaquest", False)
    seen = set()
    for ram in rams:
        extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "Seaquest", False)
        seen |= {o.__class__.__name__ for o in objects}
        if objects[0].__class__ is NoObject:
            seen.add("no player")
        if objects[35].__class__ is NoObject:
            seen.add("no oxygen bar")
        submarines = [3 < int(ram[89 + lane]) % 8 < 7 for lane in range(4)]
        for slot in range(1, 13):  # an enemy of the kind its lane no longer has, left where it was
            lane = (slot - 1) // 3
            if (objects[slot + 12] if not submarines[lane] else objects[slot]).__class__ is not NoObject:
                seen.add("stale enemy")
        for i in range(4):  # a diver left in a lane of submarines, or a missile in a lane of sharks
            if (objects[25 + i] if submarines[3 - i] else objects[29 + i]).__class__ is not NoObject:
                seen.add("stale diver or missile")
    return seen


EVERY_KIND = {"Player", "Shark", "Submarine", "Diver", "EnemyMissile", "SurfaceSubmarine", "PlayerMissile",
              "OxygenBar", "CollectedDiver", "NoObject", "no player", "no oxygen bar"}


@pytest.mark.slow
def test_seaquest_objects_equal_ocataris_on_played_games():
    """Random play (three seeds) and the competent policy's whole games (one deterministic, one with sticky actions: it meets submarines, their
    missiles and the surface patrol, which random play does not reach) reach every kind of object the reader
    makes, and lose lives; every call leaves the same list."""
    games = [played_rams(seed, 2500, "seaquest") for seed in range(3)]
    games += [competent_rams(0, 0.0), competent_rams(2, 0.25)]
    seen = set().union(*(covered(rams) for rams in games))
    assert EVERY_KIND <= seen, f"the games never reached {EVERY_KIND - seen}"
    assert [calls_that_differ(rams, first_every=1000) for rams in games] == [0] * len(games)


def test_seaquest_objects_equal_ocataris_on_random_rams():
    """Every byte the reader reads random, some at the edges of OCAtari's tests, one call after another: lanes
    turning from sharks to submarines and back, enemies, divers and missiles (dis)appearing in any order."""
    rng = np.random.default_rng(40)
    played = played_rams(4, 500, "seaquest")
    rams = []
    for i in range(6000):
        ram = played[i % len(played)].copy()
        if i % 4:  # a random few of the bytes, the rest as played (objects that stay across calls)
            chosen = rng.choice(READ, int(rng.integers(1, len(READ))), replace=False)
        else:
            chosen = READ
        for index in chosen:
            edges = EDGES.get(int(index))
            if edges is not None and rng.random() < 0.5:
                ram[index] = edges[int(rng.integers(len(edges)))]
            else:
                ram[index] = rng.integers(0, 256)
        rams.append(ram)
        if i % 9 == 0:
            rams.append(ram.copy())  # the same RAM twice: what stays put must stay put
    assert covered(rams) >= EVERY_KIND | {"stale enemy", "stale diver or missile"}
    assert calls_that_differ(rams, first_every=97, hide_every=5) == 0



@pytest.mark.slow
def test_seaquest_observations_equal_ocataris_through_the_environment():
    """The environment with the reader against the same environment with OCAtari's, the competent policy playing,
    two games each played to its end or 1,500 steps (each reset's first observation gives every slot a previous
    position, the NoObject OCAtari's list shares between 34 slots included): the same observations and object
    lists at every step."""
    game = get_game("seaquest")
    policy = load_policy((POLICIES / "seaquest_competent.py").read_text(), "seaquest_competent.py").policy
    ours, theirs = (played_through_env(spec, seeds=(3, 4), max_steps=1500, sticky=0.25, state=full_state,
                                       choose=policy) for spec in (game, dataclasses.replace(game, detect=None)))
    assert len(theirs) > 1000 and ours == theirs

