"""Gymnasium observation spaces that hold exactly the object observations of :mod:`games.envs`.

An observation is a dict whose keys come and go: ``Player`` is absent while off screen, Space Invaders has
``Alien0 .. Alien{n-1}`` for the n aliens left, Asterix adds ``Enemies`` only while an enemy is on screen, and
Breakout's brick rows are lists that shrink. Gymnasium's ``Dict`` requires every key on every step and its
``Sequence`` accepts any iterable of any length, so three small spaces of ours fill the gaps:

- :class:`ObjectDict`: required keys, optional keys, numbered categories (``Alien0 ..`` numbered densely, at most
  OCAtari's slot count) and groups of keys present together; values are Gymnasium spaces;
- :class:`ListOf`: a :class:`gymnasium.spaces.Sequence` that must be a ``list`` of bounded length, in the
  order its game sorts it (Asterix's nearest first, the lane lists ascending);
- :class:`OneOf`: one of a few values (an object's ``type``, Breakout's brick widths 8, 16, .., 144).

Every object is a ``Dict`` of ``Discrete`` integer ranges (:func:`box`): ``x, y, w, h`` within int16, as the
step log stores them (OCAtari computes boxes from RAM bytes with int64 arithmetic and reports garbage off screen:
values within +-600 over 3,000 random steps of each of the 57 games it reads, on a 160 x 210 screen); ``dx, dy``
are differences of two coordinates. A game narrows what its module knows (Q*bert keeps only on-screen objects,
Freeway folds a car's dx into [-80, 80)). ``contains`` checks keys, types, ranges, lengths and declared orders;
relations between fields (``dist`` against the player's position) are not a space's business. ``sample()``
returns a member of the space (its ints numpy integers).

:func:`observation_space` builds a game's space: the generic objects from OCAtari's categories
(:meth:`ObjectDict.of_objects`, keyed as :func:`games.envs.objects_to_dict` keys them), then the game's own
``Game.derive_space`` (in ``games/<game>.py``, beside the ``derive`` and hooks it mirrors).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
from gymnasium import spaces

from games.base import Game

COORDINATE = (-(2**15), 2**15 - 1)
"""Bounds of a box's x, y, w and h: int16, the step log's columns (``tracing/steps.py``)."""
DELTA = (COORDINATE[0] - COORDINATE[1], COORDINATE[1] - COORDINATE[0])
"""dx, dy, and any difference of two coordinates (Enduro's ``rel_x``)."""
DISTANCE = (0, 2 * DELTA[1])
"""A Manhattan distance between two points (Asterix's ``dist``)."""
LIVES = (0, 256)
"""ALE reads a game's lives from one RAM byte (Seaquest's plus one)."""


def ints(low: int, high: int) -> spaces.Discrete:
    """The integers ``low .. high``, both included."""
    return spaces.Discrete(high - low + 1, start=low)


def box(**fields: spaces.Space | tuple[int, int]) -> spaces.Dict:
    """An object ``{x, y, w, h, dx, dy}`` (ranges as above unless given) plus any extra ``fields``; a field is a
    space or an inclusive ``(low, high)`` integer range."""
    defaults = {"x": COORDINATE, "y": COORDINATE, "w": COORDINATE, "h": COORDINATE, "dx": DELTA, "dy": DELTA}
    merged = {**defaults, **fields}
    return spaces.Dict({key: ints(*value) if isinstance(value, tuple) else value for key, value in merged.items()},
                       sort_keys=False)


def with_fields(item: spaces.Dict, **fields: spaces.Space | tuple[int, int]) -> spaces.Dict:
    """``item`` with ``fields`` added or replaced (a game's derived fields: Asterix's ``lane``, ``dist``)."""
    return box(**{**item.spaces, **fields})


class OneOf(spaces.Space):
    """Exactly one of ``values`` (strings or ints; a value's Python type must match: ``16.0`` is not ``16``)."""

    def __init__(self, values: Iterable[str | int], seed: int | np.random.Generator | None = None):
        self.values = tuple(dict.fromkeys(values))
        if not self.values:
            raise ValueError("OneOf needs at least one value")
        self._members = {(type(v), v) for v in self.values}
        super().__init__(None, None, seed)

    @property
    def is_np_flattenable(self) -> bool:
        return False

    def sample(self, mask: Any = None, probability: Any = None) -> str | int:
        if mask is not None or probability is not None:
            raise NotImplementedError("OneOf.sample takes no mask or probability")
        return self.values[int(self.np_random.integers(len(self.values)))]

    def contains(self, x: Any) -> bool:
        if isinstance(x, np.integer):
            x = int(x)
        try:
            return (type(x), x) in self._members
        except TypeError:  # unhashable
            return False

    def __repr__(self) -> str:
        return f"OneOf({list(self.values)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, OneOf) and other.values == self.values


class ListOf(spaces.Sequence):
    """A ``list`` of ``min_length .. max_length`` items of ``item``, non-decreasing by ``key`` when given (strictly
    increasing with ``strict``). Gymnasium's :class:`~gymnasium.spaces.Sequence` with the bounds it lacks;
    ``sample()`` returns a list (``Sequence`` returns a tuple). ``key`` is a module-level function (or ``int``
    for a list of ints), so that the space pickles and compares equal to its copy."""

    def __init__(self, item: spaces.Space, max_length: int, min_length: int = 0,
                 key: Callable[[Any], Any] | None = None, strict: bool = False,
                 seed: int | np.random.Generator | None = None):
        if not 0 <= min_length <= max_length:
            raise ValueError(f"ListOf needs 0 <= min_length <= max_length, got {min_length}, {max_length}")
        self.min_length, self.max_length, self.key, self.strict = min_length, max_length, key, strict
        super().__init__(item, seed=seed, stack=False)

    def sample(self, mask: Any = None, probability: Any = None) -> list:
        if mask is not None or probability is not None:
            raise NotImplementedError("ListOf.sample takes no mask or probability")
        while True:  # strict lists drop repeated keys; draw again the rare time that leaves too few
            n = int(self.np_random.integers(self.min_length, self.max_length + 1))
            items = [self.feature_space.sample() for _ in range(n)]
            if self.key is None:
                return items
            items.sort(key=self.key)
            if self.strict:
                items = [item for i, item in enumerate(items) if i == 0 or self.key(items[i - 1]) != self.key(item)]
            if len(items) >= self.min_length:
                return items

    def contains(self, x: Any) -> bool:
        if type(x) is not list or not self.min_length <= len(x) <= self.max_length:
            return False
        if not all(item in self.feature_space for item in x):
            return False
        if self.key is None:
            return True
        keys = [self.key(item) for item in x]
        if self.strict:
            return all(a < b for a, b in zip(keys, keys[1:]))
        return all(a <= b for a, b in zip(keys, keys[1:]))

    def __repr__(self) -> str:
        order = "" if self.key is None else f", {'strictly ' if self.strict else ''}by {self.key.__name__}"
        return f"ListOf({self.feature_space}, {self.min_length}..{self.max_length}{order})"

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, ListOf) and other.feature_space == self.feature_space
                and (other.min_length, other.max_length, other.key, other.strict)
                == (self.min_length, self.max_length, self.key, self.strict))


class ObjectDict(spaces.Space):
    """A dict observation whose keys come and go: required keys, optional keys, numbered categories and groups of
    optional keys that are present together or not at all (Enduro's ``EnemyCars`` and ``nearest_enemy_rel_x``).

    A numbered category ``Alien`` with ``n`` slots stands for the keys ``Alien0 .. Alien{k-1}`` for some
    ``k <= n`` (numbered densely, as the observation numbers them). ``contains`` is exact for that structure: every
    key accounted for, every required key present, every value in its space. Built in place by a game's
    ``derive_space`` (:meth:`take`, :meth:`add`, :meth:`together`) before the environment uses it.
    """

    def __init__(self, seed: int | np.random.Generator | None = None):
        self.required: dict[str, spaces.Space] = {}
        self.optional: dict[str, spaces.Space] = {}
        self.numbered: dict[str, tuple[spaces.Space, int]] = {}
        self.groups: list[tuple[str, ...]] = []
        super().__init__(None, None, seed)

    @classmethod
    def of_objects(cls, max_objects: Mapping[str, int]) -> ObjectDict:
        """The generic observation: every OCAtari category (``{category: slots}``) an optional object, numbered
        when it has more than one slot (as ``games.envs.ObjectObservation`` numbers them)."""
        space = cls()
        for category, slots in max_objects.items():
            if slots > 1:
                space.numbered[category] = (box(), slots)
            else:
                space.optional[category] = box()
        return space

    # -- building (a game's derive_space) ---------------------------------------------------------------------

    def take(self, category: str) -> tuple[spaces.Space, int]:
        """Remove ``category`` (numbered or not) and return its object space and how many of it there can be,
        as :func:`games.base.pop_numbered` takes the objects out of an observation."""
        if category in self.numbered:
            return self.numbered.pop(category)
        for keys in (self.optional, self.required):
            if category in keys:
                return keys.pop(category), 1
        raise KeyError(f"the observation space has no category {category!r}: {self}")

    def add(self, key: str, space: spaces.Space, optional: bool = False) -> None:
        """Add (or replace) ``key``: always present, or absent at times with ``optional``."""
        self.required.pop(key, None)
        self.optional.pop(key, None)
        (self.optional if optional else self.required)[key] = space

    def together(self, *keys: str) -> None:
        """``keys`` (optional ones) are all present or all absent."""
        missing = [key for key in keys if key not in self.optional]
        if missing:
            raise KeyError(f"together() takes optional keys; not optional: {missing}")
        self.groups.append(tuple(keys))

    def __getitem__(self, key: str) -> spaces.Space:
        """The space of ``key`` (a numbered category's by the category's name)."""
        if key in self.numbered:
            return self.numbered[key][0]
        return self.required[key] if key in self.required else self.optional[key]

    # -- the Space interface -------------------------------------------------------------------------------------

    @property
    def is_np_flattenable(self) -> bool:
        return False

    def _subspaces(self) -> list[spaces.Space]:
        return [*self.required.values(), *self.optional.values(), *(s for s, _ in self.numbered.values())]

    def seed(self, seed: int | None = None) -> list[int]:
        """Seed this space and, from it, each subspace (one int seeds them all reproducibly)."""
        seeds = [super().seed(seed)]
        for subspace in self._subspaces():
            sub_seed = None if seed is None else int(self.np_random.integers(2**31 - 1))
            subspace.seed(sub_seed)
            seeds.append(sub_seed)
        return seeds

    def contains(self, x: Any) -> bool:
        if type(x) is not dict:
            return False
        accounted = 0
        for key, space in self.required.items():
            if key not in x or x[key] not in space:
                return False
        accounted += len(self.required)
        for key, space in self.optional.items():
            if key in x:
                if x[key] not in space:
                    return False
                accounted += 1
        for category, (space, slots) in self.numbered.items():
            i = 0
            while i < slots and (key := f"{category}{i}") in x:
                if x[key] not in space:
                    return False
                i += 1
            accounted += i
        for keys in self.groups:
            if len({key in x for key in keys}) > 1:
                return False
        return accounted == len(x)  # no key left over (an unknown key, a gap in a numbering, one too many)

    def sample(self, mask: Any = None, probability: Any = None) -> dict:
        if mask is not None or probability is not None:
            raise NotImplementedError("ObjectDict.sample takes no mask or probability")
        rng = self.np_random
        grouped = {key: keys for keys in self.groups for key in keys}
        present: dict[tuple[str, ...], bool] = {}
        out: dict[str, Any] = {key: space.sample() for key, space in self.required.items()}
        for key, space in self.optional.items():
            keys = grouped.get(key, (key,))
            if keys not in present:
                present[keys] = bool(rng.integers(2))
            if present[keys]:
                out[key] = space.sample()
        for category, (space, slots) in self.numbered.items():
            for i in range(int(rng.integers(slots + 1))):
                out[f"{category}{i}"] = space.sample()
        return out

    def __repr__(self) -> str:
        parts = [f"{key}: {space}" for key, space in self.required.items()]
        parts += [f"{key}?: {space}" for key, space in self.optional.items()]
        parts += [f"{category}0..{slots - 1}: {space}" for category, (space, slots) in self.numbered.items()]
        parts += [f"together{keys}" for keys in self.groups]
        return "ObjectDict(" + ", ".join(parts) + ")"

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, ObjectDict) and (other.required, other.optional, other.numbered, other.groups)
                == (self.required, self.optional, self.numbered, self.groups))


def object_slots(ocatari_name: str) -> dict[str, int]:
    """Every category OCAtari's RAM extractor for the game can report, with its slots: its ``MAX_NB_OBJECTS``
    (``Alien: 36``), and 1 for every other object class its module defines (some extractors report objects their
    ``MAX_NB_OBJECTS`` leaves out: Beam Rider's ``Saucer``, Asteroids' ``NoObjectPlayer``)."""
    from ocatari.ram import extract_ram_info
    from ocatari.ram.game_objects import GameObject

    module = importlib.import_module(f"ocatari.ram.{ocatari_name.lower()}")
    slots = dict(extract_ram_info.get_max_objects(ocatari_name, False))
    for value in vars(module).values():
        if (isinstance(value, type) and issubclass(value, GameObject)
                and not value.__module__.endswith(".game_objects")):  # the base classes, NoObject
            slots.setdefault(value.__name__, 1)
    return slots


def observation_space(game: Game) -> ObjectDict:
    """The space of ``game``'s observation: OCAtari's categories (:func:`object_slots`), then
    ``game.derive_space``. A game whose hooks or ``derive`` change the generic observation must say how there."""
    space = ObjectDict.of_objects(object_slots(game.ocatari_name))
    if game.derive_space is not None:
        game.derive_space(space)
    elif game.object_hooks or game.derive is not None or game.list_widths:
        raise TypeError(f"game {game.name!r} changes its observation (object_hooks, derive or list_widths) but "
                        f"declares no derive_space: add Game(derive_space=...) in its module")
    return space
