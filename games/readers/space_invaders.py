"""OCAtari's Space Invaders reader (:func:`detect_space_invaders`, the game's ``Game.detect``) line for line on
the RAM as Python ints, whose every operation costs a fraction of a NumPy scalar's (the int64 RAM it needs
under numpy 2 gives the same values), and ``bool(obj)`` written out where it was a Python call per object.
"""

from __future__ import annotations

import numpy as np
from ocatari.ram.game_objects import NoObject

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
