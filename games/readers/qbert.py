"""OCAtari's Q*bert reader (:func:`detect_qbert`, the game's ``Game.detect``) line for line on the RAM as Python
ints, with its loops replaced by what they compute.

OCAtari 2.2.1's ``ocatari.ram.qbert._detect_objects_ram`` keeps state between calls in its module's globals (Coily's
previous position, the steps of the green ball, the purple ball and Sam down the pyramid, the last values of a
few RAM bytes), which ``init_objects`` resets. :func:`detect_qbert` reads and writes those same globals (ints
where OCAtari stores NumPy scalars of the same values), so that state is OCAtari's whatever else the process does
with Q*bert lists. What it does differently, for the same result:

- every operation on Python ints instead of NumPy scalars (the int64 RAM OCAtari needs under numpy 2 gives the
  same values: nothing here leaves -52..7,700);
- ``_calc_enemy_x`` (a loop of up to 256 additions, up to four calls a step) is a table made from it on first use;
- the 21 cubes' colours are set only when their RAM bytes differ from the previous call's on the same object list
  (else they already hold those colours: the reader never replaces a cube; a list is updated by one reader, the
  environment's);
- attributes written directly where OCAtari's setters only store them (``xy`` converts with ``int()``: these are
  ints already).

Its quirks stay: the ``None`` s in empty slots, the local ``player`` still used for the collision tests after its
slot was emptied, a green ball or Sam caught by Q*bert placed from RAM[74] (index -1), Sam's object still moved
after the green ball emptied its slot.
"""

from __future__ import annotations

from operator import itemgetter

import numpy as np

_QBERT: tuple = ()
"""OCAtari's Q*bert module, its classes, its colour table and the table of ``_calc_enemy_x``, made on first use."""
_last: list = [None, ()]
"""The object list of the previous call and its cubes' 21 RAM bytes."""


def _setup() -> tuple:
    from ocatari.ram import qbert
    from ocatari.ram.utils import _color_conversion

    enemy_x = tuple(qbert._calc_enemy_x(value) for value in range(256))
    cubes = itemgetter(*qbert._cubes_cinfo)
    disks = tuple(zip((22, 23), (112, 122), (tuple(p) for p in qbert._diskposes)))
    return (qbert, qbert.Player, qbert.Disk, qbert.Coily, qbert.PurpleBall, qbert.GreenBall, qbert.Sam,
            _color_conversion, enemy_x, cubes, disks)


def _place_ball(ball, x: int, row: int, low: bool) -> None:
    """A ball's box on ``row`` (0-4) of the pyramid, low (squashed, on the cube) or in the air: OCAtari's."""
    if low:
        ball._xy, ball.wh = (x + 1, (row + 1) * 30 + 23 - row), (7, 6)
    else:
        ball._xy, ball.wh = (x + 1, (row + 1) * 30 + 9 - row), (7, 9)


def detect_qbert(objects: list, ram: np.ndarray) -> None:
    """``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "Qbert", False)``, exactly (see the
    module docstring); ``ram`` as ALE gives it (uint8)."""
    global _QBERT
    if not _QBERT:
        _QBERT = _setup()
    q, Player, Disk, Coily, PurpleBall, GreenBall, Sam, colours, enemy_x, cube_bytes, disks = _QBERT
    r = ram.tolist()
    # Q*bert's lists hold its own classes or None (never a NoObject): ``bool(o)`` is ``o is not None and o._visible``
    for obj in objects:  # saving the previous positions, as extract_ram_info.detect_objects_ram does
        if obj is not None and obj._visible:
            obj._prev_xy = obj._xy
    shades = cube_bytes(r)
    if _last[0] is not objects or _last[1] != shades:
        for cube, shade in zip(objects[1:22], shades):
            cube._rgb = colours[shade // 2]
        _last[0], _last[1] = objects, shades
    player = objects[0]
    y = r[67]
    if 16 < y < 210:
        if player is None:
            player = objects[0] = Player()
        if r[59] == 255:  # falling
            player._xy = player._xy[0], r[33] - 52
        elif y < 70:
            player._xy = r[43] - 3, y - 8
        elif y < 100:
            player._xy = r[43] - 3, y - 7
        else:
            player._xy = r[43] - 3, y - 6
    else:
        objects[0] = None
    for slot, byte, position in disks:
        if r[byte] == 0:
            if objects[slot] is not None:
                objects[slot] = None
        else:
            if objects[slot] is None:
                disk = objects[slot] = Disk()
                disk._xy = position
            objects[slot]._rgb = colours[r[byte] // 2]

    coily = objects[24]
    row = r[39]
    if row != 255:
        if coily is None:
            coily = objects[24] = Coily()
        # OCAtari moves Coily sideways only when its row changes (the x byte switches too early)
        x = enemy_x[r[71]] if q.coil_prev_y != row else q.coil_prev_x
        timer = r[56]
        if timer > 8:
            coily._xy, coily.wh = (x, row * 30 + 6), (8, 21)
        elif timer > 6:
            coily._xy, coily.wh = (x, row * 30 + 9), (8, 18)
        elif timer > 3:
            coily._xy, coily.wh = (x, row * 30 + 11), (8, 16)
        elif timer == 1:
            coily._xy, coily.wh = (x, row * 30 + 6), (8, 21)
        else:
            coily._xy, coily.wh = (x, row * 30 + 9), (8, 18)
        q.coil_prev_x = x
        q.coil_prev_y = row
    else:
        objects[24] = None
        q.coil_prev_x = 0
        q.coil_prev_y = 0

    last_lives, last_74, last_103, last_105, last_i, purple_i, green_i = (
        q.last_lives, q.last_74, q.last_103, q.last_105, q.last_i, q.purple_i, q.green_i)
    purple_ball, green_ball, sam = objects[25], objects[26], objects[27]
    if last_lives != r[8]:
        green_i = purple_i = last_i = -1
        last_lives = r[8]
        last_74 = r[74]
        objects[25] = objects[26] = objects[27] = None
    elif r[74]:
        if last_74 != r[74]:  # the balls and Sam went one row down
            last_74 = r[74]
            if last_i >= 0:
                last_i += 1
            if purple_i >= 0:
                purple_i += 1
            if green_i >= 0:
                green_i += 1

        if last_103 != r[103]:
            if r[103] == 17:
                green_i = 0
            last_103 = r[103]
        elif green_i > 4:
            green_i = -1
        if 0 <= green_i < 5:
            if green_ball is None:
                green_ball = objects[26] = GreenBall()
            if player is not None:
                b_x, b_y = enemy_x[r[75 + green_i]], (green_i + 1) * 30 + 7 - green_i
                p_x, p_y = player._xy
                if -9 < b_x - p_x < 9 and -9 < b_y - p_y < 9:  # caught: OCAtari empties Sam's slot
                    objects[27] = None
                    green_i = -1
            _place_ball(green_ball, enemy_x[r[75 + green_i]], green_i, r[56] < 7)
        else:
            objects[26] = None

        if r[119] != 0:
            objects[25] = None
            purple_i = -1
        elif purple_i < 0 and objects[24] is None:
            purple_i = 0
        elif purple_i > 4:
            purple_i = -1
        if 0 <= purple_i < 5:
            if green_i != purple_i:
                if purple_ball is None:
                    purple_ball = objects[25] = PurpleBall()
                _place_ball(purple_ball, enemy_x[r[75 + purple_i]], purple_i, r[56] < 7)
            else:
                purple_i = -1
        else:
            objects[25] = None

        if last_105 != r[105]:
            if r[105] == 6:
                last_i = 0
            last_105 = r[105]
        if 0 <= last_i < 5:
            if sam is None:
                sam = objects[27] = Sam()
            if player is not None:
                s_x, s_y = enemy_x[r[75 + last_i]], (last_i + 1) * 30 + 12 - last_i
                p_x, p_y = player._xy
                if -7 < s_x - p_x < 7 and -7 < s_y - p_y < 7:
                    objects[27] = None
                    last_i = -1
            sam._xy = enemy_x[r[75 + last_i]], (last_i + 1) * 30 + 12 - last_i
        else:
            objects[27] = None
        if last_i > 4:
            last_i = -1
    q.last_lives, q.last_74, q.last_103, q.last_105, q.last_i, q.purple_i, q.green_i = (
        last_lives, last_74, last_103, last_105, last_i, purple_i, green_i)
