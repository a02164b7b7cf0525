"""games/readers/: OCAtari's RAM readers redone with arrays leave OCAtari's object list exactly as OCAtari's own.

Compared object by object (class, position, size, colour, previous position, visibility) after every call, on the
RAMs of played games (random actions, several seeds, lives lost, bricks broken) and on RAMs whose wall bytes are
random or have single bits flipped, one call after another on the same object lists, as an episode makes them.
"""

from __future__ import annotations

import numpy as np
import pytest
from ocatari.ram import extract_ram_info

from games.readers.breakout import detect_breakout
from games.readers.space_invaders import detect_space_invaders
from tests.reader_equality import calls_that_differ, object_state, played_rams


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_breakout_objects_equal_ocataris_on_played_games(seed):
    rams = played_rams(seed, 1500)
    walls = {ram[:36].tobytes() for ram in rams}
    assert len(walls) > 3, "the games broke no brick: the sweep would not cover a changing wall"
    assert calls_that_differ(rams, "Breakout", detect_breakout) == 0


def test_breakout_objects_equal_ocataris_on_random_walls():
    rng = np.random.default_rng(7)
    played = played_rams(3, 400)
    rams = []
    for i in range(3000):
        ram = played[i % len(played)].copy()
        if i % 3 == 0:  # any wall OCAtari's 6-bit formatting of the first bytes reads
            ram[:36] = rng.integers(0, 256, 36)
            ram[:6] = rng.integers(0, 64, 6)
        elif i % 3 == 1:  # one brick more or less
            ram[rng.integers(0, 36)] ^= 1 << int(rng.integers(0, 6))
        if i % 5 == 0:  # the ball anywhere, or gone
            ram[101] = rng.integers(0, 256)
        rams.append(ram)
        if i % 7 == 0:
            rams.append(ram.copy())  # the same wall twice in a row: the reader's shortcut
    assert calls_that_differ(rams, "Breakout", detect_breakout) == 0


def test_a_wall_outside_ocataris_formatting_goes_to_ocataris_reader():
    ram = played_rams(0, 5)[-1]
    ram[2] = 200  # formatted on 8 characters where OCAtari expects 6: its own reader decides what that means
    theirs = extract_ram_info.init_objects("Breakout", False)
    ours = extract_ram_info.init_objects("Breakout", False)
    for reader, objects in ((lambda o, r: extract_ram_info.detect_objects_ram(o, r.astype(np.int64), "Breakout",
                                                                              False), theirs),
                            (detect_breakout, ours)):
        try:
            reader(objects, ram)
            outcome = object_state(objects)
        except Exception as exc:  # noqa: BLE001 - whatever OCAtari does, ours does the same
            outcome = type(exc).__name__
        if objects is theirs:
            expected = outcome
    assert outcome == expected


@pytest.mark.parametrize("seed", [0, 1])
def test_space_invaders_objects_equal_ocataris_on_played_games(seed):
    """Long enough for aliens to die, bullets to come and go, the satellite to pass and lives to be lost; the
    NoObjects OCAtari leaves in bullet slots keep the positions it gives them, and so do ours."""
    rams = played_rams(seed, 2500, "space_invaders")
    assert len({tuple(ram[18:24]) for ram in rams}) > 3, "no alien died: the sweep would not cover the bitmap"
    assert any(ram[30] and ram[30] != 180 for ram in rams), "no satellite passed"
    assert calls_that_differ(rams, "SpaceInvaders", detect_space_invaders) == 0


def test_space_invaders_objects_equal_ocataris_on_random_rams():
    rng = np.random.default_rng(11)
    played = played_rams(2, 600, "space_invaders")
    rams = []
    for i in range(2000):
        ram = played[i % len(played)].copy()
        ram[18:24] = rng.integers(0, 64, 6)  # any set of living aliens
        for index in rng.choice([16, 26, 28, 30, 81, 82, 83, 84, 85, 87] + list(range(43, 70)), 6):
            ram[index] = rng.integers(0, 256)  # positions, shields, bullets, the satellite anywhere
        ram[16] = i % 64  # every height of the alien block, the shields' edge included
        rams.append(ram)
    assert calls_that_differ(rams, "SpaceInvaders", detect_space_invaders) == 0
