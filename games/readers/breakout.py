"""OCAtari's Breakout reader with arrays (:func:`detect_breakout`, the game's ``Game.detect``).

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
"""

from __future__ import annotations

from typing import Any

import numpy as np
from ocatari.ram import breakout as _ocatari
from ocatari.ram.game_objects import NoObject

from games.breakout import BALL_Y, ball_in_play

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
    objects[0].xy = int(ram[72]) - 47, 189  # ints: no uint8 wrap-around
    if ball_in_play(ram):  # else no ball
        if type(objects[1]) is NoObject:
            objects[1] = Ball()
        objects[1].xy = int(ram[99]) - 49, int(ram[BALL_Y]) + 9
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
