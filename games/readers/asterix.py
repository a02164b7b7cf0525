"""OCAtari's Asterix reader (:func:`detect_asterix`, the game's ``Game.detect``) on the RAM as Python ints, with
the objects OCAtari makes anew every step kept instead when a fresh one would be equal.

OCAtari 2.2.1's ``ocatari.ram.asterix._detect_objects_ram`` gives each of the eight lanes three slots (a Reward in
``1 + lane``, an Enemy in ``9 + lane``, a Consumable in ``17 + lane``) but checks for an existing Enemy or
Consumable in the Reward's slot, where neither ever is: every step it makes a new Enemy or Consumable for every
lane that holds one, and two new ``NoObject`` s beside it (~24 objects a step). A new object differs from the one
already in its slot only by its previous position (``None``: dx, dy 0), so :func:`detect_asterix` keeps the
object of the same class and clears its previous position, and keeps a ``NoObject`` that is still as made (its
previous position ``None``: the environment's first observation sets it). Everything else is OCAtari's code line
for line: its quirks stay (a lane whose RAM[18 - lane] is 11 empties only the Reward's slot, leaving a stale
Enemy or Consumable beside it).
"""

from __future__ import annotations

import numpy as np
from ocatari.ram.game_objects import NoObject

from games.readers import empty_slot

_ASTERIX: tuple = ()
"""OCAtari's Asterix classes (Reward, Enemy, Consumable), imported on first use."""


def _fresh(objects: list, slot: int, cls: type):
    """The object a fresh ``cls()`` would be once placed in ``slot``: the one there when it is of that class (its
    previous position cleared, as a new object's is), else a new one."""
    obj = objects[slot]
    if obj.__class__ is cls and obj._visible:  # its size and colour are never changed: those of a new one
        obj._prev_xy = None
        return obj
    obj = objects[slot] = cls()
    return obj


def detect_asterix(objects: list, ram: np.ndarray) -> None:
    """``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "Asterix", False)``, exactly (see the
    module docstring); ``ram`` as ALE gives it (uint8)."""
    global _ASTERIX
    if not _ASTERIX:
        from ocatari.ram import asterix

        _ASTERIX = (asterix.Reward, asterix.Enemy, asterix.Consumable)
    Reward, Enemy, Consumable = _ASTERIX
    r = ram.tolist()  # ints: the same values as int64 (no arithmetic here leaves 0..4,096), at a fraction of the cost
    # ``o.__class__ is not NoObject and o._visible`` is ``bool(o)`` for these classes, without a Python call per object
    for obj in objects:  # saving the previous positions, as extract_ram_info.detect_objects_ram does
        if obj.__class__ is not NoObject and obj._visible:
            obj._prev_xy = obj._xy
    player = objects[0]
    player._xy = r[41], 26 + r[39] * 16  # the xy setter's int() of ints is a no-op
    if r[71] < 82:
        player.wh = (8, 11) if r[54] < 5 else (6, 11)  # Asterix, or Obelix
    else:  # dying: wide
        player.wh = 16, 11
    for i in range(8):
        y = 26 + i * 16
        # OCAtari tests the Reward's slot (1 + i) as it was when the call began: no earlier lane writes there
        if r[18 - i] == 11:
            empty_slot(objects, 1 + i)
        elif r[73 + i]:
            if objects[1 + i].__class__ is not Reward:
                objects[1 + i] = rew = Reward()
                empty_slot(objects, 9 + i)
                empty_slot(objects, 17 + i)
            else:
                rew = objects[1 + i]
            rew._xy = r[42 + i], y
        elif r[29 + i] % 2 == 1:
            if isinstance(objects[1 + i], Enemy):  # never, in OCAtari's own lists: kept, as it is written
                en = objects[1 + i]
            else:
                empty_slot(objects, 1 + i)
                en = _fresh(objects, 9 + i, Enemy)
                empty_slot(objects, 17 + i)
            en._xy = r[42 + i], y
        else:
            if objects[1 + i].__class__ is Consumable:  # never either
                instance = objects[1 + i]
            else:
                empty_slot(objects, 1 + i)
                empty_slot(objects, 9 + i)
                instance = _fresh(objects, 17 + i, Consumable)
            instance._xy = r[42 + i] + 1, y + 1
