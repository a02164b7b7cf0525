"""OCAtari's RAM readers redone with arrays where they loop in Python: the same objects, at a fraction of the cost.

Breakout (:func:`detect_breakout`, the game's ``Game.detect``):

OCAtari's Breakout reader (``ocatari.ram.breakout._detect_objects_ram``) formats 36 RAM bytes as binary strings,
parses them back into a 6 x 18 brick bitmap, walks it cell by cell through NumPy scalars and makes a ``Block``
for every run of bricks, every step: ~90 µs a step here, a quarter of a whole step, for a wall that changes only
when a brick breaks. :func:`detect_breakout` leaves OCAtari's object list in exactly the state OCAtari's would
(the same classes in the same slots, the same positions, sizes, colours and previous positions):

- the bitmap is a gather of bits, each cell the RAM bit OCAtari's string formatting lands there (found from
  OCAtari's own function, :func:`_bit_map`, when this module is first imported);
- the runs come from the bitmap's edges (``np.diff``) instead of a walk;
- when the 36 bytes are those of the previous call on the same object list, the slots already hold this wall:
  only what OCAtari's walk would still do to them is done (each run's Block gets its row's colour again).

A RAM whose first bytes do not fit OCAtari's 6-bit formatting (a value >= 64 there; never seen in play) goes to
OCAtari's own reader.

Space Invaders (:func:`detect_space_invaders`): OCAtari's reader line for line on the RAM as Python ints, whose
every operation costs a fraction of a NumPy scalar's (the int64 RAM it needs under numpy 2 gives the same
values), and ``bool(obj)`` written out where it was a Python call per object.

tests/test_readers.py compares each with OCAtari's on played and random RAMs, object list against object list.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from ocatari.ram import breakout as _ocatari
from ocatari.ram.game_objects import NoObject

Ball, Block = _ocatari.Ball, _ocatari.Block
ROWS, COLUMNS = 6, 18
WALL_BYTES = 36
ROW_COLOURS = [_ocatari.blockRow_colors.get(str(row)) for row in range(ROWS)]
"""The colour OCAtari gives a new Block of each row (``_calculate_blocks``)."""
SLOT_COLOURS = _ocatari.block_colors
"""The colour OCAtari gives a slot's Block that it updates in place (``_detect_objects_ram``)."""


def _bit_map() -> tuple[np.ndarray, np.ndarray]:
    """For each cell of OCAtari's 6 x 18 brick bitmap, the RAM byte and the bit it shows, found by lighting one
    bit at a time through OCAtari's ``_make_block_bitmap`` (each cell shows exactly one bit)."""
    byte = np.full((ROWS, COLUMNS), -1, dtype=np.int64)
    bit = np.zeros((ROWS, COLUMNS), dtype=np.int64)
    for index in range(WALL_BYTES):
        for b in range(6 if index < 6 else 8):  # the first six bytes are formatted on 6 bits
            ram = np.zeros(128, dtype=np.int64)
            ram[index] = 1 << b
            for r, c in zip(*np.nonzero(_ocatari._make_block_bitmap(ram))):
                if byte[r, c] != -1:
                    raise RuntimeError("OCAtari's Breakout bitmap is not one RAM bit per cell")
                byte[r, c], bit[r, c] = index, b
    if (byte < 0).any():
        raise RuntimeError("a cell of OCAtari's Breakout bitmap shows no RAM bit")
    return byte, bit


_BYTE, _BIT = _bit_map()
_last: list[Any] = [None, b"", ()]
"""The object list of the previous call, its 36 wall bytes and the runs it made: ``[(slot, (x, y, w, h),
row), ...]``."""


def detect_breakout(objects: list, ram: np.ndarray) -> None:
    """``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "Breakout", False)``, exactly (see
    the module docstring); ``ram`` as ALE gives it (uint8)."""
    wall = ram[:WALL_BYTES]
    if (wall[:6] >= 64).any():  # OCAtari's formatting differs there (a 7-8 bit string): its own reader
        _last[0] = None
        from ocatari.ram.extract_ram_info import detect_objects_ram

        detect_objects_ram(objects, ram.astype(np.int64), "Breakout", False)
        return
    key = wall.tobytes()
    same = _last[0] is objects and _last[1] == key
    for obj in objects:  # OCAtari saves every present object's position first
        if obj.__class__ is not NoObject and obj._visible:
            obj._prev_xy = obj._xy
    paddle, ball_x, ball_y = int(ram[72]), int(ram[99]), int(ram[101])  # ints: no uint8 wrap-around
    objects[0].xy = paddle - 47, 189
    if ball_y + 9 <= 196 and ball_y != 0:  # else no ball
        if type(objects[1]) is NoObject:
            objects[1] = Ball()
        objects[1].xy = ball_x - 49, ball_y + 9
    else:
        objects[1] = NoObject()
    if same:  # the slots hold this wall: OCAtari's walk only updates each run's Block in place
        for slot, xywh, row in _last[2]:
            block = objects[slot]
            block.xywh = xywh
            block.rgb = SLOT_COLOURS[row]
        return
    runs = []
    padded = np.zeros((ROWS, COLUMNS + 2), dtype=np.int8)
    padded[:, 1:-1] = (wall.astype(np.int64)[_BYTE] >> _BIT) & 1
    edges = np.diff(padded, axis=1)
    starts, ends = np.nonzero(edges == 1), np.nonzero(edges == -1)
    run_at = {}
    for row, start, end in zip(starts[0].tolist(), starts[1].tolist(), ends[1].tolist()):
        run_at[2 + row * COLUMNS + start] = (row, start, end - start)
    for row in range(ROWS):
        base = 2 + row * COLUMNS
        for slot in range(base, base + COLUMNS):
            current = objects[slot]
            present = current.__class__ is not NoObject and current._visible
            run = run_at.get(slot)
            if run is None:
                if present:
                    objects[slot] = NoObject()
                continue
            _, start, length = run
            xywh = (8 + start * 8, 57 + 6 * row, 8 * length, 6)
            runs.append((slot, xywh, row))
            if present:
                current.xywh = xywh
                current.rgb = SLOT_COLOURS[row]
            else:
                block = Block()
                block.rgb = ROW_COLOURS[row]
                block.xy = xywh[0], xywh[1]
                block.wh = xywh[2], 6
                objects[slot] = block
    _last[:] = [objects, key, tuple(runs)]


# -- Space Invaders ------------------------------------------------------------------------------------------------

_SPACE_INVADERS: tuple = ()
"""OCAtari's Space Invaders classes and bitmap function, imported on first use."""


def detect_space_invaders(objects: list, ram: np.ndarray) -> None:
    """``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "SpaceInvaders", False)``, exactly: OCAtari
    2.2.1's ``ocatari.ram.spaceinvaders._detect_objects_ram`` line for line (its quirks kept: the bullets it
    removes still get the new positions, the ``NoObject`` s left in their slots keep theirs), on the RAM as Python
    ints instead of NumPy scalars, whose every operation costs several times an int's (~50 µs a step -> ~15)."""
    global _SPACE_INVADERS
    if not _SPACE_INVADERS:
        from ocatari.ram import spaceinvaders

        _SPACE_INVADERS = (spaceinvaders.Alien, spaceinvaders.Bullet, spaceinvaders.Satellite,
                           spaceinvaders.make_bitmap)
    Alien, Bullet, Satellite, make_bitmap = _SPACE_INVADERS
    ram_state = ram.tolist()  # ints: what int64 arithmetic gives on bytes, without NumPy's per-scalar cost
    # ``o.__class__ is not NoObject and o._visible`` is ``bool(o)`` for these classes (GameObject.__bool__), without
    # a Python call per object
    for obj in objects:  # saving the previous positions, as extract_ram_info.detect_objects_ram does
        if obj.__class__ is not NoObject and obj._visible:
            obj._prev_xy = obj._xy
    player = objects[0]
    shields = objects[1:4]
    bullets = objects[4:7]
    satellite = objects[7]
    aliens = objects[8:44]

    player.xy = ram_state[28] - 1, 185
    x, y = ram_state[26], ram_state[16]
    bitmap, emptc = make_bitmap(ram_state[18:24])
    if sum(ram_state[18:24]) == 378:
        for s in shields:
            s.visible = True
    for i in range(6):
        row = bitmap[i]
        for j in range(6):
            present = aliens[35 - (i * 6 + j)]
            present = present.__class__ is not NoObject and present._visible
            alive = int(row[j])
            if present and not alive:
                objects[43 - (i * 6 + j)] = NoObject()
            elif not present and alive:
                objects[43 - (i * 6 + j)] = Alien()
    low = False
    for i in range(6):
        top = 31 + y * 2 + i * 18
        for j in range(6):
            alien = aliens[i * 6 + j]
            if alien.__class__ is not NoObject and alien._visible:
                alien.xy = x - 1 + (j - emptc) * 16, top
                low = low or alien._xy[1] + alien.wh[1] >= 157
    if low:  # an alien reached the shields' height: they go (OCAtari hides them inside its loop, once is the same)
        for s in range(3):
            if shields[s]:
                shields[s].visible = False
    upper_y = 0
    lower_y = 16
    for i in range(3):
        for j in range(9):
            if ram_state[43 + i * 9 + j] != 0:
                upper_y = j * 2
                break
        for j in range(9):
            if ram_state[43 + (i + 1) * 9 - (j + 1)] != 0:
                lower_y = j * 2
                break
        objects[1 + i].xy = 42 + i * 32, 157 + upper_y
        objects[1 + i].wh = 8, 18 - upper_y - lower_y
    bullets_visible = [20 < bullets[i].xy[1] < 195 for i in range(3)]
    for i in range(3):
        if bullets_visible[i]:
            if not bullets[i]:
                bullet = Bullet()
                objects[4 + i] = bullet
                bullets[i] = bullet
        else:
            if bullets[i]:
                objects[4 + i] = NoObject()
        if i < 2:
            bullets[i].xy = ram_state[83 + i] - 2, 2 * ram_state[81 + i] + 3
            if bullets[i].xy[1] < 194:
                if bullets[i].xy[1] + bullets[i].wh[1] > 195:
                    bullets[i].wh = bullets[i].wh[0], 195 - bullets[i].xy[1] - 1
                else:
                    bullets[i].wh = 1, 10
        else:
            bullets[2].xy = ram_state[87] - 2, 2 * ram_state[85] + 3
    if ram_state[30] and ram_state[30] != 180:
        if not satellite:
            satellite = Satellite()
            objects[7] = satellite
        satellite.xy = ram_state[30] - 1, 12
    else:
        if satellite in objects:
            objects[7] = NoObject()
