"""The step log: what the store keeps of each observation, and that it rebuilds the dict the policy saw."""

from __future__ import annotations

import copy
import random

import pytest

from games import list_widths
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


@pytest.mark.parametrize("game", ["breakout", "space_invaders", "pong"])
def test_observations_rebuild_exactly_from_either_way_of_logging_them(game):
    """The rows the environment makes along with each observation and the rows StepLog makes from the dict
    both rebuild the dict the policy saw; Breakout's bricks are stored as runs."""
    widths = list_widths(game)
    env = make_env(game)
    rng = random.Random(0)
    obs, _ = env.reset(seed=0)
    from_env, from_dict, seen = StepLog(widths), StepLog(widths), []
    for step in range(1500):  # long enough for Breakout's ball to knock bricks out
        seen.append(copy.deepcopy(obs))
        from_env.observe(obs, env.object_rows)
        from_dict.observe(obs)
        action = rng.choice([0, 2, 3])
        obs, reward, terminated, truncated, info = env.step(action)
        for log in (from_env, from_dict):
            log.outcome(step, action, reward, 0.0, terminated, truncated, info.get("lives"))
        if terminated or truncated:
            break
    env.close()
    assert _rebuilt(from_env, widths) == seen
    assert _rebuilt(from_dict, widths) == seen
    if game == "breakout":
        bricks = [sum(len(o[row]) for row in widths) for o in seen]
        assert bricks[0] == 108 and min(bricks) < 108, "the test must see bricks knocked out"
        for log in (from_env, from_dict):
            first = log.table().to_pylist()[0]["objects"]
            assert sum(o["key"] in widths for o in first) == 6  # six full rows: six runs, not 108 bricks
