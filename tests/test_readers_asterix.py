"""games/readers/asterix.py leaves OCAtari's Asterix object list exactly as OCAtari's own reader does.

Compared object by object after every call (``tests/reader_equality.py``) on the RAMs of played games (rewards,
lyres and cauldrons in every lane, lanes emptied, lives lost), on thousands of RAMs whose bytes the reader reads
are random (each lane switched between a reward, an enemy, a consumable and an emptied lane, from call to call on
the same lists), and through the environment itself, whose first observation touches every slot's previous
position, against the same environment with OCAtari's reader.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from games import get_game
from games.readers.asterix import detect_asterix
from tests.reader_equality import (
    calls_that_differ,
    played_rams,
    played_through_env,
)

LANES = np.arange(8)
READ = [39, 41, 54, 71, *range(11, 19), *range(29, 37), *range(42, 50), *range(73, 81)]
"""Every RAM byte OCAtari's Asterix reader reads (without its HUD)."""


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_asterix_objects_equal_ocataris_on_played_games(seed):
    rams = played_rams(seed, 2000, "asterix")
    stacked = np.array(rams)
    rewards, emptied = stacked[:, 73:81] != 0, stacked[:, 18 - LANES] == 11
    enemies = ~rewards & (stacked[:, 29:37] % 2 == 1)
    assert (rewards & ~emptied).any() and (enemies & ~emptied).any() and (~rewards & ~enemies & ~emptied).any()
    assert emptied.any(), "no lane was emptied: OCAtari's stale objects beside it would go unchecked"
    assert (stacked[:, 71] >= 82).any(), "the player never died"
    assert len(set(stacked[:, 83].tolist())) == 3, "no life was lost twice"
    assert calls_that_differ(rams, "Asterix", detect_asterix) == 0


def test_asterix_objects_equal_ocataris_on_random_rams():
    rng = np.random.default_rng(23)
    played = played_rams(4, 500, "asterix")
    rams = []
    for i in range(6000):
        ram = played[i % len(played)].copy()
        if i % 4 == 0:  # every byte the reader reads anything
            ram[READ] = rng.integers(0, 256, len(READ))
        else:  # each lane one of the four things it can be, its other bytes anything
            kind = rng.integers(0, 4, 8)
            ram[18 - LANES] = np.where(kind == 0, 11, rng.choice([0, 10, 12, 255], 8))
            ram[73:81] = np.where(kind == 1, rng.integers(1, 256, 8), 0)
            ram[29:37] = rng.integers(0, 128, 8) * 2 + (kind == 2)
            ram[42:50] = rng.integers(0, 256, 8)
            ram[[39, 41]] = rng.integers(0, 256, 2)
            ram[71] = rng.choice([0, 81, 82, 255])
            ram[54] = rng.choice([0, 4, 5, 255])  # Asterix, or Obelix
        rams.append(ram)
        if i % 9 == 0:
            rams.append(ram.copy())  # the same RAM twice: every lane keeps what it holds
    assert calls_that_differ(rams, "Asterix", detect_asterix) == 0


def test_asterix_observations_equal_ocataris_through_the_environment():
    """The environment sets every slot's previous position after its first observation (NoObjects included):
    a NoObject kept from then on would differ from the new one OCAtari puts there."""
    game = get_game("asterix")
    ours, theirs = (played_through_env(spec, seeds=(3, 3, 3)) for spec in (game, dataclasses.replace(game, detect=None)))
    assert len(theirs) > 300 and ours == theirs

