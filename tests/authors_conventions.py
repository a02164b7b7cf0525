"""The authors' observations, rebuilt by rules of our own from what their environments do, for comparison.

For each curated game, :data:`AUTHORS` maps it to a function that turns OCAtari's object slots (the list our
environment detected at a step) into the observation the authors' environment would have built from them
(``trace_envs/<game>.py`` and ``breakout_training.py`` of ameliakuang/LLM-Game-Playing-Agents, as read in
docs/observations.md). It follows their rules, not their code: which categories they skip, how they group,
number, order and sort, which fields they copy, and what they add (``lives``, and the previous step's
``reward``, every game). Only OCAtari's ``NoObject`` placeholders and empty slots are skipped, as theirs do; an
object OCAtari marks invisible is kept, as theirs keeps it.

:func:`as_decided` then applies codearcade's documented decisions where it builds something else on purpose
(the table in docs/observations.md), and :func:`differences` compares what is left with codearcade's
observation: the same keys in the same order, the same entries in the same order, the same values of every
field the authors have (ours may add fields, declared keys and trailing entries of declared types).
"""

from __future__ import annotations

from typing import Any, Callable

BOX = ("x", "y", "w", "h", "dx", "dy")
SCREEN_W, SCREEN_H = 160, 210


def _category(o: Any) -> str:
    return "NoObject" if o is None else type(o).__name__


def _box(o: Any, fields: tuple[str, ...] = BOX) -> dict[str, Any]:
    """Their ``{"x": object.x, ...}``: OCAtari's properties (dx, dy: the move since the last detection)."""
    x, y = int(o._xy[0]), int(o._xy[1])
    prev = o._prev_xy if o._prev_xy is not None else o._xy
    values = {"x": x, "y": y, "w": int(o.wh[0]), "h": int(o.wh[1]), "dx": x - int(prev[0]), "dy": y - int(prev[1])}
    entry = {f: values[f] for f in fields}
    if not o._visible:
        entry["_invisible"] = True  # a marker for as_decided; theirs has no such field
    return entry


def _present(objects: list) -> list:
    """Their loops skip OCAtari's placeholders: ``category == "NoObject"`` and, where slots can be None, None."""
    return [o for o in objects if _category(o) != "NoObject"]


def pong(objects: list, lives: int) -> dict:
    # their Pong loop skips nothing: a NoObject slot (the ball between points) becomes a "NoObject" key
    return {_category(o): _box(o) for o in objects if o is not None}


BREAKOUT_ROWS = {57: "RB", 63: "OB", 69: "YB", 75: "GB", 81: "AB", 87: "BB"}


def breakout(objects: list, lives: int) -> dict:
    obs: dict[str, Any] = {}
    rows: dict[str, list] = {key: [] for key in BREAKOUT_ROWS.values()}
    for o in _present(objects):
        if _category(o) == "Block":
            key = BREAKOUT_ROWS.get(int(o._xy[1]))
            if key is not None:
                rows[key].append(_box(o, ("x", "y", "w", "h")))  # a Block unchanged: a run of bricks, w = 8 * n
        else:
            obs[_category(o)] = _box(o)
    obs.update((key, bricks) for key, bricks in rows.items() if bricks)
    obs["lives"] = lives
    return obs


def space_invaders(objects: list, lives: int) -> dict:
    obs: dict[str, Any] = {}
    counts: dict[str, int] = {}
    for o in _present(objects):
        category = _category(o)
        if category in ("Alien", "Shield", "Bullet"):
            counts[category] = counts.get(category, -1) + 1
            obs[f"{category}{counts[category]}"] = _box(o)
        else:
            obs[category] = _box(o)
    return obs


def asterix(objects: list, lives: int) -> dict:
    obs: dict[str, Any] = {}
    groups: dict[str, list] = {"Enemy": [], "Consumable": [], "Reward": []}
    player = None
    for o in _present(objects):
        category = _category(o)
        if category == "Player":
            player = _box(o, ("x", "y"))
            obs["Player"] = player
        elif category in groups:
            groups[category].append({**_box(o, ("x", "y")), "type": category})
    if player is not None:  # nearest first, by Manhattan distance; a stable sort
        for items in groups.values():
            items.sort(key=lambda i: abs(i["x"] - player["x"]) + abs(i["y"] - player["y"]))
    for category, key in (("Enemy", "Enemies"), ("Consumable", "Consumables"), ("Reward", "Rewards")):
        if groups[category]:
            obs[key] = groups[category]
    obs["lives"] = lives
    return obs


def enduro(objects: list, lives: int) -> dict:
    obs: dict[str, Any] = {}
    cars = []
    player = None
    for o in _present(objects):
        if _category(o) == "Player":
            player = obs["Player"] = _box(o, ("x", "y", "w", "h"))
        elif _category(o) == "Car":
            cars.append(_box(o, ("x", "y", "w", "h")))
    if player is not None:
        for car in cars:
            car["rel_x"], car["rel_y"] = car["x"] - player["x"], car["y"] - player["y"]
        cars.sort(key=lambda c: -c["y"])
    if cars:
        obs["EnemyCars"] = cars
        obs["nearest_enemy_rel_x"], obs["nearest_enemy_rel_y"] = cars[0]["rel_x"], cars[0]["rel_y"]
    return obs


def freeway(objects: list, lives: int) -> dict:
    obs: dict[str, Any] = {}
    cars = []
    for o in _present(objects):
        if _category(o) == "Chicken" and o._xy[0] < 80:  # player 1's chicken only
            obs["Chicken"] = _box(o)
        elif _category(o) == "Car":
            cars.append(_box(o))
    if cars:
        cars.sort(key=lambda c: c["y"])
        obs["Cars"] = cars
    return obs


def qbert(objects: list, lives: int) -> dict:
    obs: dict[str, Any] = {}
    enemies, friendlies, disks = [], [], []
    for o in _present(objects):
        category = _category(o)
        if category == "Player":
            obs["Player"] = _box(o)
        elif category in ("Coily", "PurpleBall", "RedBall"):
            enemies.append({**_box(o), "type": category})
        elif category in ("Sam", "GreenBall"):
            friendlies.append({**_box(o), "type": category})
        elif category == "Disk":
            disks.append(_box(o, ("x", "y", "w", "h")))
    for key, items in (("Enemies", enemies), ("Friendlies", friendlies), ("Disks", disks)):
        if items:
            obs[key] = items
    obs["lives"] = lives
    return obs


def seaquest(objects: list, lives: int) -> dict:
    obs: dict[str, Any] = {}
    enemies, divers = [], []
    for o in _present(objects):
        category = _category(o)
        if category == "Player":
            obs["Player"] = _box(o)
        elif category in ("Shark", "Submarine", "EnemyMissile"):
            enemies.append({**_box(o), "type": category})
        elif category == "Diver":
            divers.append(_box(o))
    if enemies:
        obs["Enemies"] = enemies
    if divers:
        obs["Divers"] = divers
    obs["lives"] = lives
    return obs


AUTHORS: dict[str, Callable[[list, int], dict]] = {
    "pong": pong, "breakout": breakout, "space_invaders": space_invaders, "asterix": asterix, "enduro": enduro,
    "freeway": freeway, "qbert": qbert, "seaquest": seaquest,
}


def authors_observation(game: str, objects: list, lives: int, previous_reward: float) -> dict:
    """The authors' observation of a step: their rules on OCAtari's slots, then their ``reward``."""
    obs = AUTHORS[game](objects, lives)
    obs["reward"] = previous_reward
    return obs


# --- codearcade's decisions where it builds something else (docs/observations.md) ----------------------------

OURS_ONLY_KEYS = {
    "asterix": {"enemy_lanes", "safe_collectible_lanes"},   # promised by their instruction, never computed
    "seaquest": {"oxygen", "divers_collected"},             # asked for by their instruction
}
"""Keys codearcade adds (derived); every other key of ours must be one of theirs."""
OURS_ONLY_ENTRIES = {"seaquest": ("Enemies", "SurfaceSubmarine")}
"""A list of ours may end with entries of this ``type`` that theirs lacks (their fork had no such category)."""


def _on_screen(entry: dict) -> bool:
    return 0 <= entry["x"] < SCREEN_W and 0 <= entry["y"] < SCREEN_H


def as_decided(game: str, theirs: dict) -> dict:
    """Their observation with codearcade's documented decisions applied (each names its row of the table)."""
    obs = dict(theirs)
    obs.pop("reward")      # the previous step's reward: not in ours (every step's reward is in the trace)
    obs.pop("NoObject", None)  # Pong: an absent object is an absent key, never a placeholder
    if game == "space_invaders":  # an object OCAtari marks invisible is not on screen: absent, numbering dense
        counts: dict[str, int] = {}
        kept = {}
        for key, entry in obs.items():
            if entry.get("_invisible"):
                continue
            category = key.rstrip("0123456789")
            if category != key:
                counts[category] = counts.get(category, -1) + 1
                key = f"{category}{counts[category]}"
            kept[key] = entry
        obs = kept
    if game == "qbert":  # OCAtari's off-screen garbage (a falling Q*bert, a stale GreenBall) is dropped
        if "Player" in obs and not _on_screen(obs["Player"]):
            del obs["Player"]
        for key in ("Enemies", "Friendlies", "Disks"):
            if key in obs:
                obs[key] = [e for e in obs[key] if _on_screen(e)]
                if not obs[key]:
                    del obs[key]
    if game == "freeway" and "Cars" in obs:  # a car's dx with the screen wrap folded out
        obs["Cars"] = [{**car, "dx": (car["dx"] + 80) % 160 - 80} for car in obs["Cars"]]
    return obs


def differences(game: str, ours: dict, theirs: dict) -> list[str]:
    """Where ``ours`` is not ``theirs`` (already :func:`as_decided`), in words; empty when it is."""
    found = []
    shared = [key for key in ours if key in theirs]
    if shared != [key for key in theirs if key in ours]:
        found.append(f"key order: ours {shared}, theirs {list(theirs)}")
    found += [f"missing key {key}" for key in theirs if key not in ours]
    extra_key, extra_type = OURS_ONLY_ENTRIES.get(game, (None, None))
    for key in ours:
        if key in theirs or key in OURS_ONLY_KEYS.get(game, ()):
            continue
        if key == extra_key and all(e.get("type") == extra_type for e in ours[key]):
            continue  # a list of ours with only entries theirs lacks
        found.append(f"extra key {key}")
    for key in shared:
        mine, their = ours[key], theirs[key]
        if isinstance(their, list):
            tail = mine[len(their):]
            if key != extra_key and tail or any(e.get("type") != extra_type for e in tail):
                found.append(f"{key}: extra entries {tail}")
            pairs = list(zip(mine, their))
            if len(mine) < len(their):
                found.append(f"{key}: {len(mine)} entries, theirs {len(their)}")
        else:
            pairs = [(mine, their)]
        for m, t in pairs:
            if isinstance(t, dict):
                if not isinstance(m, dict) or {f: m.get(f) for f in t if f != "_invisible"} != \
                        {f: v for f, v in t.items() if f != "_invisible"}:
                    found.append(f"{key}: ours {m}, theirs {t}")
            elif m != t:
                found.append(f"{key}: ours {m!r}, theirs {t!r}")
    return found
