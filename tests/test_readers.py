"""games/readers/: OCAtari's RAM readers redone with arrays leave OCAtari's object list exactly as OCAtari's own.

Compared object by object (class, position, size, colour, previous position, visibility) after every call, on the
RAMs of played games (random actions, several seeds, lives lost, bricks broken) and on RAMs whose wall bytes are
random or have single bits flipped, one call after another on the same object lists, as an episode makes them.
Space Invaders' reader redoes nothing whose bytes stand: its sweeps hold one alien bitmap for runs of calls while
the other bytes change or stand, give it any bytes (OCAtari's exceptions compared too), alternate two object lists,
and go through the environment itself.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ocatari.ram import extract_ram_info

from games import get_game
from games.readers.breakout import detect_breakout
from games.readers.space_invaders import detect_space_invaders
from tests.reader_equality import (
    calls_that_differ,
    object_state,
    played_rams,
    played_through_env,
)


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


SPACE_INVADERS_READ = [16, *range(18, 24), 26, 28, 30, *range(43, 70), 81, 82, 83, 84, 85, 87]
"""Every RAM byte OCAtari's Space Invaders reader reads (without its HUD)."""


def space_invaders_outcomes_that_differ(rams: list[np.ndarray], lists: int = 1) -> int:
    """Calls after which OCAtari's reader and ours differ, in the exception they raise (its type) or the object
    list they leave, with ``lists`` object lists used in turn (each carried from call to call, as an episode
    carries it; the reader's memory of the previous call belongs to one list)."""
    theirs = [extract_ram_info.init_objects("SpaceInvaders", False) for _ in range(lists)]
    ours = [extract_ram_info.init_objects("SpaceInvaders", False) for _ in range(lists)]
    differ = 0
    for n, ram in enumerate(rams):
        outcomes = []
        for reader, objects in ((lambda o, r: extract_ram_info.detect_objects_ram(o, r.astype(np.int64),
                                                                                  "SpaceInvaders", False),
                                 theirs[n % lists]),
                                (detect_space_invaders, ours[n % lists])):
            try:
                reader(objects, ram)
                raised = None
            except Exception as exc:  # noqa: BLE001 - whatever OCAtari does, ours does the same
                raised = type(exc).__name__
            outcomes.append((raised, object_state(objects)))
        differ += outcomes[0] != outcomes[1]
    return differ


def space_invaders_runs(seed: int, calls: int, out_of_range: float = 0.0) -> list[np.ndarray]:
    """RAMs in runs that hold one alien bitmap (random, a full wave, none, one alien more or less than the last,
    one alien alone) while the game's played RAMs go on under it (lives lost included) and the other bytes the
    reader reads change or stand: the block still or moving down to the shields, shields hit, emptied or
    untouched, bombs and the player's bullet anywhere (their bottom edge included), the satellite there or not;
    now and then the same RAM twice. With ``out_of_range``, that share of the bitmaps has bytes >= 64 (never
    seen in play: OCAtari's formatting raises)."""
    rng = np.random.default_rng(seed)
    played = played_rams(seed, 700, "space_invaders")
    rams = []
    bitmap = played[0][18:24].copy()
    ram = played[0].copy()
    at = 0
    while len(rams) < calls:
        kind = rng.integers(0, 6)
        if rng.random() < out_of_range:
            bitmap = rng.integers(0, 256, 6).astype(np.uint8)
        elif kind == 0:
            bitmap = rng.integers(0, 64, 6).astype(np.uint8)
        elif kind == 1:
            bitmap = np.full(6, 63, dtype=np.uint8)  # a full wave: OCAtari shows the shields again
        elif kind == 2:
            bitmap = np.zeros(6, dtype=np.uint8)
        elif kind == 3:  # one alien killed, or back
            bitmap = bitmap.copy()
            bitmap[rng.integers(0, 6)] ^= np.uint8(1 << int(rng.integers(0, 6)))
        elif kind == 4:
            bitmap = np.zeros(6, dtype=np.uint8)
            bitmap[rng.integers(0, 6)] = 1 << int(rng.integers(0, 6))
        else:
            bitmap = bitmap.copy()  # the same bitmap again, after a run of it
        for _ in range(int(rng.integers(1, 12))):
            before = ram
            ram = played[at % len(played)].copy()
            at += 1
            ram[18:24] = bitmap
            change = rng.random(6)
            if change[0] < 0.4:  # the block stands (or, from the game's RAM, moves as played)
                ram[[16, 26]] = before[[16, 26]]
            elif change[0] < 0.7:  # anywhere, down to the shields' height and beyond
                ram[16] = rng.integers(0, 256) if rng.random() < 0.3 else rng.integers(0, 64)
                ram[26] = rng.integers(0, 256)
            if change[1] < 0.4:
                ram[43:70] = before[43:70]
            elif change[1] < 0.7:
                ram[43:70] = rng.integers(0, 256, 27) * (rng.random(27) < 0.5)
                ram[43 + 9 * rng.integers(0, 3):][:9] = 0  # a shield shot away
            if change[2] < 0.5:  # bombs and bullet: on screen, at the bottom edge (y 186..193), off, anything
                ram[[81, 82, 85]] = rng.choice([0, 5, 9, 50, 91, 92, 93, 94, 95, 96, 200, 255], 3)
                ram[[83, 84, 87]] = rng.integers(0, 256, 3)
            if change[3] < 0.3:
                ram[30] = rng.choice([0, 180, 1, 179, 181, 255, int(rng.integers(0, 256))])
            if change[4] < 0.2:
                ram[28] = rng.integers(0, 256)
            rams.append(ram)
            if change[5] < 0.1:
                rams.append(ram.copy())
    return rams


@pytest.mark.parametrize("seed", [3, 4])
def test_space_invaders_objects_equal_ocataris_while_the_bitmap_stands(seed):
    """The reader re-derives the alien slots only when the bitmap or the object list changes, places the aliens
    only when the block moved, writes the shields only when their bytes changed: runs of one bitmap while
    everything else changes or stands, bitmaps changing after runs, on one object list and on two in turn."""
    rams = space_invaders_runs(seed, 3000)
    stacked = np.array(rams)
    runs = np.flatnonzero((stacked[1:, 18:24] != stacked[:-1, 18:24]).any(axis=1))
    assert 200 < len(runs) < len(rams) / 3, "the bitmap should change after runs of calls, not every call"
    assert (stacked[:, 18:24] == 63).all(axis=1).any() and (stacked[:, 18:24] == 0).all(axis=1).any()
    assert (2 * stacked[:, 16].astype(int) + 18 * 5 >= 116).sum() > 100, "the block never reached the shields"
    assert len(set(stacked[:, 73].tolist())) >= 3, "no life was lost"
    assert space_invaders_outcomes_that_differ(rams) == 0
    assert space_invaders_outcomes_that_differ(rams, lists=2) == 0


def test_space_invaders_objects_equal_ocataris_on_any_bytes():
    """Every byte the reader reads random, bitmaps with bytes >= 64 among them (OCAtari raises there, leaving
    its list half-updated; the next calls go on from that list), and runs of them."""
    rng = np.random.default_rng(19)
    played = played_rams(5, 300, "space_invaders")
    rams = []
    for i in range(3000):
        ram = played[i % len(played)].copy()
        ram[SPACE_INVADERS_READ] = rng.integers(0, 256, len(SPACE_INVADERS_READ))
        if rng.random() < 0.8:
            ram[18:24] = rng.integers(0, 64, 6)
        rams.append(ram)
    rams += space_invaders_runs(6, 2000, out_of_range=0.2)
    assert sum(ram[18:24].max() >= 64 for ram in rams) > 300
    assert space_invaders_outcomes_that_differ(rams) == 0
    assert space_invaders_outcomes_that_differ(rams, lists=2) == 0


def test_space_invaders_observations_equal_ocataris_through_the_environment():
    """The environment sets every slot's previous position after its first observation (NoObjects included):
    the satellite's NoObject kept from then on would differ from the new one OCAtari puts there."""
    game = get_game("space_invaders")
    ours, theirs = (played_through_env(spec) for spec in (game, dataclasses.replace(game, detect=None)))
    assert len(theirs) > 600 and ours == theirs

