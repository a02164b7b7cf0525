"""Per-step capture of a rollout: action, reward, score, flags, lives and the whole object observation.

:class:`StepLog` appends one row per environment step into column lists and turns them into an Arrow table
(``STEP_SCHEMA``) at the end of the episode, so the store receives one batched insert, never row by row.

A step is logged before the policy sees its observation (:meth:`StepLog.observe`) and completed after
(:meth:`StepLog.outcome`). The observation is stored twice over: typed hot columns (``player_x/y``, ``ball_x/y``; NULL when absent) for
quick SQL, and ``objects``, a list of ``{key, idx, category, x, y, w, h, dx, dy}`` structs that holds the
whole dict: ``key`` is the observation key (``Ball``, ``Alien3``, ``RB``), ``idx`` the position inside a list
value (Breakout's brick rows) or NULL, ``category`` the key without its trailing number. :func:`objects_to_obs`
rebuilds the exact dict the policy saw.
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
    """Column lists for the steps of one episode (see the module docstring).

    A step is logged in two calls: :meth:`observe` before the policy runs (so a policy that mutates the
    observation cannot alter what is stored) and :meth:`outcome` once the action's effect is known.
    """

    def __init__(self) -> None:
        self.scalars: dict[str, list] = {name: [] for name in STEP_SCHEMA.names if name != "objects"}
        self.offsets: list[int] = [0]
        self.objects: dict[str, list] = {name: [] for name in OBJECT_TYPE.names}

    def __len__(self) -> int:
        return len(self.scalars["step"])

    def observe(self, obs: Mapping[str, Any]) -> None:
        """Flatten the observation of the next step into the object columns."""
        s = self.scalars
        player, ball = obs.get("Player"), obs.get("Ball")
        s["player_x"].append(player["x"] if player else None)
        s["player_y"].append(player["y"] if player else None)
        s["ball_x"].append(ball["x"] if ball else None)
        s["ball_y"].append(ball["y"] if ball else None)
        o = self.objects
        keys, idxs, cats = o["key"], o["idx"], o["category"]
        xs, ys, ws, hs, dxs, dys = (o[f] for f in OBJECT_FIELDS)
        n = 0
        for key, value in obs.items():
            category = category_of(key)
            items: Iterable = enumerate(value) if type(value) is list else ((-1, value),)
            for idx, obj in items:
                keys.append(key)
                idxs.append(idx)
                cats.append(category)
                xs.append(obj["x"])
                ys.append(obj["y"])
                ws.append(obj["w"])
                hs.append(obj["h"])
                dxs.append(obj["dx"])
                dys.append(obj["dy"])
                n += 1
        self.offsets.append(self.offsets[-1] + n)

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

    def table(self) -> pa.Table:
        n = len(self)
        if len(self.offsets) - 1 != n:
            raise RuntimeError(f"StepLog has {len(self.offsets) - 1} observations for {n} steps")
        columns = [pa.array(self.scalars[name], type=STEP_SCHEMA.field(name).type) for name in self.scalars]
        o = self.objects
        idx = np.asarray(o["idx"], dtype=np.int16)
        children = [
            pa.array(o["key"], type=pa.string()),
            pa.array(idx, mask=idx < 0),
            pa.array(o["category"], type=pa.string()),
        ] + [_int16(o[f]) for f in OBJECT_FIELDS]
        structs = pa.StructArray.from_arrays(children, fields=list(OBJECT_TYPE))
        objects = pa.ListArray.from_arrays(pa.array(self.offsets, type=pa.int32()), structs)
        return pa.Table.from_arrays(columns + [objects], schema=STEP_SCHEMA)


def objects_to_obs(objects: Iterable[Mapping[str, Any]] | None, list_keys: Iterable[str] = ()) -> dict[str, Any]:
    """Rebuild an observation dict from the ``objects`` column of one step.

    ``list_keys`` are keys whose value is always a list, even when empty (Breakout's brick rows; an empty
    list leaves no object rows behind).
    """
    obs: dict[str, Any] = {key: [] for key in list_keys}
    for o in objects or ():
        value = {f: o[f] for f in OBJECT_FIELDS}
        if o["idx"] is None:
            obs[o["key"]] = value
        else:
            obs.setdefault(o["key"], []).append(value)
    return obs
