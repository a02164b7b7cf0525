"""``codearcade new POLICY.py --game G``: a policy scaffold for any game.

A curated game's scaffold is its file in ``games/scaffolds/``. For any other game one is written from what
the game shows: its object categories, found by playing :data:`SURVEY_STEPS` random steps (with the most
objects of each category seen at once and their screen ranges), and its action meanings from ALE. The
scaffold has one trainable method that picks a random legal action: a starting point that plays, for the
optimizer (or a person) to improve.
"""

from __future__ import annotations

import random
import re
import textwrap
from dataclasses import dataclass, field

from games import Game, get_game

SURVEY_STEPS = 400
"""Random steps played to see which objects a game shows."""


@dataclass
class CategorySurvey:
    """What a survey saw of one object category."""

    count: int = 0
    """Most objects of the category on screen at once."""
    keys: set[str] = field(default_factory=set)
    x: tuple[int, int] = (10_000, -10_000)
    y: tuple[int, int] = (10_000, -10_000)

    def see(self, key: str, obj: dict) -> None:
        self.keys.add(key)
        self.x = (min(self.x[0], obj["x"]), max(self.x[1], obj["x"]))
        self.y = (min(self.y[0], obj["y"]), max(self.y[1], obj["y"]))


def survey(game: Game, steps: int = SURVEY_STEPS, seed: int = 0) -> dict[str, CategorySurvey]:
    """Play ``steps`` random steps of ``game`` and report the object categories it showed."""
    from games.envs import make_env

    env = make_env(game)
    rng = random.Random(seed)
    seen: dict[str, CategorySurvey] = {}
    try:
        obs, _ = env.reset(seed=seed)
        for _ in range(steps):
            counts: dict[str, int] = {}
            for key, value in obs.items():
                for item in (value if isinstance(value, list) else [value]):
                    if isinstance(item, dict) and "x" in item:
                        category = key.rstrip("0123456789") or key
                        counts[category] = counts.get(category, 0) + 1
                        seen.setdefault(category, CategorySurvey()).see(key, item)
            for category, n in counts.items():
                seen[category].count = max(seen[category].count, n)
            obs, _, terminated, truncated, _ = env.step(rng.randrange(game.n_actions))
            if terminated or truncated:
                obs, _ = env.reset()
    finally:
        env.close()
    return dict(sorted(seen.items()))


_PLAIN_NAME = re.compile(r"[\w./+-]+")
"""A file name that reads the same inside a docstring and at a shell prompt."""


def scaffold_text(game: str | Game, steps: int = SURVEY_STEPS, path: str | None = None) -> str:
    """The text of a policy file for ``game``: the curated scaffold, or one written from a survey. ``path``: the
    file's name as the person typed it, which the commands in its docstring then name (the copy of a curated
    scaffold named its original, a surveyed one ``THIS_FILE``); a name that could not sit in a docstring as it is
    (quotes, backslashes, a line break) leaves them naming ``POLICY.py``."""
    spec = get_game(game)
    named = path if path is not None and _PLAIN_NAME.fullmatch(path) else "POLICY.py"
    if spec.scaffold is not None:
        text = spec.scaffold.read_text()
        return text if path is None else text.replace(f"games/scaffolds/{spec.scaffold.name}", named)
    categories = survey(spec, steps)
    lines = []
    for category, s in categories.items():
        keys = f"``{category}``" if s.count <= 1 and category in s.keys else \
            f"``{category}0`` .. ``{category}{max(s.count - 1, 0)}``"
        lines.append(f"    - {keys}: up to {s.count} on screen, x {s.x[0]}..{s.x[1]}, y {s.y[0]}..{s.y[1]}")
    objects = "\n".join(lines) or "    (no objects appeared in the survey)"
    actions = "\n".join(textwrap.wrap(", ".join(f"{i} {name}" for i, name in enumerate(spec.actions)) + ".",
                                      100, initial_indent=" " * 12, subsequent_indent=" " * 12))
    lives = f"The game starts with {spec.lives} lives." if spec.lives else "The game has no lives."
    title = spec.env_id.split("NoFrameskip")[0]
    return f'''"""{title}: a policy scaffold written by `codearcade new` from {steps} random steps of the game.

Improve it with ``codearcade optimize {named}``; evaluate it with ``codearcade eval {named}``.
"""

import random

import tracing as trace

GAME = "{spec.name}"


@trace.model
class Policy(trace.Module):
    """{title} policy.

    Observation ``obs`` is a dict of the objects on screen; each maps to ``{{x, y, w, h, dx, dy}}`` (top-left
    corner, size, movement since the previous step; y grows downward; the screen is 160 x 210). A category with
    several objects is numbered from 0 in screen-slot order. Objects seen in the survey:
{objects}
    A key is missing when its object is not on screen. {lives}
    """

    def __call__(self, obs):
        return self.select_action(obs)

    @trace.bundle(trainable=True)
    def select_action(self, obs):
        """Choose the next action from the observation.

        Actions:
{actions}

        Args:
            obs (dict): the observation (see the class docstring).
        Returns:
            int: an action between 0 and {spec.n_actions - 1}.
        """
        return random.randrange({spec.n_actions})
'''
