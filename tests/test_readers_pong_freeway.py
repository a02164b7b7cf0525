"""games/readers/pong.py and games/readers/freeway.py leave OCAtari's object lists exactly as OCAtari's own readers.

Compared object by object after every call (``tests/reader_equality.py``) on the RAMs of played games (Pong: points
won and lost, the ball gone between them; Freeway: both chickens crossing, every car wrapping around), on thousands
of RAMs whose bytes the readers read are random (one call after another on the same lists), and through the
environment itself, whose first observation gives every slot a previous position (a NoObject kept from then on would
differ from the fresh one OCAtari puts there).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from games import get_game
from games.readers.freeway import detect_freeway
from games.readers.pong import detect_pong
from tests.reader_equality import (
    calls_that_differ,
    played_rams,
    played_through_env,
)

READERS = {"pong": ("Pong", detect_pong, [49, 50, 51, 54]),
           "freeway": ("Freeway", detect_freeway, [14, 15, *range(108, 118)])}
"""Per game: OCAtari's name, our reader, and every RAM byte OCAtari's reader reads (without its HUD)."""


@pytest.mark.parametrize("seed", [0, 1])
def test_pong_objects_equal_ocataris_on_played_games(seed):
    rams = played_rams(seed, 3000, "pong")
    stacked = np.array(rams)
    assert ((stacked[:, 54] == 0) | (stacked[:, 49] <= 49)).any(), "the ball never left: its empty slot goes unchecked"
    assert len(set(stacked[:, 13].tolist())) > 2 and len(set(stacked[:, 14].tolist())) > 1, "no points were scored"
    assert calls_that_differ(rams, "Pong", detect_pong) == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_freeway_objects_equal_ocataris_on_played_games(seed):
    rams = played_rams(seed, 2500, "freeway")
    stacked = np.array(rams)
    assert (np.diff(stacked[:, 108:118].astype(int), axis=0) != 0).any(axis=0).all(), "a car never moved"
    assert (stacked[:, 108:118] < 3).any(), "no car reached the screen's left edge (x < 0)"
    assert len(set(stacked[:, 14].tolist())) > 10, "the chicken never moved"
    assert calls_that_differ(rams, "Freeway", detect_freeway) == 0


@pytest.mark.parametrize("game", sorted(READERS))
def test_objects_equal_ocataris_on_random_rams(game):
    name, reader, read = READERS[game]
    rng = np.random.default_rng(31)
    played = played_rams(2, 400, game)
    rams = []
    for i in range(5000):
        ram = played[i % len(played)].copy()
        if i % 3 == 0:  # every byte the reader reads anything
            ram[read] = rng.integers(0, 256, len(read))
        else:  # one of them anything, at its edges more often (Pong's paddle clipping, an absent ball)
            ram[rng.choice(read)] = rng.choice([0, 1, 13, 14, 33, 34, 47, 48, 49, 50, 192, 193, 194, 195, 255,
                                                 int(rng.integers(0, 256))])
        rams.append(ram)
        if i % 7 == 0:
            rams.append(ram.copy())  # the same RAM twice: every slot keeps what it holds
    assert calls_that_differ(rams, name, reader) == 0


@pytest.mark.slow
@pytest.mark.parametrize("game", sorted(READERS))
def test_observations_equal_ocataris_through_the_environment(game):
    spec = get_game(game)
    ours, theirs = (played_through_env(g, max_steps=1500) for g in (spec, dataclasses.replace(spec, detect=None)))
    assert len(theirs) > 1000 and ours == theirs
