"""OCAtari's Seaquest reader slot by slot (:func:`detect_seaquest`, the game's ``Game.detect``).

OCAtari's Seaquest reader (``ocatari.ram.seaquest._detect_objects_ram``) writes every one of its 42 slots every
step, and most of what it writes is a fresh ``NoObject`` for an empty enemy, diver or missile slot (two per empty
enemy slot: ~25 a step, each a constructor call), on the RAM as NumPy scalars. :func:`detect_seaquest` leaves the
object list in exactly the state OCAtari's would (the same classes in the same slots, the same positions, sizes,
colours, previous positions, visibility, orientation and oxygen value, and the same objects shared between slots):

- the RAM as Python ints (``ram.tolist()``), whose operations cost a fraction of a NumPy scalar's and give what
  OCAtari's int64 arithmetic gives (nothing here leaves the int64 range);
- each slot visited once, its previous position saved there (``extract_ram_info.detect_objects_ram`` saves every
  present object's first: the same, as OCAtari's reader only ever reads an object in its own slot, and the one
  object it shares between slots, the initial ``CollectedDiver``, never moves);
- a slot that must become a ``NoObject`` keeps the one it holds when that one is in a fresh ``NoObject``'s state:
  nothing writes a ``NoObject`` outside slot 0 (whose every write is redone here as OCAtari does it) except
  ``games.envs.ObjectObservation``'s first observation, which gives it a previous position (then a fresh one is
  made, as OCAtari would);
- attributes written directly where OCAtari's setter only converts to ``int`` (already ints here).

OCAtari's quirks are kept: the enemy of the other kind stays in its slot, unmoved, when a lane turns from sharks
to submarines (or back); a diver stays when its lane's byte goes off screen while the lane has submarines (and a
missile when it has sharks); the player slot's object gets the new position and orientation before it is
replaced; the six ``CollectedDiver`` slots share OCAtari's first one, at (0, 0), until a slot empties.
"""

from __future__ import annotations

import numpy as np
from ocatari.ram.game_objects import NoObject, Orientation
from ocatari.ram.seaquest import (
    CollectedDiver,
    Diver,
    EnemyMissile,
    OxygenBar,
    Player,
    PlayerMissile,
    Shark,
    Submarine,
    SurfaceSubmarine,
)

_EAST, _WEST = Orientation.E, Orientation.W
_ENEMY_SLOTS = tuple((lane, 4 >> j, lane * 3 + j + 1, lane * 3 + j + 13, 16 * j, 141 - lane * 24)
                     for lane in range(4) for j in range(3))
"""Per enemy slot, left to right in each lane, bottom lane first: its lane, the lane's formation bit that fills it
(OCAtari's ``(formation // 2 ** (2 - j)) % 2``), its shark and submarine slots, its x offset and its y."""
_DIVER_SLOTS = tuple((74 - i, 3 - i, 25 + i, 29 + i, 141 - (3 - i) * 24) for i in range(4))
"""Per diver / missile slot pair, bottom lane first: the RAM byte of its x, its lane, its two slots, a diver's y."""


def _place(objects: list, slot: int, kind: type, x: int, y: int) -> None:
    """OCAtari's ``obj = objects[slot]; if type(obj) is not kind: obj = kind()``, then ``obj.xy = x, y`` (with the
    previous position saved first when ``obj`` was there and present)."""
    obj = objects[slot]
    if obj.__class__ is kind:
        if obj._visible:
            obj._prev_xy = obj._xy
    else:
        obj = objects[slot] = kind()
    obj._xy = x, y


def detect_seaquest(objects: list, ram: np.ndarray) -> None:
    """``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "Seaquest", False)``, exactly (see the
    module docstring); ``ram`` as ALE gives it (uint8)."""
    r = ram.tolist()
    # ``o.__class__ is not NoObject and o._visible`` is ``bool(o)`` (GameObject.__bool__) without a Python call;
    # ``o.__class__ is not NoObject or o._prev_xy is not None``: ``o`` is not a NoObject as fresh as OCAtari's

    # the player (slot 0): the object there moves and turns, then is replaced if it should (dis)appear
    player = objects[0]
    if player.__class__ is not NoObject and player._visible:
        player._prev_xy = player._xy
    player._xy = r[70], r[97] + 33
    player._orientation = _EAST if r[86] == 0 else _WEST
    if 0 < r[105] < 15:
        if player.__class__ is not NoObject and player._visible:
            objects[0] = NoObject()
    elif player.__class__ is NoObject or not player._visible:
        objects[0] = Player()

    # enemies: four lanes of three slots, sharks in slots 1-12, submarines in 13-24 (_ENEMY_SLOTS)
    bob = r[93] - 4  # sharks float up and down around their lane
    for lane, bit, shark_slot, sub_slot, dx, y in _ENEMY_SLOTS:
        x = (r[30 + lane] + dx) % 256
        if r[36 + lane] & bit and x <= 165:  # x >= 0 >= -5 always
            if 3 < r[89 + lane] % 8 < 7:  # a lane of submarines
                kind, slot, other = Submarine, sub_slot, objects[shark_slot]
            else:
                kind, slot, other, y = Shark, shark_slot, objects[sub_slot], y + bob
            _place(objects, slot, kind, x, y)
            if other.__class__ is not NoObject and other._visible:  # left where it was (OCAtari's quirk)
                other._prev_xy = other._xy
        else:  # both slots empty
            o = objects[shark_slot]
            if o.__class__ is not NoObject or o._prev_xy is not None:
                objects[shark_slot] = NoObject()
            o = objects[sub_slot]
            if o.__class__ is not NoObject or o._prev_xy is not None:
                objects[sub_slot] = NoObject()

    # divers (slots 25-28) and enemy missiles (29-32) share a byte per lane, bottom lane first: the lane's
    # submarines' missile, or its diver; the slot of the other kind empties when this one is on screen, and keeps
    # what it holds, where it was, when not (OCAtari's quirk)
    for byte, lane, diver_slot, missile_slot, y in _DIVER_SLOTS:
        x = r[byte]
        if 3 < r[89 + lane] % 8 < 7:
            kind, slot, other_slot, x, y = EnemyMissile, missile_slot, diver_slot, x + 3, y + 4
        else:
            kind, slot, other_slot = Diver, diver_slot, missile_slot
        if 0 < r[byte] < 160:
            _place(objects, slot, kind, x, y)
            o = objects[other_slot]
            if o.__class__ is not NoObject or o._prev_xy is not None:
                objects[other_slot] = NoObject()
        else:
            o = objects[slot]
            if o.__class__ is not NoObject or o._prev_xy is not None:
                objects[slot] = NoObject()
            stale = objects[other_slot]
            if stale.__class__ is not NoObject and stale._visible:
                stale._prev_xy = stale._xy

    # the surface patrol (slot 33), only in later waves
    patrol = objects[33]
    if r[60] >= 2 and r[118] < 160:
        if patrol.__class__ is NoObject:
            patrol = objects[33] = SurfaceSubmarine()
        elif patrol._visible:
            patrol._prev_xy = patrol._xy
        patrol._xy = r[118], 45
    elif patrol.__class__ is not NoObject or patrol._prev_xy is not None:
        objects[33] = NoObject()

    # the player's torpedo (slot 34)
    torpedo = objects[34]
    if 0 < r[103] < 160:
        if torpedo.__class__ is NoObject:
            torpedo = objects[34] = PlayerMissile()
        elif torpedo._visible:
            torpedo._prev_xy = torpedo._xy
        torpedo._xy = r[103], r[97] + 40
    elif torpedo.__class__ is not NoObject or torpedo._prev_xy is not None:
        objects[34] = NoObject()

    # the oxygen bar (slot 35): a ValueObject, whose previous value is saved with its position
    bar = objects[35]
    oxygen = r[102]
    if oxygen != 0:
        if bar.__class__ is not OxygenBar:
            bar = objects[35] = OxygenBar()
        elif bar._visible:
            bar._prev_xy = bar._xy
            bar._prev_value = bar._value
        bar.wh = min(oxygen, 63), 5
        bar._value = oxygen
    elif bar.__class__ is not NoObject or bar._prev_xy is not None or bar.nslen != 1:
        objects[35] = NoObject(nslen=1)

    # the collected divers' icons (slots 36-41)
    collected = r[62]
    for i in range(6):
        icon = objects[36 + i]
        if i < collected:
            if icon.__class__ is CollectedDiver:
                if icon._visible:
                    icon._prev_xy = icon._xy
            else:
                icon = objects[36 + i] = CollectedDiver()
                icon._xy = 58 + i * 8, 178
        elif icon.__class__ is not NoObject or icon._prev_xy is not None:
            objects[36 + i] = NoObject()
