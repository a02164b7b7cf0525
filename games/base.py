"""What a game is to codearcade: :class:`Game` (environment, observation hooks, actions, colours) and its
:class:`Task` (what the optimizer is told and how long it plays).

A game module (``games/pong.py``) defines one ``GAME = Game(...)``; everything codearcade knows about that
game is there, and every other package reads it from the registry (``games.get_game``). This module imports
nothing heavier than the standard library, so the registry loads in milliseconds.
"""

from __future__ import annotations

import importlib
import reprlib
import secrets
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping

STANDARD_STICKY = 0.25
STANDARD_NOOP_MAX = 30
"""The standard stochastic Atari protocol (Machado et al. 2018): sticky actions with probability 0.25 and up to
30 no-op starts. The paper's protocol is sticky 0, no no-op starts."""

AUDIT_SEED_BASE = 1_000_000
AUDIT_SEED_END = 2**31 - 1
"""The held-out audit's seeds (``codearcade audit``) are drawn, when an audit runs, from the OS's entropy over
``[AUDIT_SEED_BASE, AUDIT_SEED_END)``; tuning seeds (those the loop selects on: ``--seed`` and the seeds after it)
are below it, so the two sets never meet, no prompt ever shows an audit episode, and no policy can know the
audit's games in advance (they are recorded only with the episodes they produced)."""


def draw_audit_seeds(n: int) -> list[int]:
    """``n`` distinct audit seeds from the OS's entropy: nothing before the audit runs can know them."""
    return secrets.SystemRandom().sample(range(AUDIT_SEED_BASE, AUDIT_SEED_END), n)


ONE_LIFE_CONTINUE = "continue"
"""The ``one_life`` setting (``codearcade eval --one-life-continue``; ``OptimizeConfig.one_life``) that plays the
authors' one-life protocol exactly: the evaluation episodes of a run are the lives of one game, each continuing
where the one before ended (``games.wrappers.EpisodicLife``). The other values: ``False``, whole games (the paper's);
``True`` (``--one-life``), each episode the *first* life of a game reset from its own seed
(``games.wrappers.OneLife``)."""
ONE_LIFE_SETTINGS = (False, True, ONE_LIFE_CONTINUE)


def one_life_setting(value: Any) -> bool | str:
    """``value`` as a ``one_life`` setting (:data:`ONE_LIFE_SETTINGS`; ``"first"`` is ``True``), or ValueError in
    one line that names the choices."""
    if value == "first":
        return True
    if isinstance(value, bool) or value == ONE_LIFE_CONTINUE:
        return value
    raise ValueError(f"one_life must be false, true (--one-life: first lives) or {ONE_LIFE_CONTINUE!r} "
                     f"(--one-life-continue: the lives of one game), not {value!r}")


OBSERVATION_VERSION = 2
"""The version of the observation conventions codearcade builds today. A run records the version it played
(``config.observation``) and is read back and replayed with it, so that a stored run replays as it was made:

1. Breakout's bricks split into 8-pixel entries, each row always present (``[]`` when cleared); Seaquest's
   enemies grouped by type with ``SurfaceSubmarine`` before ``EnemyMissile``; Q*bert's ``Friendlies`` Sam first.
2. The authors' conventions (docs/observations.md): Breakout's bricks one entry per OCAtari ``Block`` (a run
   of adjacent bricks, ``w = 8 * n``), keys ``Player``, ``Ball``, the rows present only while they have
   bricks, and ``lives``; Seaquest's enemies and Q*bert's friendlies in OCAtari's slot order.
"""

UNRECORDED_OBSERVATION = 1
"""The version of a run whose config records none: every run stored before versions were recorded."""


def recorded_observation(config: Mapping[str, Any]) -> int:
    """The observation version a stored run's config (``runs.config``) says it played; ValueError in one line when
    it is no whole number (a store is anyone's file: ``int()`` of a list raised TypeError, of infinity
    OverflowError)."""
    version = config.get("observation", UNRECORDED_OBSERVATION)
    if not isinstance(version, int) or isinstance(version, bool):
        raise ValueError(f"observation must be a whole number (the version of the observation conventions the run "
                         f"played), not {reprlib.repr(version)}")
    return version


SCAFFOLDS = Path(__file__).resolve().parent / "scaffolds"
"""The curated games' policy scaffolds: ``scaffolds/<game>.py`` beside the game modules."""


def normalize_name(name: str) -> str:
    """``Space-Invaders``, ``SpaceInvaders`` and ``space_invaders`` all name ``spaceinvaders``: the one spelling
    rule of the registry (curated games) and of the generic games (ALE's ROM ids)."""
    return name.strip().lower().replace("-", "").replace("_", "").replace(" ", "")


@dataclass(frozen=True)
class Published:
    """A score the authors published for the game: the best-so-far evaluation return of their optimization runs
    (the mean over ``trials`` runs, with its standard error), under their protocol (sticky 0, their caps and
    episode counts; the follow-up ends an episode at a lost life where ``Task.one_life_episodes``). SQL reads
    them from the store's ``published_scores`` (``store/published.py``)."""

    source: str
    """``paper`` (Kuang et al. 2025, Table 1) or ``follow-up`` (arXiv 2603.23994, their repository's
    ``results/aggregated/all_games_aggregate.csv``, the last optimization step)."""
    setting: str
    """``paper``; or the follow-up's ``default`` (the paper's horizons), ``h1`` or ``h100`` (training horizon)."""
    score: float
    horizon: int
    """Training rollout steps of the setting."""
    trials: int = 1
    stderr: float | None = None
    """Standard error over the trials (None: one trial, or not published)."""


@dataclass(frozen=True)
class Task:
    """The optimization task of a game, as the paper and the authors' follow-up set it. A policy file may
    override each with an upper-case constant (``ROLLOUT_STEPS``, ``EVAL_MAX_STEPS``, ``FEEDBACK``,
    ``INSTRUCTION``)."""

    instruction: str
    """What the optimizer is asked to achieve."""
    rollout_steps: int
    """Horizon of the traced training rollout shown in the prompt (paper: Pong 400, Breakout 300, SI 15)."""
    eval_max_steps: int
    """Cap of an evaluation episode (paper: 4000)."""
    feedback: Mapping[str, Any]
    """Staged feedback bands: ``{"high": h, "low": l, "target": t, "messages": {"high"|"medium"|"low": text}}``;
    a score >= high is high, <= low is low; texts may use ``{score}``, ``{gap}`` and ``{target}``."""
    eval_episodes: int = 1
    """Evaluation episodes the authors average over (informational; ``--eval-episodes`` sets it for a run)."""
    one_life_episodes: bool = False
    """The authors' follow-up ends an episode at every lost life (their ``trace_envs/<game>.py`` implement
    baselines' ``EpisodicLifeEnv``) and goes on with the same game in the next: a "1 x 4,000" evaluation is the
    first life of a game, "3 x 20,000" lives 1-3 of one game. codearcade plays whole games unless asked for
    theirs: ``--one-life-continue`` exactly (``games.wrappers.EpisodicLife``), ``--one-life`` the first life of each
    of N seeded games (``games.wrappers.OneLife``)."""
    published: tuple[Published, ...] = ()
    """The authors' published scores for the game (``examples/benchmarks.sql`` sets a batch's beside them)."""


ObjectHook = Callable[[Any, dict, "list | None"], None]
"""``hook(ocatari_object, obs, rows)``: put one object of its category into the observation (and its step-log
rows into ``rows`` when given) instead of the generic ``{x, y, w, h, dx, dy}`` entry. ``None`` in its place leaves
the category's objects out (Q*bert's cubes)."""


@dataclass(frozen=True)
class Game:
    """One Atari game as codearcade plays it."""

    name: str
    """Short name on the command line and in the store (``pong``, ``space_invaders``)."""
    env_id: str
    """Gymnasium id in the paper's setting (``PongNoFrameskip-v4``); frameskip 4 and sticky actions are set
    explicitly when the environment is made."""
    ocatari_name: str
    """The game's name for OCAtari's RAM extractors (``Pong``, ``SpaceInvaders``)."""
    actions: tuple[str, ...]
    """ALE action meanings (the minimal action set); an action is legal when it indexes this tuple."""
    lives: int
    """Lives at the start of a game (0 when the game has none, as Pong)."""
    task: Task
    """The optimization task: instruction, horizons, feedback bands."""
    fire_on_life_loss: bool = False
    """Press FIRE after reset and after each lost life (Breakout does not relaunch the ball by itself)."""
    ball_in_play: Callable[[Any], bool] | None = None
    """``ball_in_play(ram)`` (with ``fire_on_life_loss``): whether a ball is in play, so that FIRE is pressed again
    when none has been for a while (``games.wrappers.ServeAgain``: sticky actions can swallow a press)."""
    colours: Mapping[str, tuple[int, int, int]] = field(default_factory=dict)
    """RGB of each object category's boxes in Rerun recordings (others get a colour from their name)."""
    list_widths: Mapping[str, int] = field(default_factory=dict)
    """Observation keys that are always present as lists of equal-width items, with that width (Breakout's
    8-pixel bricks under observation version 1); the step log stores runs of adjacent items as one object."""
    object_hooks: Mapping[str, ObjectHook | None] = field(default_factory=dict)
    """Per OCAtari category, how its objects enter the observation (Breakout files its brick runs by row), or
    ``None``: they do not (Q*bert's cubes)."""
    detect: Callable[[list, Any], None] | None = None
    """``detect(objects, ram)`` updates OCAtari's object list from a RAM snapshot (uint8, as ALE gives it) instead
    of OCAtari's own RAM extractor (run with int64 RAM); for a game whose extractor is wrong under numpy 2
    (Enduro) or slow (every other curated game: :func:`fast_reader`, ``games/readers/``), leaving the objects exactly
    as OCAtari's would."""
    derive: Callable[[dict, int], None] | None = None
    """``derive(obs, lives)`` adds fields computed from the objects (lanes, nearest enemies, ``lives``) to the
    observation, in place. The store keeps the objects and lives; the same call rebuilds the derived fields
    when a prompt or a viewer reads a step back, so they are never stored twice."""
    derive_space: Callable[[Any], None] | None = None
    """``derive_space(space)`` turns the generic observation space (a ``games.spaces.ObjectDict`` of OCAtari's
    categories) into this game's, in place, as ``object_hooks`` and ``derive`` turn the generic observation into
    it (required when either is given). Called when an environment is made; it imports ``games.spaces`` (and so
    Gymnasium) inside, so the registry stays light."""
    hot_keys: tuple[str, str | None] = ("Player", "Ball")
    """The observation keys of the player and of the ball (or what stands for it) whose x/y fill the ``steps``
    table's hot columns ``player_x/y`` and ``ball_x/y`` (Freeway's player is its ``Chicken``)."""
    action_moves: Mapping[int, str] = field(default_factory=dict)
    """What an action does on screen where ALE's name says otherwise (Pong's RIGHT moves the paddle up): shown
    beside the name where actions are printed for people (``compare``), so ``2 RIGHT (up)`` reads as the scaffold
    and its docstrings say it. The prompt keeps ALE's names, which the scaffolds' docstrings explain."""
    worst_return: float | None = None
    """The lowest return a whole game can give (Pong: -21, every point lost; 0 where no reward is negative);
    None when unknown. ``compare``'s sensitivity line counts a forfeited game at it (``store.scores.worst_return``:
    without one, the lowest return played out in the comparison, said so)."""
    restorable_reset: bool = False
    """Whether ALE's reset of this game (~64 frames played, ~4 ms) may be replaced by restoring the state it leads
    to (``games.envs.reload_from_snapshot``): only where the emulator keeps nothing outside ALE's saved state that a
    later frame reads, which is tested step by step against a real reset for every curated game. Q*bert's is not:
    after a restored reset its first steps run a frame apart (a counter in RAM byte 0). Off for generic games."""
    status: str = "curated"
    """``curated`` (a module with the authors' conventions and a scaffold) or ``generic`` (any OCAtari game)."""
    scaffold: Path | None = None
    """The policy scaffold the optimizer starts from; None for generic games (``codearcade new`` writes one)."""
    earlier_observations: Mapping[int, Mapping[str, Any]] = field(default_factory=dict)
    """How the observation of an earlier version (:data:`OBSERVATION_VERSION`) was built: per version, the
    values of the fields that differed (``object_hooks``, ``list_widths``, ``derive``). Version v is built with
    those of the smallest listed version >= v, or as today when none is listed."""
    observation: int = OBSERVATION_VERSION
    """The observation version this object builds (:meth:`observing` makes the others)."""

    def observing(self, version: int | None) -> "Game":
        """This game building the observation of ``version`` (None: today's), for a stored run to be read
        back and replayed as it was made."""
        if version is None or version == self.observation:
            return self
        if self.observation != OBSERVATION_VERSION:
            raise ValueError(f"{self.name} already builds observation version {self.observation}; "
                             "ask the registry's game (games.get_game) for another")
        if not 1 <= version <= OBSERVATION_VERSION:
            raise ValueError(f"observation version {version} is not one this codearcade builds "
                             f"(1..{OBSERVATION_VERSION}); a newer codearcade made the run: upgrade to read it")
        listed = [v for v in sorted(self.earlier_observations) if v >= version]
        if not listed:
            return self  # built the same way then as now
        return replace(self, observation=version, **self.earlier_observations[listed[0]])

    @property
    def n_actions(self) -> int:
        return len(self.actions)

    def check_one_life(self, one_life: bool | str) -> None:
        """ValueError in one line when ``one_life`` (a :func:`one_life_setting`) asks this game for the lives of
        one game and it has none: Pong's ``--one-life-continue`` played whole games past their step cap as
        "lives", with an interval over them. ``--one-life`` (the first life) is a whole game there, as without it
        (a batch may set it for every game)."""
        if one_life == ONE_LIFE_CONTINUE and not self.lives:
            raise ValueError(f"{self.name} has no lives: --one-life-continue (one_life = 'continue') plays the lives "
                             "of one game as its episodes; leave it out for this game")


NUMBERED_KEYS_MADE = 64
"""Numbered keys made at once per category (``Alien0`` .. ``Alien63``); further ones are made when asked."""
_NUMBERED_KEYS: dict[str, tuple[str, ...]] = {}


def numbered_keys(category: str) -> tuple[str, ...]:
    """``(category0, category1, ...)``, the first :data:`NUMBERED_KEYS_MADE` keys of a multi-slot category, made once
    per process: the observation is built and taken apart every step, an f-string per object added up."""
    keys = _NUMBERED_KEYS.get(category)
    if keys is None:
        keys = _NUMBERED_KEYS[category] = tuple(f"{category}{i}" for i in range(NUMBERED_KEYS_MADE))
    return keys


def pop_numbered(obs: dict, category: str) -> list[dict]:
    """Remove ``category0, category1, ...`` (a multi-slot category's objects, numbered densely in OCAtari's slot
    order by the generic observation) from ``obs`` and return them in that order; a helper for ``derive``."""
    items = []
    pop = obs.pop
    for key in numbered_keys(category):
        item = pop(key, None)
        if item is None:
            return items
        items.append(item)
    i = len(items)
    while True:
        item = pop(f"{category}{i}", None)
        if item is None:
            return items
        items.append(item)
        i += 1


def fast_reader(name: str) -> Callable[[list, Any], None]:
    """The ``Game.detect`` of a game whose OCAtari reader is redone in ``games/readers/<name>.py``: its
    ``detect_<name>(objects, ram)``, which leaves OCAtari's object list exactly as OCAtari's own reader would, faster.
    Imported on the first call, not with the game's module (the registry imports every game module and must stay
    light), and kept: an import statement in every call cost ~0.5 µs a step."""
    loaded: list[Callable[[list, Any], None]] = []

    def detect(objects: list, ram: Any) -> None:
        if not loaded:
            loaded.append(getattr(importlib.import_module(f"games.readers.{name}"), f"detect_{name}"))
        loaded[0](objects, ram)

    detect.__qualname__ = detect.__name__ = f"detect_{name}"
    return detect
