"""Generic games: every Atari game that both ALE ships and OCAtari reads from RAM, played without curation.

A generic game's observation is OCAtari's objects by category, numbered densely as in Space Invaders
(``Enemy0``, ``Enemy1``, ...; a category with one slot is keyed by its name), its actions are ALE's minimal
action set, and its task is plain: score as much as possible, a 100-step training rollout, a 4000-step
evaluation, feedback that names the score. ``codearcade new POLICY.py --game riverraid`` writes a scaffold
for one; curating a game means giving it a module of its own (see ``games/pong.py``).

Names are ALE's ROM ids (``riverraid``, ``ms_pacman``, ``bank_heist``); any spelling that differs only in
case, ``-`` or ``_`` is accepted.
"""

from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path

from games.base import Game, Task, normalize_name

GENERIC_ROLLOUT_STEPS = 100
"""The authors' default training horizon for the games they added."""
GENERIC_EVAL_MAX_STEPS = 4000
GENERIC_FEEDBACK = {
    "high": 1e9,  # no score is known to be "high" for a game nobody has curated: the medium text always applies
    "low": 0,
    "target": 1e9,
    "messages": {
        "medium": "Score {score:g}. Find what earns the most points in this game and do more of it, and avoid "
                  "what loses lives or ends the game.",
        "low": "Score {score:g}: the policy earns nothing yet. Find out from the trace which objects matter "
               "and what earns points, and act on them.",
    },
}


BROKEN_EXTRACTORS = {
    "adventure": "OCAtari's RAM extractor for it lacks MAX_NB_OBJECTS_HUD",
    "air_raid": "OCAtari's RAM extractor for it indexes a list with a numpy bool",
    "miniature_golf": "OCAtari has no RAM extractor for it (no init_objects)",
    "road_runner": "OCAtari's RAM extractor for it refers to an undefined BirdSeeds class",
    "time_pilot": "OCAtari's RAM extractor for it overruns its object list within 300 steps",
}
"""Games whose OCAtari 2.2.1 RAM extractor fails (found by playing 300 steps of every game): refused by name, with
the reason as a whole clause (the error is ``{game} cannot be played: {reason}``)."""


class BrokenGameError(ValueError):
    """A game OCAtari lists but cannot read; the message says why."""


@lru_cache(maxsize=1)
def _ocatari_games() -> frozenset[str]:
    """OCAtari's RAM extractor modules (found on disk: importing ocatari here would cost a second)."""
    spec = importlib.util.find_spec("ocatari")
    folders = list(spec.submodule_search_locations or []) if spec is not None else []
    return frozenset(p.stem for folder in folders for p in (Path(folder) / "ram").glob("*.py")
                     if not p.stem.startswith("_") and p.stem not in ("extract_ram_info", "game_objects", "utils"))


@lru_cache(maxsize=1)
def _rom_ids() -> dict[str, str]:
    """ALE's ROM ids by their normalized name."""
    from ale_py import roms

    return {normalize_name(rom): rom for rom in roms.get_all_rom_ids()}


def generic_names() -> list[str]:
    """Every game that can be played generically (curated ones included), by ROM id."""
    return sorted(rom for key, rom in _rom_ids().items() if key in _ocatari_games() and rom not in BROKEN_EXTRACTORS)


@lru_cache(maxsize=None)
def generic_game(name: str) -> Game | None:
    """The generic :class:`Game` for ``name``, or None when ALE or OCAtari does not know it."""
    key = normalize_name(name)
    rom = _rom_ids().get(key)
    if rom is None or key not in _ocatari_games():
        return None
    if rom in BROKEN_EXTRACTORS:
        raise BrokenGameError(f"{rom} cannot be played: {BROKEN_EXTRACTORS[rom]}")
    actions, lives = _ale_facts(rom)
    title = rom_title(rom)
    instruction = (f"You play Atari {title}. Improve the trainable methods so the policy scores as many points "
                   f"as possible" + (" without losing lives." if lives else "."))
    return Game(
        name=rom,
        env_id=_env_id(title),
        ocatari_name=title,
        actions=actions,
        lives=lives,
        task=Task(instruction=instruction, rollout_steps=GENERIC_ROLLOUT_STEPS,
                  eval_max_steps=GENERIC_EVAL_MAX_STEPS, feedback=GENERIC_FEEDBACK),
        status="generic",
    )


def rom_title(rom: str) -> str:
    """``MsPacman`` for ``ms_pacman``: a game's name as OCAtari and ALE's ids spell it (and ``games.envs.gym_id``)."""
    return "".join(part.capitalize() for part in rom.split("_"))


def _env_id(title: str) -> str:
    """``{Title}NoFrameskip-v4`` where Gymnasium registers it, else ALE's ``ALE/{Title}-v5`` (the newer ROMs):
    the environment is made with frameskip 4 and the sticky probability set explicitly either way."""
    import ale_py
    import gymnasium as gym

    gym.register_envs(ale_py)
    legacy = f"{title}NoFrameskip-v4"
    return legacy if legacy in gym.registry else f"ALE/{title}-v5"


def _ale_facts(rom: str) -> tuple[tuple[str, ...], int]:
    """The minimal action set's meanings and the lives at the start: as ``games/_generic_facts.py`` has them for the
    ale-py it was written with (loading a ROM takes ~0.1 s: ``codearcade games`` lists ~50), else from the ROM."""
    import ale_py

    from games._generic_facts import ALE_PY, FACTS

    if ale_py.__version__ == ALE_PY and rom in FACTS:
        return FACTS[rom]
    return read_ale_facts(rom)


def read_ale_facts(rom: str) -> tuple[tuple[str, ...], int]:
    """The minimal action set's meanings and the lives at the start, read from the ROM itself."""
    import ale_py
    from ale_py import roms

    ale_py.ALEInterface.setLoggerMode(ale_py.LoggerMode.Error)
    ale = ale_py.ALEInterface()
    ale.loadROM(roms.get_rom_path(rom))
    return tuple(action.name for action in ale.getMinimalActionSet()), int(ale.lives())


def write_facts(path: Path = Path(__file__).with_name("_generic_facts.py")) -> None:
    """Write ``games/_generic_facts.py`` from the ROMs of the installed ale-py (after upgrading it)."""
    import pprint

    import ale_py

    facts = pprint.pformat({rom: read_ale_facts(rom) for rom in generic_names()}, width=110, compact=True)
    path.write_text(f"{FACTS_HEADER}ALE_PY = {ale_py.__version__!r}\nFACTS = {facts}\n")


FACTS_HEADER = '''"""ALE's facts of every generic game: its minimal action set's meanings and its lives at the start, as the ROMs of
ale-py ``ALE_PY`` give them. ``codearcade games`` lists every generic game, and reading each ROM took ~0.1 s (5 s in
all); with another ale-py the ROMs are read again (``games.generic._ale_facts``). Written by
``games.generic.write_facts()``; ``tests/test_games.py`` checks every entry against its ROM.
"""

'''
