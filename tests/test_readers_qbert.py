"""games/readers/qbert.py leaves OCAtari's Q*bert object list, and the state OCAtari keeps in its module's globals,
exactly as OCAtari's own reader does.

Q*bert's lists hold ``None`` in empty slots, which ``tests/reader_equality.object_state`` does not take, and both
readers keep their state in OCAtari's module globals: :func:`calls_that_differ` gives each reader its own copy of
that state (swapped in around each call) and compares lists slot by slot (``None`` or ``object_state``) and the
globals after every call. The sweeps: played games (Coily, the purple ball and Sam come and go, Q*bert falls,
lives are lost), thousands of RAMs whose bytes the reader reads are random or set to the values that start and
move its balls and Sam (a green ball, which random play never reaches, and the disks going), Q*bert put next to
them to catch them, and the environment itself against the same environment with OCAtari's reader.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ocatari.ram import extract_ram_info, qbert

from games import get_game
from games.readers.qbert import detect_qbert
from tests.reader_equality import object_state, played_rams, played_through_env

GLOBALS = ("coil_prev_x", "coil_prev_y", "last_i", "purple_i", "green_i", "last_74", "last_lives", "last_105",
           "last_103")
"""OCAtari's Q*bert reader's state between calls (module globals, reset by ``init_objects``)."""
CUBES = list(qbert._cubes_cinfo)
READ = [*CUBES, 8, 33, 39, 43, 56, 59, 67, 71, 74, *range(75, 80), 103, 105, 112, 119, 122]
"""Every RAM byte OCAtari's Q*bert reader reads (without its HUD)."""


def slots(objects: list) -> list:
    return [None if o is None else object_state([o])[0] for o in objects]


def calls_that_differ(rams: list[np.ndarray], seen: set[str] | None = None) -> int:
    """Calls after which OCAtari's list or globals and :func:`detect_qbert`'s differ; ``seen`` gains the classes
    OCAtari's list held and ``gone <slot>`` for each slot it emptied."""
    theirs = extract_ram_info.init_objects("Qbert", False)
    ours = extract_ram_info.init_objects("Qbert", False)
    our_globals = {name: getattr(qbert, name) for name in GLOBALS}  # as init_objects left them
    differ = 0
    held = [o is not None for o in theirs]
    for ram in rams:
        extract_ram_info.detect_objects_ram(theirs, ram.astype(np.int64), "Qbert", False)
        their_globals = {name: getattr(qbert, name) for name in GLOBALS}
        for name, value in our_globals.items():
            setattr(qbert, name, value)
        detect_qbert(ours, ram)
        our_globals = {name: getattr(qbert, name) for name in GLOBALS}
        for name, value in their_globals.items():
            setattr(qbert, name, value)
        differ += slots(theirs) != slots(ours) or their_globals != our_globals
        if seen is not None:
            seen.update(o.__class__.__name__ for o in theirs if o is not None)
            seen.update(f"gone {slot}" for slot in range(len(theirs)) if theirs[slot] is None and held[slot])
            held = [o is not None for o in theirs]
    return differ


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_qbert_objects_equal_ocataris_on_played_games(seed):
    rams = played_rams(seed, 3000, "qbert")
    seen: set[str] = set()
    assert calls_that_differ(rams, seen) == 0
    assert {"Player", "Coily", "PurpleBall", "Sam", "gone 0", "gone 24", "gone 25", "gone 27"} <= seen
    assert len({int(ram[8]) for ram in rams}) >= 3, "no life was lost twice"


def test_qbert_objects_equal_ocataris_on_random_rams():
    rng = np.random.default_rng(31)
    played = played_rams(5, 800, "qbert")
    enemy_x = [qbert._calc_enemy_x(value) for value in range(13)]
    rams = []
    seen: set[str] = set()
    previous = played[0]
    for i in range(8000):
        ram = played[i % len(played)].copy()
        if i < 3000 and i % 3 == 0:  # every byte the reader reads anything (a life lost each time: only at first)
            ram[READ] = rng.integers(0, 256, len(READ))
        else:  # the events the reader follows, each now and then (runs of calls long enough for a ball or Sam
            # to reach the bottom row), the other bytes anything in their range
            ram[[8, 74, 103, 105, 119]] = previous[[8, 74, 103, 105, 119]]
            if rng.random() < 0.4:
                ram[74] = rng.integers(0, 256)  # the balls and Sam go down a row (or it is 0: no one moves)
            if rng.random() < 0.2:
                ram[103] = 17 if rng.random() < 0.5 else rng.integers(0, 256)  # a green ball starts
            if rng.random() < 0.2:
                ram[105] = 6 if rng.random() < 0.5 else rng.integers(0, 256)  # Sam starts
            if rng.random() < 0.2:
                ram[119] = 0 if rng.random() < 0.6 else rng.integers(1, 256)
            if rng.random() < 0.02:
                ram[8] = rng.integers(0, 256)  # a life lost (or gained)
            ram[39] = 255 if rng.random() < 0.5 else rng.integers(0, 8)  # Coily, or none
            ram[[56, 71]] = rng.integers(0, 12), rng.integers(0, 13)
            ram[75:80] = rng.integers(0, 13, 5)
            ram[67] = rng.choice([0, 16, 17, 69, 70, 99, 100, 209, 210, int(rng.integers(0, 256))])
            ram[59] = 255 if rng.random() < 0.2 else rng.integers(0, 255)
            ram[[43, 33]] = rng.integers(0, 256, 2)
            for byte in (112, 122):
                ram[byte] = 0 if rng.random() < 0.3 else rng.integers(1, 256)  # a disk used, or back
            if rng.random() < 0.2:
                ram[CUBES] = rng.integers(0, 256, len(CUBES))
            if rng.random() < 0.3:  # Q*bert within reach of whatever is on row k
                k = int(rng.integers(0, 5))
                ram[43] = enemy_x[ram[75 + k]] + 3 + rng.integers(-9, 10)
                ram[67] = (k + 1) * 30 + 12 - k + 7 + rng.integers(-9, 10)
                ram[59] = 0
        previous = ram
        rams.append(ram)
        if i % 9 == 0:
            rams.append(ram.copy())  # the same RAM again: nothing moves on, the cubes' shortcut
    assert calls_that_differ(rams, seen) == 0
    assert {"Player", "Coily", "PurpleBall", "GreenBall", "Sam", "gone 0", "gone 22", "gone 23", "gone 24", "gone 25", "gone 26",
                    "gone 27"} <= seen


def test_qbert_a_new_object_list_gets_its_cubes_colours():
    """The cubes' shortcut holds for one object list: a new one (a new game) gets its colours even when its first
    RAM's cube bytes are those of the previous call, on another list."""
    rng = np.random.default_rng(37)
    rams = played_rams(6, 60, "qbert")
    for ram in rams:
        ram[CUBES] = rng.integers(0, 256, len(CUBES))  # colours a new Cube does not have
    assert calls_that_differ(rams[:30]) == 0
    assert calls_that_differ(rams[29:]) == 0


def test_qbert_observations_equal_ocataris_through_the_environment():
    """The environment sets every object's previous position after its first observation; one environment at a
    time, as OCAtari's state is its module's."""
    game = get_game("qbert")
    ours, theirs = (played_through_env(spec, seeds=(3, 3, 3), state=slots)
                    for spec in (game, dataclasses.replace(game, detect=None)))
    assert len(theirs) > 1000 and ours == theirs

