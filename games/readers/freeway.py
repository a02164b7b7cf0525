"""OCAtari's Freeway reader (:func:`detect_freeway`, the game's ``Game.detect``) on the RAM as Python ints.

OCAtari 2.2.1's ``ocatari.ram.freeway._detect_objects_ram`` places the two chickens (RAM 14 and 15) and the ten cars
(RAM 108-117, one per lane, each keeping its lane's y) through the ``xy`` and ``x`` property setters, on NumPy
scalars, after ``extract_ram_info.detect_objects_ram`` has called each object's ``__bool__`` and ``_save_prev``: ~5.4
µs a step. Freeway's twelve objects are always there (it makes no ``NoObject``), so the same, done on ints with the
setters' one assignment written out, is ~1.8 µs, and the positions it leaves are Python ints, which the observation
build then takes as they are.
"""

from __future__ import annotations

import numpy as np
from ocatari.ram.game_objects import NoObject


def detect_freeway(objects: list, ram: np.ndarray) -> None:
    """``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "Freeway", False)``, exactly; ``ram`` as
    ALE gives it (uint8)."""
    r = ram.tolist()  # ints: the same values as int64 (193 - byte and byte - 3 stay far inside either)
    # ``o.__class__ is not NoObject and o._visible`` is ``bool(o)`` for these classes, without a Python call per object
    for obj in objects:  # saving the previous positions, as extract_ram_info.detect_objects_ram does
        if obj.__class__ is not NoObject and obj._visible:
            obj._prev_xy = obj._xy
    objects[0]._xy = 44, 193 - r[14]  # the xy setter's int() of ints is a no-op
    objects[1]._xy = 108, 193 - r[15]
    for lane in range(10):  # the x setter keeps the car's y
        car = objects[2 + lane]
        car._xy = r[117 - lane] - 3, car._xy[1]
