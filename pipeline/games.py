"""The games codearcade knows, with the facts of the environment that every other module relies on.

A game is named on the command line by its short name (``pong``, ``breakout``, ``space_invaders``). This
module maps that name to the ALE environment id of the paper's setting (``{Game}NoFrameskip-v4``), the
OCAtari module that reads its objects from RAM, and its action meanings. Task settings (rollout horizon,
evaluation cap, feedback bands, instructions) live with the policy scaffolds in ``examples/``.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass


@dataclass(frozen=True)
class GameSpec:
    """One Atari game as codearcade plays it."""

    name: str
    """Short name used on the command line and in the store (``pong``)."""
    env_id: str
    """Gymnasium id of the paper's setting; frameskip and sticky actions are set explicitly at make time."""
    ocatari_name: str
    """Module name of the game inside ``ocatari.ram``'s object extractors."""
    actions: tuple[str, ...]
    """ALE action meanings; an action is legal when it indexes this tuple."""
    lives: int
    """Lives at the start of a game (0 when the game has no lives, as Pong)."""
    fire_on_life_loss: bool = False
    """Press FIRE after reset and after each lost life (Breakout does not relaunch the ball by itself)."""

    @property
    def n_actions(self) -> int:
        return len(self.actions)


GAMES: dict[str, GameSpec] = {
    spec.name: spec
    for spec in (
        GameSpec(
            name="pong",
            env_id="PongNoFrameskip-v4",
            ocatari_name="Pong",
            actions=("NOOP", "FIRE", "RIGHT", "LEFT", "RIGHTFIRE", "LEFTFIRE"),
            lives=0,
        ),
        GameSpec(
            name="breakout",
            env_id="BreakoutNoFrameskip-v4",
            ocatari_name="Breakout",
            actions=("NOOP", "FIRE", "RIGHT", "LEFT"),
            lives=5,
            fire_on_life_loss=True,
        ),
        GameSpec(
            name="space_invaders",
            env_id="SpaceInvadersNoFrameskip-v4",
            ocatari_name="SpaceInvaders",
            actions=("NOOP", "FIRE", "RIGHT", "LEFT", "RIGHTFIRE", "LEFTFIRE"),
            lives=3,
        ),
    )
}


class UnknownGameError(ValueError):
    """A game name that codearcade does not know; the message lists the known ones."""


def get_game(name: str) -> GameSpec:
    """Return the spec for ``name``, accepting ``SpaceInvaders``/``space-invaders`` spellings too."""
    key = name.strip().lower().replace("-", "_").replace(" ", "_")
    key = {"spaceinvaders": "space_invaders"}.get(key, key)
    if key in GAMES:
        return GAMES[key]
    close = difflib.get_close_matches(key, GAMES, n=1)
    hint = f" Did you mean '{close[0]}'?" if close else ""
    raise UnknownGameError(f"unknown game '{name}'; known games: {', '.join(GAMES)}.{hint}")
