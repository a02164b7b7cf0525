"""Atari environments in the paper's setting, with object-centric dict observations.

``make_env("pong")`` builds ``PongNoFrameskip-v4`` with frameskip 4 and sticky-action probability 0.0 (the
paper's protocol; ``sticky=0.25, noop_max=30`` gives the standard stochastic Atari protocol) and wraps it with
the protocol's wrappers (``games/wrappers.py``, one concern each):

- ``NoopReset`` takes a random number of NOOPs after reset (standard protocol only);
- ``AutoFire`` presses FIRE after reset and after every lost life (Breakout);
- ``ServeAgain`` presses it again when sticky actions swallowed the press (no ball in play for 30 steps);
- ``OneLife`` ends the episode at the first lost life (``one_life=True``: the first life of a seeded game);
- ``EpisodicLife`` is the authors' one-life protocol exactly (``one_life="continue"``): an episode ends at
  a lost life and the next ``reset()`` goes on with the same game (see its docstring);

and with this module's :class:`ObjectObservation`, which replaces the pixel observation by a plain dict of game
objects read from RAM by OCAtari's extractors; its ``observation_space`` holds exactly those dicts
(``games/spaces.py``).

Importing this module registers every game with Gymnasium as ``codearcade/<Game>-v0`` (:func:`register_envs`),
so ``gymnasium.make("codearcade/Pong-v0", sticky=0.25, noop_max=30)`` builds the same environment.

Observation conventions (the paper's): every object is ``{"x", "y", "w", "h", "dx", "dy"}`` (ints; dx/dy
are the movement since the previous agent step, 0 when an object (re)appears). Categories with one object
are keyed by name (``Player``, ``Ball``, ``Enemy``, ``Satellite``); categories with several are numbered
densely in OCAtari's slot order (``Alien0``, ``Alien1``, ..., ``Shield0``, ``Bullet0``), so ``Alien{i}``
exists for ``i < count``. Breakout's bricks are lists under ``RB OB YB GB AB BB`` (rows top to bottom),
one entry per OCAtari ``Block``, a run of adjacent bricks (``w = 8 * n``), as the authors have them; a row
is absent once cleared. An object that is not on screen is an absent key, never a placeholder. The games of
the authors' follow-up group and extend these objects (``Game.derive``). These are the conventions of
observation version 2 (``games.base.OBSERVATION_VERSION``); ``make_env(..., observation=1)`` builds the
earlier one that runs stored before it replay with (docs/observations.md).

We call OCAtari's RAM extractors directly instead of its ``OCAtari`` env class: the class returns
``(obs, reward, truncated, terminated)`` in a non-Gymnasium order, keeps frame buffers we do not need, and
does uint8 arithmetic that under numpy 2 corrupts Space Invaders objects and then overflows; passing the RAM
as int64 gives the numpy-1 results (../shared/NOTES.md).
"""

from __future__ import annotations

import copy
import dis
import functools
import importlib
import types
import weakref
from typing import Any, Callable, Mapping

import ale_py
import gymnasium as gym
import numpy as np
from ocatari.ram import extract_ram_info
from ocatari.ram import game_objects as ram_objects
from ocatari.vision import game_objects as vision_objects

from games import GAMES, Game, get_game, lean_ocatari
from games.base import ONE_LIFE_CONTINUE, numbered_keys, one_life_setting
from games.spaces import observation_space as game_observation_space
from games.wrappers import AutoFire, EpisodicLife, NoopReset, OneLife, ServeAgain

Observation = dict[str, Any]


ale_py.ALEInterface.setLoggerMode(ale_py.LoggerMode.Error)  # no banner for every environment
gym.register_envs(ale_py)
for _game in GAMES.values():  # import the extractors once (worker processes fork with them loaded)
    importlib.import_module(f"ocatari.ram.{_game.ocatari_name.lower()}")


@functools.cache  # ~2 ms of bytecode a module: once per process, not once per environment
def written_globals(module: types.ModuleType) -> tuple[str, ...]:
    """The globals ``module``'s own functions assign (``global x`` then ``x = ...``): the state an OCAtari extractor
    keeps between calls (Q*bert's Coily and balls; Assault, Boxing, Pitfall, ... have theirs)."""
    names: set[str] = set()
    pending = [value.__code__ for value in vars(module).values()
               if isinstance(value, types.FunctionType) and value.__module__ == module.__name__]
    while pending:
        code = pending.pop()
        names.update(i.argval for i in dis.get_instructions(code) if i.opname in ("STORE_GLOBAL", "DELETE_GLOBAL"))
        pending.extend(const for const in code.co_consts if isinstance(const, types.CodeType))
    return tuple(sorted(names))


_READER_HOLDERS: dict[str, "weakref.ref[ObjectObservation]"] = {}
"""Per OCAtari extractor module, the environment whose state its globals hold now."""


class ObjectObservation(gym.Wrapper):
    """Turn an ALE env's observations into the paper's object dicts (see the module docstring).

    The wrapped ALE env must observe its RAM (``obs_type="ram"``, as :func:`make_env` builds it): the objects
    are read from it, and no screen is copied out every step. ``observation_space`` is the game's
    :class:`games.spaces.ObjectDict` (keys that come and go, lists, derived fields), built when first asked for:
    codearcade never asks, Gymnasium's checkers and RL code do. The frame stays available through
    ``env.unwrapped.ale.getScreenRGB()`` (``render()`` with ``render_mode="rgb_array"``).

    Some OCAtari extractors keep state between calls in their module's globals (:func:`written_globals`), one set
    per process: two environments of such a game stepped in turn (``gymnasium.vector.SyncVectorEnv``, or by hand)
    read each other's state, and Q*bert's enemies came and went. Each environment keeps its own: the one about to
    read takes the globals over, saving those of the environment that held them (a copy, only when the holder
    changes; one environment alone never copies).
    """

    def __init__(self, env: gym.Env, game: Game):
        super().__init__(env)
        self.game = game
        # generic games: their extractor imported on first use
        self._reader = importlib.import_module(f"ocatari.ram.{game.ocatari_name.lower()}")
        lean_ocatari.ready(self._reader)  # what it calls of OCAtari's deferred imports, imported here, not per host
        self._reader_globals = written_globals(self._reader)
        self._reader_state: tuple | None = None
        """The reader's globals as this environment left them when another took them over."""
        self._as_holder = weakref.ref(self)
        """What :data:`_READER_HOLDERS` holds while this environment holds its reader's globals."""
        max_objects = extract_ram_info.get_max_objects(game.ocatari_name, False)
        self._numbered = {category for category, count in max_objects.items() if count > 1}
        self.metadata = {**env.metadata, "render_modes": ["rgb_array"]}  # "human": gymnasium's HumanRendering
        self._objects: list = []
        self._plan = ObservationPlan(None, self._numbered)
        self.object_rows: list[tuple] = []
        """The last observation as step-log rows (``tracing.steps.StepLog.observe(obs, rows)``), made with it."""

    @property
    def observation_space(self):
        if self._observation_space is None:  # on first use: a game without derive_space plays, this raises
            self._observation_space = game_observation_space(self.game)
        return self._observation_space

    @observation_space.setter
    def observation_space(self, space):
        self._observation_space = space

    def reset(self, **kwargs):
        ram, info = self.env.reset(**kwargs)
        if self._reader_globals and _READER_HOLDERS.get(self._reader.__name__) is not self._as_holder:
            self._hold_reader()  # before init_objects resets them: the holder's state is saved first
        self._objects = extract_ram_info.init_objects(self.game.ocatari_name, False)
        return self._observe(ram, first=True), info

    def step(self, action):
        ram, reward, terminated, truncated, info = self.env.step(action)
        return self._observe(ram), reward, terminated, truncated, info

    def _hold_reader(self) -> None:
        """Make the reader module's globals this environment's (see the class docstring)."""
        module, names = self._reader, self._reader_globals
        held = _READER_HOLDERS.get(module.__name__)
        holder = held() if held is not None else None
        if holder is not None and holder is not self:
            holder._reader_state = copy.deepcopy(tuple(getattr(module, name, None) for name in names))
        if self._reader_state is not None:
            for name, value in zip(names, self._reader_state):
                setattr(module, name, value)
        _READER_HOLDERS[module.__name__] = self._as_holder

    def _observe(self, ram: np.ndarray, first: bool = False) -> Observation:
        if self._reader_globals and _READER_HOLDERS.get(self._reader.__name__) is not self._as_holder:
            self._hold_reader()
        if self.game.detect is not None:
            self.game.detect(self._objects, ram)
        else:  # int64: OCAtari's extractors do arithmetic on the RAM bytes, which wraps around under numpy 2
            extract_ram_info.detect_objects_ram(self._objects, ram.astype(np.int64), self.game.ocatari_name, False)
        if first:  # fresh objects "moved" from (0, 0): nothing has moved yet on the first observation
            for o in self._objects:
                if o is not None:
                    o._prev_xy = o._xy
        game = self.game
        plan = self._plan
        if plan.game is not game:  # the first observation, or a game swapped in since (bench/step_profile.py)
            plan = self._plan = ObservationPlan.of(game, self._numbered)
        self.object_rows = rows = []
        obs = objects_to_dict(self._objects, plan, rows)
        if game.derive is not None:
            game.derive(obs, self.env.unwrapped.ale.lives())
        return obs


_NO_OBJECT_CLASSES = (ram_objects.NoObject, vision_objects.NoObject, type(None))  # some extractors leave slots None
_SKIP = ()


class ObservationPlan:
    """How each OCAtari class enters one environment's observation, decided on its first object and kept.

    :func:`objects_to_dict` runs every step for every object: what does not change within a game (a class's
    category, whether it is numbered, its keys ``Alien0, Alien1, ...``, its hook) is looked up once per class
    here, not once per object. A plan belongs to one :class:`Game` (its ``list_widths`` and ``object_hooks``) and
    that game's numbered categories (those with several OCAtari slots).
    """

    def __init__(self, game: Game | None, numbered: set[str], lists: Mapping[str, int] | None = None,
                 hooks: Mapping[str, Callable | None] | None = None) -> None:
        self.game = game
        self.numbered = frozenset(numbered)
        self.lists = tuple(lists or ())
        self.hooks = dict(hooks or {})
        self.counts = dict.fromkeys(self.numbered, 0)
        """Each numbered category's objects so far: copied at the start of every observation."""
        self.entries: dict[type, tuple] = dict.fromkeys(_NO_OBJECT_CLASSES, _SKIP)
        """Per class: ``_SKIP``, or ``(hook, None, None)``, ``(key, category, None)`` (one slot) or
        ``(None, category, keys)`` (numbered)."""

    @classmethod
    def of(cls, game: Game, numbered: set[str]) -> "ObservationPlan":
        """The plan of ``game``'s observation as it builds it (``list_widths``, ``object_hooks``)."""
        return cls(game, numbered, game.list_widths, game.object_hooks)

    def entry(self, cls: type) -> tuple:
        """The entry of ``cls`` (see :attr:`entries`), made on its first object."""
        entry = self.entries.get(cls)
        if entry is None:
            category = cls.__name__
            if category in self.hooks:
                hook = self.hooks[category]
                entry = _SKIP if hook is None else (hook, None, None)  # None: the category is left out
            elif category in self.numbered:
                entry = (None, category, numbered_keys(category))
            else:
                entry = (category, category, None)
            self.entries[cls] = entry
        return entry


def objects_to_dict(objects: list, plan: ObservationPlan, rows: list[tuple] | None = None) -> Observation:
    """Convert OCAtari's padded object list into the observation dict (``NoObject`` and invisible slots skipped).

    ``plan`` (:class:`ObservationPlan`) holds the keys that are always present as lists (``Game.list_widths``), the
    hooks that put the objects of their category into the dict themselves (``Game.object_hooks``: Breakout files
    its brick runs by row) and the numbered categories. With ``rows``, also append the observation's rows for the
    step log (``tracing.steps.OBJECT_TYPE`` order), made from the same values in the same pass: what
    ``StepLog.observe`` would otherwise make by walking the dict again.

    This runs every step, so it reads OCAtari's fields directly instead of through its property chain
    (``o.dx`` alone goes through three properties); the values are the same. A value that is not a Python int
    (OCAtari's own readers give NumPy ints; ``games/readers/`` give ints) goes through ``int()``: a class test
    per value costs a fifth of an ``int()`` call.
    """
    obs: Observation = {key: [] for key in plan.lists} if plan.lists else {}
    entries = plan.entries
    counts = plan.counts.copy()
    for o in objects:
        try:
            entry = entries[o.__class__]
        except KeyError:  # the first object of its class
            entry = plan.entry(o.__class__)
        if entry is _SKIP or not o._visible:
            continue
        key, category, keys = entry
        if category is None:  # a hook
            key(o, obs, rows)
            continue
        x, y = o._xy
        w, h = o.wh
        prev = o._prev_xy
        if prev is None:
            if not (x.__class__ is int and y.__class__ is int and w.__class__ is int and h.__class__ is int):
                x, y, w, h = int(x), int(y), int(w), int(h)
            dx = dy = 0
        else:
            px, py = prev
            if not (x.__class__ is int and y.__class__ is int and w.__class__ is int and h.__class__ is int
                    and px.__class__ is int and py.__class__ is int):
                x, y, w, h, px, py = int(x), int(y), int(w), int(h), int(px), int(py)
            dx, dy = x - px, y - py
        if keys is not None:
            n = counts[category]
            counts[category] = n + 1
            try:
                key = keys[n]
            except IndexError:
                key = f"{category}{n}"
        obs[key] = {"x": x, "y": y, "w": w, "h": h, "dx": dx, "dy": dy}
        if rows is not None:
            rows.append((key, None, category, x, y, w, h, dx, dy))
    return obs


def make_env(game: str | Game, sticky: float = 0.0, noop_max: int = 0, render: bool = False,
             one_life: bool | str = False, observation: int | None = None, objects: bool = True,
             serve_again: bool = True) -> gym.Env:
    """Build the wrapped environment for ``game``; see the module docstring for the observation format.

    ``one_life=True`` ends each episode at the first lost life (:class:`OneLife`); ``one_life="continue"``
    is the authors' protocol exactly, each ``reset()`` going on with the game (:class:`EpisodicLife`); a game
    without lives plays as before.

    ``objects=False`` leaves out the object extraction (:class:`ObjectObservation`): the observation is the RAM,
    rewards, flags and lives are the same (what a replay of recorded actions needs).

    ``observation`` is the version of the observation conventions (``games.base.OBSERVATION_VERSION``; None:
    today's, or the one ``game`` already builds when it is a :meth:`Game.observing` of another).

    ``serve_again=False`` leaves out :class:`ServeAgain`, as every game was played before 2026-12-05: a replay of
    a game stored then whose serve sticky actions swallowed (``pipeline/play/verify.py``).

    ``render=True`` keeps the RGB frame available through ``env.unwrapped.ale.getScreenRGB()`` (it always is;
    the flag only asks ALE for ``rgb_array`` rendering for viewers that call ``env.render()``).
    """
    spec = get_game(game).observing(observation)
    one_life = one_life_setting(one_life)
    if not 0.0 <= sticky <= 1.0:
        raise ValueError(f"sticky-action probability must be within [0, 1], got {sticky}")
    if noop_max < 0:
        raise ValueError(f"noop_max must be >= 0, got {noop_max}")
    env = gym.make(
        spec.env_id,
        obs_type="ram",  # objects come from RAM; the screen is read only by viewers that ask for it
        frameskip=4,
        repeat_action_probability=sticky,
        full_action_space=False,
        render_mode="rgb_array" if render else None,
        disable_env_checker=True,
    )
    if sticky == 0.0:
        reload_from_snapshot(env.unwrapped, spec.restorable_reset)
    if noop_max:
        env = NoopReset(env, noop_max)
    if spec.ball_in_play is not None and serve_again:
        env = ServeAgain(env, spec.ball_in_play)
    episodic = one_life == ONE_LIFE_CONTINUE
    if spec.fire_on_life_loss and not episodic:
        env = AutoFire(env)
    if one_life is True:
        env = OneLife(env)
    if objects:
        env = ObjectObservation(env, spec)
    return EpisodicLife(env, fire=spec.fire_on_life_loss) if episodic else env


RESET_WITHOUT_SCREEN = {"screen": False}
"""Reset options for a caller that reads no screen before the first step (a game host whose episode records no
frames): a seeded reset without sticky actions may then restore the state ALE's reset leads to instead of playing
it (:func:`reload_from_snapshot`), and the screen shows the last frame drawn until the first step draws its own."""


def reload_from_snapshot(atari_env: Any, restorable_reset: bool = False) -> None:
    """Make ``atari_env``'s seeded resets restore the state its construction loaded instead of loading the ROM
    again: ALE's ``loadROM`` takes 0.12-0.2 s here, as long as 150-200 steps, in every episode's reset.

    Only without sticky actions: there the seed reaches nothing a game plays. ALE draws from its random
    generator only to decide whether to repeat an action (never, at probability 0), and a freshly loaded
    game's state does not depend on the seed (tested: obs, rewards, flags, lives, screen and RAM of all eight
    games are the same byte for byte either way). With sticky actions the seed must reseed ALE's generator,
    which only ``loadROM`` does. The environment's own generator (no-op starts) is still seeded by ``reset``.

    With ``restorable_reset`` (the game's :attr:`Game.restorable_reset`), a seeded reset with
    :data:`RESET_WITHOUT_SCREEN` skips ALE's ``reset_game`` as well: it plays ~64 frames (60 no-ops, the console's
    reset, the game's starting actions), ~4 ms, the same from the same loaded state every time, so the state it
    leads to is taken once here and restored. The state holds the emulator's RAM, CPU, chips, the game's score and
    lives and the frame counters, but not the screen, which therefore still shows the frame drawn last until the
    first step (tested against a real ``loadROM``, step by step), nor whatever else a game's frames may read
    that the console's reset would have cleared (Q*bert's: the reason the game says whether this holds).
    """
    ale = atari_env.ale
    loaded = ale.cloneState()  # the constructor has just loaded the ROM and set the game's mode

    def load_game() -> None:
        atari_env.ale.restoreState(loaded)

    atari_env.load_game = load_game
    if not restorable_reset:
        return
    ale.reset_game()
    started = ale.cloneState()
    ale.restoreState(loaded)
    ale_reset = type(atari_env).reset

    def reset(*, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is None or not options or options.get("screen", True):
            return ale_reset(atari_env, seed=seed, options=options)
        gym.Env.reset(atari_env, seed=seed, options=options)  # what ALE's reset does before it seeds its own
        seeded_with = atari_env.seed_game(seed)
        atari_env.ale.restoreState(started)
        return atari_env._get_obs(), {**atari_env._get_info(), "seeds": seeded_with}

    atari_env.reset = reset


_shared: dict[tuple[str, int, float, int, bool | str], gym.Env] = {}


def shared_env(game: str | Game, sticky: float = 0.0, noop_max: int = 0, one_life: bool | str = False,
               observation: int | None = None) -> gym.Env:
    """An environment for one episode after another in this process (``make_env`` is ~0.1 s a call).

    Reuse is safe because every episode starts with ``reset(seed=...)``, which reloads the game (or restores it
    as loaded: :func:`reload_from_snapshot`) and reseeds every random source, so an episode plays the same on a
    fresh or a reused environment (tested); the episodes that continue a game (``one_life="continue"``) follow
    the one they continue on the same environment.
    """
    spec = get_game(game).observing(observation)
    key = (spec.name, spec.observation, float(sticky), int(noop_max), one_life_setting(one_life))
    env = _shared.get(key)
    if env is None:
        env = _shared[key] = make_env(spec, sticky=sticky, noop_max=noop_max, one_life=one_life)
    return env


def discard_env(env: gym.Env) -> None:
    """Drop ``env`` from the shared ones (after an error left it in an unknown state) and close it."""
    for key, shared in list(_shared.items()):
        if shared is env:
            del _shared[key]
    env.close()


# -- Gymnasium ids ----------------------------------------------------------------------------------------------

NAMESPACE = "codearcade"


def gym_id(game: str | Game) -> str:
    """The Gymnasium id of a game: ``codearcade/SpaceInvaders-v0`` for ``space_invaders``."""
    from games.generic import rom_title

    return f"{NAMESPACE}/{rom_title(game.name if isinstance(game, Game) else game)}-v0"


def make_registered(game: str, render_mode: str | None = None, sticky: float = 0.0, noop_max: int = 0,
                    one_life: bool | str = False) -> gym.Env:
    """What ``gymnasium.make("codearcade/<Game>-v0", ...)`` builds: :func:`make_env` (the paper's protocol unless
    ``sticky``, ``noop_max`` or ``one_life`` say otherwise). ``render_mode="rgb_array"`` renders the frame;
    ``"human"`` shows it in a window (Gymnasium's ``HumanRendering``, which needs pygame and a display)."""
    if render_mode not in (None, "rgb_array", "human"):
        raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
    env = make_env(game, sticky=sticky, noop_max=noop_max, render=render_mode is not None, one_life=one_life)
    return gym.wrappers.HumanRendering(env) if render_mode == "human" else env


def register_envs() -> None:
    """Register ``codearcade/<Game>-v0`` for every curated game and every generic one (done when this module is
    imported; ``import games`` alone registers nothing, so it stays free of Gymnasium). Each id is capped at its
    game's evaluation length (``Task.eval_max_steps``; ``gymnasium.make(..., max_episode_steps=-1)`` lifts it)."""
    from games.generic import GENERIC_EVAL_MAX_STEPS, generic_names

    caps = {name: GENERIC_EVAL_MAX_STEPS for name in generic_names()}  # no Game made: that reads each ROM
    caps.update({game.name: game.task.eval_max_steps for game in GAMES.values()})
    for name, max_steps in caps.items():
        if gym_id(name) not in gym.registry:
            gym.register(gym_id(name), entry_point=f"{__name__}:make_registered", kwargs={"game": name},
                         max_episode_steps=max_steps)


register_envs()
