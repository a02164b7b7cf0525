"""The games codearcade plays: a registry of :class:`~games.base.Game` modules, curated and generic.

- **Curated games** are modules of this package (``games/pong.py``, ``games/breakout.py``, ...), each defining
  ``GAME = Game(...)`` with the authors' observation conventions, task and colours, and a policy scaffold in
  ``games/scaffolds/``. They are found by listing the package, so adding a game is adding its module and its
  scaffold. Games from elsewhere register the same way: a module named in ``CODEARCADE_GAME_MODULES``
  (comma-separated import names) or in the ``codearcade.games`` entry-point group.
- **Generic games** are every other game OCAtari reads from RAM (``riverraid``, ``ms_pacman``, ...): objects by
  category, numbered as in Space Invaders, action meanings from ALE (``games/generic.py``).

This package is the ground floor: it imports nothing from ``pipeline``, ``store``, ``tracing`` or ``viewers``,
and nothing outside it branches on a game's name.
"""

from __future__ import annotations

import difflib
import importlib
import os
import pkgutil
import reprlib
from functools import lru_cache

from games import lean_ocatari
from games.base import Game, Task, normalize_name

lean_ocatari.install()  # before anything imports OCAtari: its vision mode's plotting imports are not paid

__all__ = ["Game", "Task", "GAMES", "UnknownGameError", "get_game", "curated_games", "list_widths", "normalize_name"]

_NOT_GAMES = frozenset({"base", "envs", "generic", "lean_ocatari", "readers", "scaffolding", "spaces", "wrappers"})
"""Modules of this package that are machinery, not games."""

GAME_MODULES_VARIABLE = "CODEARCADE_GAME_MODULES"


class UnknownGameError(ValueError):
    """A game name that codearcade does not know (or cannot play); the message lists the known ones."""


def _module_names() -> list[str]:
    names = [f"games.{m.name}" for m in pkgutil.iter_modules(__path__)
             if not m.name.startswith("_") and m.name not in _NOT_GAMES]
    names += [n.strip() for n in os.environ.get(GAME_MODULES_VARIABLE, "").split(",") if n.strip()]
    try:
        from importlib.metadata import entry_points

        names += [ep.value for ep in entry_points(group="codearcade.games")]
    except Exception:  # noqa: BLE001 - broken package metadata must not hide the built-in games
        pass
    return names


@lru_cache(maxsize=None)
def curated_games() -> dict[str, Game]:
    """Every game module's ``GAME``, by name (the built-in ones first, in name order)."""
    found: dict[str, Game] = {}
    for module_name in _module_names():
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise UnknownGameError(f"game module '{module_name}' (from {GAME_MODULES_VARIABLE} or an entry point) "
                                   f"cannot be imported: {exc}") from None
        game = getattr(module, "GAME", None)
        if not isinstance(game, Game):
            raise UnknownGameError(f"game module '{module_name}' defines no GAME = games.Game(...)")
        found[game.name] = game
    return found


GAMES: dict[str, Game] = curated_games()
"""The curated games by name (game modules import only ``games.base``, so loading them all is cheap)."""


def get_game(name: str | Game) -> Game:
    """The game called ``name`` (any spelling: ``SpaceInvaders``, ``space-invaders``): a curated one, else
    a generic one for any game OCAtari reads from RAM; :class:`UnknownGameError` lists the choices."""
    if isinstance(name, Game):
        return name
    key = normalize_name(name)
    for game in GAMES.values():
        if normalize_name(game.name) == key:
            return game
    from games.generic import generic_game, generic_names

    try:
        game = generic_game(key)
    except ValueError as exc:  # a game OCAtari lists but cannot read
        raise UnknownGameError(str(exc)) from None
    if game is not None:
        return game
    candidates = list(GAMES) + generic_names()
    close = difflib.get_close_matches(name.strip().lower(), candidates, n=1)
    hint = f" Did you mean '{close[0]}'?" if close else ""
    # the name as Python writes it (cut): a terminal-safe copy of "pong\x1b[2J" said "unknown game 'pong'"
    raise UnknownGameError(f"unknown game {reprlib.repr(name)}; curated games: {', '.join(GAMES)}; any other game "
                           f"OCAtari reads is played generically (`codearcade games` lists them all).{hint}")


def list_widths(game: str | Game) -> dict[str, int]:
    """Observation keys whose value is always a list, even when empty, with the width of its items
    (Breakout's brick rows: 8 px). The step log stores runs of adjacent items as one object (tracing/steps.py)."""
    return dict(get_game(game).list_widths)
