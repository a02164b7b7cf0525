"""OCAtari's Pong reader (:func:`detect_pong`, the game's ``Game.detect``) on the RAM as Python ints, with the
``NoObject`` it makes anew every step kept instead when a fresh one would be equal.

OCAtari 2.2.1's ``ocatari.ram.pong._detect_objects_ram`` reads the ball (RAM 49, 54), the enemy's paddle (50) and the
player's (51) on NumPy scalars, and puts a new ``NoObject`` in the ball's and the enemy's slot at every step either is
absent (the ball between points: a third of a game). A new ``NoObject`` differs from the one already there only if
the environment's first observation gave that one a previous position, so :func:`detect_pong` keeps a ``NoObject``
whose previous position is still ``None``. The rest is OCAtari's code line for line, its sizes as ints (OCAtari's
are NumPy ints of the same values).
"""

from __future__ import annotations

import numpy as np
from ocatari.ram.game_objects import NoObject

from games.readers import empty_slot

_PONG: tuple = ()
"""OCAtari's Pong classes (Ball, Enemy), imported on first use."""


def detect_pong(objects: list, ram: np.ndarray) -> None:
    """``extract_ram_info.detect_objects_ram(objects, ram.astype(np.int64), "Pong", False)``, exactly (see the
    module docstring); ``ram`` as ALE gives it (uint8)."""
    global _PONG
    if not _PONG:
        from ocatari.ram import pong

        _PONG = (pong.Ball, pong.Enemy)
    Ball, Enemy = _PONG
    ball_x, enemy_y, player_y, ball_y = int(ram[49]), int(ram[50]), int(ram[51]), int(ram[54])
    # ``o.__class__ is not NoObject and o._visible`` is ``bool(o)`` for these classes, without a Python call per object
    for obj in objects:  # saving the previous positions, as extract_ram_info.detect_objects_ram does
        if obj.__class__ is not NoObject and obj._visible:
            obj._prev_xy = obj._xy
    player, ball, enemy = objects[:3]
    if ball_y != 0 and ball_x > 49:  # otherwise no ball
        if not (ball.__class__ is not NoObject and ball._visible):
            ball = objects[1] = Ball()
        ball._xy = ball_x - 49, ball_y - 14  # the xy setter's int() of ints is a no-op
    else:
        empty_slot(objects, 1)
    if enemy_y > 33:  # OCAtari's test is ``> 18 and > 33``
        if not (enemy.__class__ is not NoObject and enemy._visible):
            enemy = objects[2] = Enemy()
        if enemy_y - 15 < 34:
            enemy._xy = 16, 34
            enemy.wh = 4, enemy_y - 33
        elif enemy_y > 194:
            enemy._xy = 16, enemy_y - 15
            enemy.wh = 4, 209 - enemy_y
        else:
            enemy._xy = 16, enemy_y - 15
            enemy.wh = 4, 15
    else:
        empty_slot(objects, 2)
    if player_y > 13:  # otherwise no player (its slot keeps the paddle where it was)
        if player_y < 47:
            player._xy = 140, 34
            player.wh = 4, player_y - 33
        elif player_y > 192:
            player._xy = 140, player_y - 13
            player.wh = 4, 207 - player_y
        else:
            player._xy = 140, player_y - 13
            player.wh = 4, 15
