"""Per-step capture of a rollout: action, reward, score, flags, lives and the whole object observation.

:class:`StepLog` appends one row per environment step (scalars into column lists, objects as tuples) and turns them into an Arrow table
(``STEP_SCHEMA``) at the end of the episode, so the store receives one batched insert, never row by row.

A step is logged before the policy sees its observation (:meth:`StepLog.observe`) and completed after
(:meth:`StepLog.outcome`). The observation is stored twice over: typed hot columns (``player_x/y``,
``ball_x/y``: the objects each game names in ``Game.hot_keys``; NULL when absent) for quick SQL, and
``objects``, a list of ``{key, idx, category, x, y, w, h, dx, dy}`` structs that holds the whole dict: ``key``
is the observation key (``Ball``, ``Alien3``, ``RB``), ``idx`` the position inside a list value (Breakout's
brick rows) or NULL, ``category`` the key without its trailing number. Each entry of a list is one row, as it
is: Breakout's entries are OCAtari's Blocks, runs of adjacent bricks (a full wall is 6 rows). A list of
equal-width items (``list_widths``: Breakout's 8-pixel bricks under observation version 1) is stored with
each run of adjacent items as one row (``idx`` its first item, ``w`` the items' width times their number) and
split back when read with the same ``list_widths``; without them nothing is split.
:func:`objects_to_obs` rebuilds the exact dict the policy saw, keys in the same order.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping

import numpy as np
import pyarrow as pa

OBJECT_FIELDS = ("x", "y", "w", "h", "dx", "dy")
OBJECT_TYPE = pa.struct(
    [("key", pa.string()), ("idx", pa.int16()), ("category", pa.string())]
    + [(f, pa.int16()) for f in OBJECT_FIELDS]
)
STEP_SCHEMA = pa.schema(
    [
        ("step", pa.int32()),
        ("action", pa.int16()),
        ("reward", pa.float64()),
        ("score", pa.float64()),
        ("terminated", pa.bool_()),
        ("truncated", pa.bool_()),
        ("lives", pa.int16()),
        ("player_x", pa.int16()),
        ("player_y", pa.int16()),
        ("ball_x", pa.int16()),
        ("ball_y", pa.int16()),
        ("objects", pa.list_(OBJECT_TYPE)),
    ]
)
"""Columns a StepLog produces; the store adds ``episode_id``."""
_WIDTH = len(OBJECT_TYPE)

_CATEGORY_CACHE: dict[str, str] = {}


def category_of(key: str) -> str:
    """``Alien12`` -> ``Alien``; ``Ball`` -> ``Ball``; ``RB`` -> ``RB``."""
    category = _CATEGORY_CACHE.get(key)
    if category is None:
        category = _CATEGORY_CACHE[key] = key.rstrip("0123456789") or key
    return category


def _int16(values: list[int]) -> pa.Array:
    """Python ints as int16, saturating: OCAtari can report garbage far off screen (a 160x210 screen fits)."""
    return pa.array(np.clip(np.asarray(values, dtype=np.int64), -32768, 32767).astype(np.int16))


class StepLog:
    """Rows of the steps of one episode (see the module docstring).

    A step is logged in two calls: :meth:`observe` before the policy runs (so a policy that mutates the
    observation cannot alter what is stored) and :meth:`outcome` once the action's effect is known.
    ``list_widths`` names the observation keys whose value is a list of equal-width items (Breakout's brick
    rows) with that width: adjacent items of such a list are stored as one run (see :func:`merge_runs`).
    """

    def __init__(self, list_widths: Mapping[str, int] | None = None, player_key: str = "Player",
                 ball_key: str | None = "Ball") -> None:
        self.scalars: dict[str, list] = {name: [] for name in STEP_SCHEMA.names if name != "objects"}
        self.offsets: list[int] = [0]
        """Objects stored before each step (and in all, last)."""
        self.flat: list = []
        """The stored objects' fields, ``OBJECT_TYPE`` order, one object after another. A flat list of ints and
        strings, not a tuple per object: tuples kept alive for the whole episode made the cyclic garbage
        collector run ever more often and walk them all (12% of a Space Invaders episode)."""
        self.list_widths = dict(list_widths or {})
        self.player_key, self.ball_key = player_key, ball_key
        """The observation keys whose positions fill the hot columns ``player_x/y`` and ``ball_x/y``."""

    def __len__(self) -> int:
        return len(self.scalars["step"])

    def observe(self, obs: Mapping[str, Any], rows: Iterable[tuple] | None = None) -> None:
        """Flatten the observation of the next step into object rows.

        ``rows``, when the environment made them along with ``obs`` (``games.envs.ObjectObservation``),
        are taken as they are instead of walking the dict again (a tenth of the time of a Space Invaders
        step): ``OBJECT_TYPE`` tuples that :func:`objects_to_obs` turns back into ``obs``.
        """
        s = self.scalars
        player, ball = obs.get(self.player_key), obs.get(self.ball_key)
        s["player_x"].append(player["x"] if player else None)
        s["player_y"].append(player["y"] if player else None)
        s["ball_x"].append(ball["x"] if ball else None)
        s["ball_y"].append(ball["y"] if ball else None)
        flat = self.flat
        if rows is None:
            rows = []
            for key, value in obs.items():
                if type(value) is list:
                    width = self.list_widths.get(key)
                    if width is None:
                        category = category_of(key)
                        rows.extend((key, idx, category, o["x"], o["y"], o["w"], o["h"], o["dx"], o["dy"])
                                    for idx, o in enumerate(value))
                    else:
                        rows.extend(merge_runs(key, value, width))
                else:
                    rows.append((key, None, category_of(key), value["x"], value["y"], value["w"], value["h"],
                                 value["dx"], value["dy"]))
        for row in rows:
            flat.extend(row)
        self.offsets.append(len(flat) // _WIDTH)

    def outcome(
        self,
        step: int,
        action: int | None,
        reward: float,
        score: float,
        terminated: bool,
        truncated: bool,
        lives: int | None,
    ) -> None:
        """Complete the step whose observation was last observed (``action`` None: the policy failed)."""
        s = self.scalars
        s["step"].append(step)
        s["action"].append(action)
        s["reward"].append(reward)
        s["score"].append(score)
        s["terminated"].append(terminated)
        s["truncated"].append(truncated)
        s["lives"].append(lives)

    def append(self, step: int, obs: Mapping[str, Any], action: int | None, reward: float, score: float,
               terminated: bool, truncated: bool, lives: int | None) -> None:
        """Both halves at once."""
        self.observe(obs)
        self.outcome(step, action, reward, score, terminated, truncated, lives)

    def object_columns(self, start: int = 0, stop: int | None = None) -> dict[str, list]:
        """The object rows of steps ``start <= step < stop`` as one list per ``OBJECT_TYPE`` field."""
        stop = len(self.offsets) - 1 if stop is None else stop
        flat = self.flat[self.offsets[start] * _WIDTH:self.offsets[stop] * _WIDTH]
        return {name: flat[i::_WIDTH] for i, name in enumerate(OBJECT_TYPE.names)}

    def table(self) -> pa.Table:
        n = len(self)
        if len(self.offsets) - 1 != n:
            raise RuntimeError(f"StepLog has {len(self.offsets) - 1} observations for {n} steps")
        columns = [pa.array(self.scalars[name], type=STEP_SCHEMA.field(name).type) for name in self.scalars]
        o = self.object_columns()
        children = [pa.array(o["key"], type=pa.string()), pa.array(o["idx"], type=pa.int16()),
                    pa.array(o["category"], type=pa.string())] + [_int16(o[f]) for f in OBJECT_FIELDS]
        structs = pa.StructArray.from_arrays(children, fields=list(OBJECT_TYPE))
        objects = pa.ListArray.from_arrays(pa.array(self.offsets, type=pa.int32()), structs)
        return pa.Table.from_arrays(columns + [objects], schema=STEP_SCHEMA)


def merge_runs(key: str, items: list[Mapping[str, Any]], width: int) -> list[tuple]:
    """Object rows for a list of equal-width items, each run of adjacent ones as a single row.

    A run is a row whose ``idx`` is the position of its first item and whose ``w`` is ``width`` times its
    number of items: a full Breakout brick row is one object, not 18 (12x fewer rows to write and store).
    Items join a run only when they continue it exactly (same y, h, dx, dy; width ``width``; x right after
    it), so :func:`objects_to_obs` splits it back into the same items.
    """
    rows: list[tuple] = []
    run: list | None = None  # [idx, x, y, w, h, dx, dy] of the run being extended
    for idx, o in enumerate(items):
        x, y, w, h, dx, dy = o["x"], o["y"], o["w"], o["h"], o["dx"], o["dy"]
        if (run is not None and w == width and x == run[1] + run[3] and y == run[2] and h == run[4]
                and dx == run[5] and dy == run[6]):
            run[3] += w
            continue
        if run is not None:
            rows.append((key, run[0], key, *run[1:]))
            run = None
        if w == width:
            run = [idx, x, y, w, h, dx, dy]
        else:  # not an item of the list's width: stored as it is
            rows.append((key, idx, key, x, y, w, h, dx, dy))
    if run is not None:
        rows.append((key, run[0], key, *run[1:]))
    return rows


def objects_to_obs(objects: Iterable[Mapping[str, Any]] | None,
                   list_widths: Mapping[str, int] | None = None) -> dict[str, Any]:
    """Rebuild an observation dict from the ``objects`` column of one step.

    ``list_widths`` (as given to :class:`StepLog`) names the keys whose value is always a list, even when
    empty (an empty list leaves no object rows behind), with the width of their items: a stored run wider than
    that is split back into its items. Rows written before runs were merged (one per item) read the same.
    """
    list_widths = list_widths or {}
    obs: dict[str, Any] = {key: [] for key in list_widths}
    for o in objects or ():
        key = o["key"]
        value = {f: o[f] for f in OBJECT_FIELDS}
        if o["idx"] is None:
            obs[key] = value
            continue
        items = obs.setdefault(key, [])
        width = list_widths.get(key)
        w = value["w"]
        if width is None or w <= width or w % width:
            items.append(value)
        else:
            items.extend({**value, "x": value["x"] + i * width, "w": width} for i in range(w // width))
    return obs
