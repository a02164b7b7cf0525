"""The step log: what the store keeps of each observation, and that it rebuilds the dict the policy saw."""

from __future__ import annotations

import copy
import random

import pytest

from games import get_game, list_widths
from games.envs import make_env
from tracing.steps import StepLog, merge_runs, objects_to_obs


def _brick(x, y=57, w=8, h=6, dx=0, dy=0):
    return {"x": x, "y": y, "w": w, "h": h, "dx": dx, "dy": dy}


def _rebuilt(log: StepLog, widths) -> list[dict]:
    return [objects_to_obs(step["objects"], widths) for step in log.table().to_pylist()]


def test_adjacent_items_merge_into_runs_and_split_back():
    row = [_brick(8), _brick(16), _brick(24), _brick(40), _brick(48, y=58), _brick(56, w=5), _brick(61),
           _brick(69, dx=1)]
    runs = merge_runs("RB", row, 8)
    # 8-24 is one run; 40 stands alone (gap); 48 has another y; 56 has another width; 61 and 69 differ in dx
    assert [(r[1], r[3], r[5]) for r in runs] == [(0, 8, 24), (3, 40, 8), (4, 48, 8), (5, 56, 5), (6, 61, 8),
                                                 (7, 69, 8)]
    assert objects_to_obs([dict(zip(("key", "idx", "category", "x", "y", "w", "h", "dx", "dy"), r))
                           for r in runs], {"RB": 8})["RB"] == row


def test_list_keys_are_present_even_when_empty_and_other_lists_are_kept_item_by_item():
    log = StepLog({"RB": 8, "OB": 8})
    obs = {"Ball": _brick(1, w=2), "RB": [], "OB": [_brick(0), _brick(8)], "Misc": [_brick(0), _brick(8)]}
    log.append(0, obs, 1, 0.0, 0.0, False, False, 5)
    stored = log.table().to_pylist()[0]["objects"]
    assert [o["key"] for o in stored] == ["Ball", "OB", "Misc", "Misc"]  # Misc has no width: no merging
    assert _rebuilt(log, {"RB": 8, "OB": 8}) == [obs]


@pytest.mark.parametrize("game,observation", [("breakout", 2), ("breakout", 1), ("space_invaders", 2), ("pong", 2)])
def test_observations_rebuild_exactly_from_either_way_of_logging_them(game, observation):
    """The rows the environment makes along with each observation and the rows StepLog makes from the dict
    both rebuild the dict the policy saw, keys in the same order (the game's derived fields, Breakout's
    ``lives``, rebuilt by its ``derive``: the dict way takes observations without them). Breakout's bricks: one
    entry (and one stored row) per OCAtari Block, a run of adjacent bricks; under observation version 1, 8-pixel
    bricks stored as runs and split back."""
    spec = get_game(game).observing(observation)
    widths = list_widths(spec)
    env = make_env(spec)
    rng = random.Random(0)
    obs, info = env.reset(seed=0)
    from_env, from_dict, seen = StepLog(widths), StepLog(widths), []
    for step in range(1500):  # long enough for Breakout's ball to knock bricks out
        seen.append(copy.deepcopy(obs))
        from_env.observe(obs, env.object_rows)
        from_dict.observe({k: v for k, v in obs.items() if not isinstance(v, int)})
        action = rng.choice([0, 2, 3])
        lives = info.get("lives")  # as the episode's step row has them: when the observation was made
        obs, reward, terminated, truncated, info = env.step(action)
        for log in (from_env, from_dict):
            log.outcome(step, action, reward, 0.0, terminated, truncated, lives)
        if terminated or truncated:
            break
    env.close()
    for log in (from_env, from_dict):
        rebuilt = _rebuilt(log, widths)
        if spec.derive is not None:
            for o, lives in zip(rebuilt, log.scalars["lives"]):
                spec.derive(o, lives)
        assert rebuilt == seen
        assert [list(o) for o in rebuilt] == [list(o) for o in seen]
    if game == "breakout":
        rows = ("RB", "OB", "YB", "GB", "AB", "BB")
        bricks = [sum(b["w"] // 8 for row in rows for b in o.get(row, [])) for o in seen]
        assert bricks[0] == 108 and min(bricks) < 108, "the test must see bricks knocked out"
        for log in (from_env, from_dict):
            first = log.table().to_pylist()[0]["objects"]
            assert [(o["key"], o["w"]) for o in first if o["key"] in rows] == [(row, 144) for row in rows]
        entries = [sum(len(o.get(row, [])) for row in rows) for o in seen]
        if observation == 1:
            assert all(b["w"] == 8 for o in seen for row in rows for b in o[row]) and entries == bricks
        else:
            assert entries[0] == 6 and max(entries) < min(bricks), "one entry per run of bricks"
            assert any(b["w"] not in (8, 144) for o in seen for row in rows for b in o.get(row, []))
