"""The observation build (``games.envs.objects_to_dict`` and each game's hooks and ``derive``) gives exactly what it
gave before it was made cheaper (issue 40): the same dict, the same key order at every level, the same value types
(a NumPy int where a Python int was is a difference: marshal refuses it), the same lists in the same order, and the
same step-log rows.

The oracle is the build as it was (commit 74f563e), copied below unchanged: ``objects_to_dict`` and the hooks and
``derive`` functions of Asterix, Q*bert, Freeway, Seaquest and Breakout (both observation versions where they
differ). Each game is played from several seeds, lives lost included, and at every step both builders run on the
same OCAtari objects; then the same objects are perturbed (slots emptied, hidden, swapped, moved, given NumPy or
float coordinates, no previous position) and both run again.
"""

from __future__ import annotations

import copy
import importlib
import random
from typing import Any, Callable, Mapping

import numpy as np
import pytest
from ocatari.ram import game_objects as ram_objects
from ocatari.vision import game_objects as vision_objects

from games import GAMES, get_game
from games.base import Game
from games.envs import ObjectObservation, ObservationPlan, make_env, objects_to_dict

# ---------------------------------------------------------------------------------------------------------------
# The oracle: the observation build of commit 74f563e, verbatim (only renamed where two versions meet)
# ---------------------------------------------------------------------------------------------------------------

_NO_OBJECT_CLASSES = (ram_objects.NoObject, vision_objects.NoObject)


def ref_objects_to_dict(objects: list, numbered: set[str], lists: Mapping[str, int] | None = None,
                        hooks: Mapping[str, Callable] | None = None, rows: list[tuple] | None = None) -> dict:
    obs: dict = {key: [] for key in lists} if lists else {}
    counts: dict[str, int] = {}
    for o in objects:
        cls = o.__class__
        if cls in _NO_OBJECT_CLASSES or o is None or not o._visible:  # some extractors leave empty slots None
            continue
        category = cls.__name__
        if hooks and category in hooks:
            hooks[category](o, obs, rows)
            continue
        x, y = o._xy
        w, h = o.wh
        x, y, w, h = int(x), int(y), int(w), int(h)
        prev = o._prev_xy
        if prev is None:
            dx = dy = 0
        else:
            dx, dy = x - int(prev[0]), y - int(prev[1])
        if category in numbered:
            n = counts.get(category, 0)
            counts[category] = n + 1
            key = _ref_numbered_key(category, n)
        else:
            key = category
        obs[key] = {"x": x, "y": y, "w": w, "h": h, "dx": dx, "dy": dy}
        if rows is not None:
            rows.append((key, None, category, x, y, w, h, dx, dy))
    return obs


_NUMBERED_KEYS: dict[tuple[str, int], str] = {}


def _ref_numbered_key(category: str, n: int) -> str:
    key = _NUMBERED_KEYS.get((category, n))
    if key is None:
        key = _NUMBERED_KEYS[(category, n)] = f"{category}{n}"
    return key


def ref_pop_numbered(obs: dict, category: str) -> list[dict]:
    items = []
    i = 0
    while True:
        item = obs.pop(f"{category}{i}", None)
        if item is None:
            return items
        items.append(item)
        i += 1


# Asterix
ASTERIX_GROUPS = (("Enemy", "Enemies"), ("Consumable", "Consumables"), ("Reward", "Rewards"))


def _asterix_lane(y: int) -> int:
    lane = (y - 18) // 16
    return 0 if lane < 0 else 7 if lane > 7 else lane


def ref_asterix_derive(obs: dict, lives: int) -> None:
    player = obs.get("Player")
    if player is not None:
        player["lane"] = _asterix_lane(player["y"])
        px, py = player["x"], player["y"]
    else:
        px, py = (76, 74)
    enemy_lanes: set[int] = set()
    item_lanes: set[int] = set()
    for category, key in ASTERIX_GROUPS:
        items = ref_pop_numbered(obs, category)
        if not items:
            continue
        lanes = enemy_lanes if category == "Enemy" else item_lanes
        for item in items:
            item["type"] = category
            item["lane"] = _asterix_lane(item["y"])
            item["dist"] = abs(item["x"] - px) + abs(item["y"] - py)
            lanes.add(item["lane"])
        items.sort(key=lambda item: item["dist"])  # stable: ties keep the slot order
        obs[key] = items
    obs["enemy_lanes"] = sorted(enemy_lanes)
    obs["safe_collectible_lanes"] = sorted(item_lanes - enemy_lanes)
    obs["lives"] = int(lives)


# Q*bert
QBERT_ENEMY_TYPES = ("Coily", "PurpleBall", "RedBall")
QBERT_FRIENDLY_TYPES = ("GreenBall", "Sam")
QBERT_FRIENDLY_TYPES_V1 = ("Sam", "GreenBall")


def ref_qbert_drop(o, obs: dict, rows: list | None) -> None:
    pass


def _qbert_on_screen(box: dict) -> bool:
    return 0 <= box["x"] < 160 and 0 <= box["y"] < 210


def _qbert_numbered(obs: dict, category: str) -> list[dict]:
    single = obs.pop(category, None)
    items = [] if single is None else [single]
    i = 0
    while f"{category}{i}" in obs:
        items.append(obs.pop(f"{category}{i}"))
        i += 1
    return items


def ref_qbert_derive(obs: dict, lives: int, friendly_types: tuple[str, ...] = QBERT_FRIENDLY_TYPES) -> None:
    player = obs.get("Player")
    if player is not None and not _qbert_on_screen(player):
        del obs["Player"]
    for key, types in (("Enemies", QBERT_ENEMY_TYPES), ("Friendlies", friendly_types), ("Disks", ("Disk",))):
        items = []
        for category in types:
            for item in _qbert_numbered(obs, category):
                if _qbert_on_screen(item):
                    if key != "Disks":
                        item["type"] = category
                    items.append(item)
        if items:
            obs[key] = items
    obs["lives"] = int(lives)


def ref_qbert_derive_v1(obs: dict, lives: int) -> None:
    ref_qbert_derive(obs, lives, QBERT_FRIENDLY_TYPES_V1)


# Freeway
FREEWAY_LANE_Y = (27, 43, 59, 75, 91, 107, 123, 139, 155, 171)


def _freeway_box(o) -> tuple[int, int, int, int, int, int]:
    x, y = o._xy
    w, h = o.wh
    x, y, w, h = int(x), int(y), int(w), int(h)
    prev = o._prev_xy
    dx, dy = (0, 0) if prev is None else (x - int(prev[0]), y - int(prev[1]))
    return x, y, w, h, dx, dy


def ref_freeway_chicken(o, obs: dict, rows: list | None) -> None:
    x, y, w, h, dx, dy = _freeway_box(o)
    if x >= 80:
        return
    obs["Chicken"] = {"x": x, "y": y, "w": w, "h": h, "dx": dx, "dy": dy}
    if rows is not None:
        rows.append(("Chicken", None, "Chicken", x, y, w, h, dx, dy))


def ref_freeway_car(o, obs: dict, rows: list | None) -> None:
    x, y, w, h, dx, dy = _freeway_box(o)
    dx = ((dx + 80) % 160) - 80
    n = 0
    while f"Car{n}" in obs:
        n += 1
    key = f"Car{n}"
    obs[key] = {"x": x, "y": y, "w": w, "h": h, "dx": dx, "dy": dy}
    if rows is not None:
        rows.append((key, None, "Car", x, y, w, h, dx, dy))


def _freeway_lane(y: int) -> int:
    return min(range(len(FREEWAY_LANE_Y)), key=lambda i: abs(FREEWAY_LANE_Y[i] - y)) + 1


def ref_freeway_derive(obs: dict, lives: int) -> None:
    cars = ref_pop_numbered(obs, "Car")
    cars.sort(key=lambda car: car["y"])  # stable
    for c in cars:
        c["lane"] = _freeway_lane(c["y"])
    obs["Cars"] = cars


# Seaquest
SEAQUEST_ENEMY_TYPES = ("Shark", "Submarine", "EnemyMissile", "SurfaceSubmarine")
SEAQUEST_ENEMY_TYPES_V1 = ("Shark", "Submarine", "SurfaceSubmarine", "EnemyMissile")
SEAQUEST_MULTI_SLOT = frozenset({"Shark", "Submarine", "Diver", "EnemyMissile", "CollectedDiver"})


def _seaquest_take(obs: dict, category: str) -> list[dict]:
    if category in SEAQUEST_MULTI_SLOT:
        return ref_pop_numbered(obs, category)
    item = obs.pop(category, None)
    return [] if item is None else [item]


def ref_seaquest_derive(obs: dict, lives: int, enemy_types: tuple[str, ...] = SEAQUEST_ENEMY_TYPES) -> None:
    enemies = []
    for category in enemy_types:
        for item in _seaquest_take(obs, category):
            item["type"] = category
            enemies.append(item)
    if enemies:
        obs["Enemies"] = enemies
    divers = _seaquest_take(obs, "Diver")
    if divers:
        obs["Divers"] = divers
    _seaquest_take(obs, "PlayerMissile")
    bar = _seaquest_take(obs, "OxygenBar")
    obs["lives"] = int(lives)
    obs["oxygen"] = bar[0]["w"] if bar else 0
    obs["divers_collected"] = len(_seaquest_take(obs, "CollectedDiver"))


def ref_seaquest_derive_v1(obs: dict, lives: int) -> None:
    ref_seaquest_derive(obs, lives, SEAQUEST_ENEMY_TYPES_V1)


# Breakout
BREAKOUT_ROWS = {57: "RB", 63: "OB", 69: "YB", 75: "GB", 81: "AB", 87: "BB"}


def ref_breakout_brick_runs(block, obs: dict, rows: list | None) -> None:
    x, y = block._xy
    x, y = int(x), int(y)
    key = BREAKOUT_ROWS.get(y)
    if key is None:
        return
    w, h = block.wh
    w, h = int(w), int(h)
    bricks = obs.get(key)
    if bricks is None:
        bricks = obs[key] = []
    if rows is not None:
        rows.append((key, len(bricks), key, x, y, w, h, 0, 0))
    bricks.append({"x": x, "y": y, "w": w, "h": h, "dx": 0, "dy": 0})


def ref_breakout_derive(obs: dict, lives: int) -> None:
    obs["lives"] = int(lives)


def ref_breakout_split_bricks(block, obs: dict, rows: list | None) -> None:
    x, y = (int(v) for v in block._xy)
    key = BREAKOUT_ROWS.get(y)
    if key is None:
        return
    w, h = (int(v) for v in block.wh)
    bricks = obs[key]
    n = max(1, w // 8)
    if rows is not None:
        rows.append((key, len(bricks), key, x, y, n * 8, h, 0, 0))
    for i in range(n):
        bricks.append({"x": x + i * 8, "y": y, "w": 8, "h": h, "dx": 0, "dy": 0})


# Enduro (its derive is unchanged, but pop_numbered under it is not)
def ref_enduro_derive(obs: dict, lives: int) -> None:
    cars = ref_pop_numbered(obs, "Car")
    if not cars:
        return
    player = obs.get("Player")
    px, py = (player["x"], player["y"]) if player is not None else (77, 144)
    for car in cars:
        car["rel_x"] = car["x"] - px
        car["rel_y"] = car["y"] - py
    cars.sort(key=lambda car: -car["y"])  # stable
    obs["EnemyCars"] = cars
    obs["nearest_enemy_rel_x"] = cars[0]["rel_x"]
    obs["nearest_enemy_rel_y"] = cars[0]["rel_y"]


REFERENCE: dict[tuple[str, int], dict[str, Any]] = {
    ("asterix", 2): {"derive": ref_asterix_derive},
    ("qbert", 2): {"object_hooks": {"Cube": ref_qbert_drop}, "derive": ref_qbert_derive},
    ("qbert", 1): {"object_hooks": {"Cube": ref_qbert_drop}, "derive": ref_qbert_derive_v1},
    ("freeway", 2): {"object_hooks": {"Chicken": ref_freeway_chicken, "Car": ref_freeway_car},
                     "derive": ref_freeway_derive},
    ("seaquest", 2): {"derive": ref_seaquest_derive},
    ("seaquest", 1): {"derive": ref_seaquest_derive_v1},
    ("breakout", 2): {"object_hooks": {"Block": ref_breakout_brick_runs}, "derive": ref_breakout_derive},
    ("breakout", 1): {"object_hooks": {"Block": ref_breakout_split_bricks}, "derive": None,
                      "list_widths": {key: 8 for key in BREAKOUT_ROWS.values()}},
    ("enduro", 2): {"derive": ref_enduro_derive},
}
"""Per game and observation version, the oracle's hooks, derive and list widths where the game has any (Pong, Space
Invaders and the generic games have none)."""


# ---------------------------------------------------------------------------------------------------------------
# The comparison
# ---------------------------------------------------------------------------------------------------------------

GENERIC = "riverraid"
"""A generic game: OCAtari's own reader, whose objects mix NumPy and Python ints."""
CASES = [(name, 2) for name in GAMES] + [("breakout", 1), ("qbert", 1), ("seaquest", 1), (GENERIC, 2)]
STEPS = 3000
"""Played steps per case, over episodes from seeds 0, 1, 2, ... of at most :data:`EPISODE_STEPS` each."""
EPISODE_STEPS = 1500
PERTURB_EVERY = 10
"""Every this many played steps, the step's objects are perturbed :data:`PERTURBATIONS` times and built again."""
PERTURBATIONS = 3


def typed(value: Any) -> Any:
    """``value`` with every level's order and every leaf's class spelled out: equal only when the two are the same
    dict, in the same key order, with the same lists in the same order and values of the same classes."""
    if value.__class__ is dict:
        return ("dict", [(key.__class__, key, typed(item)) for key, item in value.items()])
    if value.__class__ in (list, tuple):
        return (value.__class__.__name__, [typed(item) for item in value])
    return (value.__class__, value)


def assert_same(ours: Any, theirs: Any, where: str) -> None:
    if typed(ours) != typed(theirs):
        pytest.fail(f"{where}: built\n{ours!r}\nthe oracle built\n{theirs!r}")


class Oracle:
    """The build of commit 74f563e for one game and observation version."""

    def __init__(self, game: Game, version: int, numbered: set[str]):
        ref = REFERENCE.get((game.name, version))
        if ref is None:  # nothing of the game's own: the generic build alone
            assert not game.object_hooks and game.derive is None and not game.list_widths, game.name
            ref = {}
        self.numbered = numbered
        self.hooks = ref.get("object_hooks", {})
        self.lists = ref.get("list_widths", {})
        self.derive = ref.get("derive")

    def build(self, objects: list, lives: int) -> tuple[dict, list]:
        rows: list[tuple] = []
        obs = ref_objects_to_dict(objects, self.numbered, self.lists, self.hooks, rows=rows)
        if self.derive is not None:
            self.derive(obs, lives)
        return obs, rows


def build(plan: ObservationPlan, objects: list, lives: int) -> tuple[dict, list]:
    """Today's build, as ``ObjectObservation._observe`` does it."""
    rows: list[tuple] = []
    obs = objects_to_dict(objects, plan, rows)
    if plan.game.derive is not None:
        plan.game.derive(obs, lives)
    return obs, rows


def outcome(make: Callable[[], tuple[dict, list]]) -> Any:
    """What a build gives, or the class of what it raised (both must raise alike on objects neither can build)."""
    try:
        return make()
    except Exception as error:  # noqa: BLE001 - compared, not hidden
        return ("raised", error.__class__)


_KINDS = (np.int64, np.uint8, np.int16, float, lambda v: v + 0.5, lambda v: bool(v % 2))
"""What a number of an object may come as: NumPy ints (OCAtari's own readers), floats, a bool."""


_EDGES = (-1, 0, 18, 79, 80, 159, 160, 209, 210, 255, 256)
"""Where a game's rules change (the screen's edges, Freeway's player-one bound, the lane tables' ends)."""


class Stranger(ram_objects.GameObject):
    """An object of a class no game has: its generic key among the game's own."""


def object_classes(game: Game) -> list[type]:
    """The classes of the game's OCAtari module that can be made without arguments, and :class:`Stranger`."""
    module = importlib.import_module(f"ocatari.ram.{game.ocatari_name.lower()}")
    classes = [Stranger]
    for value in vars(module).values():
        if not (isinstance(value, type) and issubclass(value, ram_objects.GameObject)
                and value.__module__ == module.__name__):
            continue
        try:
            value()
        except TypeError:
            continue
        classes.append(value)
    return classes


def perturbed(objects: list, rng: random.Random, classes: list[type]) -> list:
    """A copy of an OCAtari object list changed as no reader changes it, but as a builder must still take it: slots
    emptied (None, a NoObject), hidden or shown, moved anywhere (off screen, negative, to the edges of the games'
    rules), one number of an object (x, y, w, h or the previous x, y) of another kind (a NumPy int, a float, a
    bool), no previous position, slots swapped, an object of another of the game's classes or of one it does not
    have (``classes``) put in, and objects repeated past the numbered keys made in advance (64 per category)."""
    objs = [None if o is None else copy.copy(o) for o in objects]
    for i, o in enumerate(objs):
        if o is None or rng.random() > 0.35:
            continue
        change = rng.randrange(7)
        if change == 0:
            objs[i] = None
        elif change == 1:
            objs[i] = ram_objects.NoObject()
        elif change == 2:
            o._visible = not o._visible
        elif change == 3:
            o._xy = (rng.choice(_EDGES) if rng.random() < 0.5 else rng.randint(-300, 400),
                     rng.choice(_EDGES) if rng.random() < 0.5 else rng.randint(-300, 400))
        elif change == 4:
            o._prev_xy = None
        elif change == 5:
            numbers = [*o._xy, *o.wh, *(o._prev_xy or o._xy)]
            field = rng.randrange(len(numbers))
            numbers[field] = rng.choice(_KINDS)(int(numbers[field]) % 200)
            o._xy, o.wh = tuple(numbers[:2]), tuple(numbers[2:4])
            if o._prev_xy is not None or field >= 4:
                o._prev_xy = tuple(numbers[4:])
        else:
            other = rng.choice(classes)()
            other._xy, other._prev_xy = o._xy, o._prev_xy
            objs.insert(rng.randrange(len(objs) + 1), other)
    for _ in range(rng.randrange(3)):
        a, b = rng.randrange(len(objs)), rng.randrange(len(objs))
        objs[a], objs[b] = objs[b], objs[a]
    present = [o for o in objs if o is not None and o.__class__ is not ram_objects.NoObject]
    if present and rng.random() < 0.2:
        objs += [copy.copy(rng.choice(present)) for _ in range(rng.randrange(60, 140))]
    return objs


def _observer(env) -> ObjectObservation:
    while not isinstance(env, ObjectObservation):
        env = env.env
    return env


@pytest.mark.slow
@pytest.mark.parametrize(("game", "version"), CASES)
def test_played_and_perturbed_objects_build_the_observation_they_built_before(game, version):
    env = make_env(game, observation=version)
    observer = _observer(env)
    spec, ale = observer.game, env.unwrapped.ale
    oracle = Oracle(spec, version, observer._numbered)
    plan = ObservationPlan.of(spec, observer._numbered)
    classes = object_classes(spec)
    actions, rng = np.random.default_rng(0), random.Random(0)
    steps = lives_lost = raised = 0
    seed = 0
    try:
        while steps < STEPS:
            obs, _ = env.reset(seed=seed)
            lives = ale.lives()
            for step in range(EPISODE_STEPS):
                where = f"{game} v{version}, seed {seed}, step {step}"
                theirs, rows = oracle.build(observer._objects, lives)
                assert_same(obs, theirs, where)
                assert_same(observer.object_rows, rows, f"{where}, the step log's rows")
                if steps % PERTURB_EVERY == 0:
                    for k in range(PERTURBATIONS):
                        objs, n = perturbed(observer._objects, rng, classes), rng.choice((lives, 0, 5))
                        ours, theirs = outcome(lambda: build(plan, objs, n)), outcome(lambda: oracle.build(objs, n))
                        assert_same(ours, theirs, f"{where}, perturbation {k}")
                        raised += theirs[0] == "raised"
                obs, _, terminated, truncated, _ = env.step(int(actions.integers(spec.n_actions)))
                steps += 1
                lives_lost += ale.lives() < lives
                lives = ale.lives()
                if terminated or truncated or steps >= STEPS:
                    break
            seed += 1
    finally:
        env.close()
    assert seed >= 2 or steps >= STEPS
    if spec.lives:
        assert lives_lost, "no life was lost: the steps around a lost life were never compared"
    assert raised < STEPS // PERTURB_EVERY, "the perturbations mostly broke both builders: compared nothing"


@pytest.mark.slow
def test_a_game_swapped_into_an_environment_builds_its_own_observation():
    """``ObjectObservation.game`` replaced mid-game (bench/step_profile.py times a game's ``detect`` and ``derive``
    so): the next observation is built with the new game's hooks and lists, not the plan of the old one."""
    env = make_env("breakout")
    observer = _observer(env)
    env.reset(seed=0)
    for _ in range(20):
        env.step(0)
    observer.game = get_game("breakout").observing(1)
    obs, *_ = env.step(0)
    theirs, rows = Oracle(observer.game, 1, observer._numbered).build(observer._objects, env.unwrapped.ale.lives())
    assert_same(obs, theirs, "breakout v1 after v2")
    assert_same(observer.object_rows, rows, "breakout v1 after v2, rows")
    assert any(len(bricks) == 18 for bricks in obs.values() if isinstance(bricks, list)), "no 8-px bricks: still v2"
    env.close()


@pytest.mark.parametrize(("ours", "theirs"), [
    ({"x": 1}, {"x": np.int64(1)}),
    ({"x": 1}, {"x": True}),
    ({"x": 1}, {"x": 1.0}),
    ({"a": {}, "b": {}}, {"b": {}, "a": {}}),
    ({"Cars": [{"x": 1}, {"x": 2}]}, {"Cars": [{"x": 2}, {"x": 1}]}),
    ({"Player": {"x": 1, "lane": 0}}, {"Player": {"lane": 0, "x": 1}}),
    ([("Alien0", None, "Alien", 1)], [("Alien0", 0, "Alien", 1)]),
])
def test_the_comparison_tells_apart_what_a_policy_could(ours, theirs):
    """Not the same observation, equal under ``==`` or not: a NumPy int, a bool or a float for an int, another key
    order at any level, another list order, another row."""
    with pytest.raises(pytest.fail.Exception):
        assert_same(ours, theirs, "deliberately different")
    assert_same(ours, copy.deepcopy(ours), "the same")
