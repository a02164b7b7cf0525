"""The environments as Gymnasium sees them: ``check_env`` passes, the registered ids play with the protocol's
kwargs, and the observation spaces are exact (they hold what the env returns and reject what it never does)."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
import pickle
import re
import subprocess
import sys
import warnings

import gymnasium as gym
import pytest
from gymnasium.utils.env_checker import check_env

from games import GAMES, get_game
from tests.conftest import ROOT
from games.envs import gym_id, make_env
from games.spaces import ObjectDict, observation_space

GENERIC = "riverraid"
CHECKED = [*GAMES, GENERIC]
WRAPPED = "is different from the unwrapped version"
"""check_env's one warning for any wrapped env: the object observation is a wrapper of ALE's RAM env."""


def _first_observation(game: str, steps: int = 0, action: int = 0) -> dict:
    env = make_env(game)
    obs, _ = env.reset(seed=0)
    for _ in range(steps):
        obs, *_ = env.step(action)
    env.close()
    return obs


@pytest.mark.parametrize("game", CHECKED)
def test_check_env_passes(game):
    env = gym.make(gym_id(game))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    env.close()
    assert isinstance(env.observation_space, ObjectDict)
    assert [str(w.message) for w in caught if WRAPPED not in str(w.message)] == []


def test_a_registered_id_plays_with_the_protocol_kwargs():
    env = gym.make("codearcade/Breakout-v0", sticky=0.25, noop_max=30, one_life=True)
    assert env.unwrapped.ale.getFloat("repeat_action_probability") == 0.25
    assert env.spec.max_episode_steps == get_game("breakout").task.eval_max_steps
    obs, info = env.reset(seed=1)
    lives = info["lives"]
    steps = 0
    terminated = truncated = False
    while not (terminated or truncated):
        assert obs in env.observation_space
        obs, reward, terminated, truncated, info = env.step(0)  # NOOP: the ball is missed
        steps += 1
    env.close()
    assert terminated and info["lives"] == lives - 1, "one_life ends the episode at the first lost life"
    assert {"Player", "RB", "BB"} <= set(obs)


def test_a_registered_id_is_the_env_codearcade_plays():
    env = gym.make("codearcade/SpaceInvaders-v0")
    ours = make_env("space_invaders")
    for e in (env, ours):
        e.reset(seed=3)
    actions = [1, 2, 3, 4, 5] * 20
    for action in actions:
        assert env.step(action) == ours.step(action)
    env.close()
    ours.close()


def test_the_module_prefixed_id_needs_no_import():
    """Gymnasium's own convention for environments of a package it does not know: ``gym.make("MODULE:ID")``
    imports the module that registers them, so RL code needs no ``import games.envs`` of its own."""
    code = ("import gymnasium as gym; env = gym.make('games.envs:codearcade/Pong-v0'); obs, _ = env.reset(seed=0); "
            "print(env.spec.entry_point, obs in env.observation_space, type(obs).__name__, env.spec.id)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout
    assert out.split() == ["games.envs:make_registered", "True", "dict", "codearcade/Pong-v0"]


def test_import_games_stays_free_of_gymnasium():
    """Registration happens in games.envs; policy workers and the CLI import games alone."""
    code = "import sys, games; print(sorted({'gymnasium', 'games.envs', 'games.spaces'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("game", CHECKED)
def test_samples_are_members_and_the_space_pickles(game):
    space = observation_space(get_game(game))
    space.seed(7)
    samples = [space.sample() for _ in range(20)]
    assert all(s in space for s in samples)
    again = observation_space(get_game(game))
    again.seed(7)
    assert repr([again.sample() for _ in range(20)]) == repr(samples), "seeded samples repeat"
    assert pickle.loads(pickle.dumps(space)) == space


def test_space_invaders_space_rejects_what_the_env_never_returns():
    obs = _first_observation("space_invaders")
    space = observation_space(get_game("space_invaders"))
    assert obs in space and "Alien35" in obs

    def rejected(change):
        changed = copy.deepcopy(obs)
        change(changed)
        return changed not in space

    assert rejected(lambda o: o.pop("Alien3")), "a gap in the numbering"
    assert rejected(lambda o: o.update(Alien36=o["Alien0"])), "more aliens than OCAtari has slots"
    assert rejected(lambda o: o.update(Ufo=o["Alien0"])), "a category the game does not have"
    assert rejected(lambda o: o["Player"].update(x=1.5)), "a float coordinate"
    assert rejected(lambda o: o["Player"].update(lane=1)), "a field objects do not have"
    assert rejected(lambda o: o["Player"].pop("dy")), "a missing field"
    assert not rejected(lambda o: [o.pop(f"Alien{i}") for i in range(30, 36)]), "the last aliens shot"


def test_derived_fields_are_exact():
    asterix = observation_space(get_game("asterix"))
    obs = _first_observation("asterix", steps=40)
    assert obs in asterix
    for key, bad in [("enemy_lanes", [3, 3]), ("enemy_lanes", [4, 2]), ("enemy_lanes", (2,)), ("enemy_lanes", [8]),
                     ("lives", -1)]:
        assert {**obs, key: bad} not in asterix, (key, bad)
    present = next(key for key in ("Enemies", "Consumables", "Rewards") if key in obs)  # StopIteration: none
    assert {**obs, present: []} not in asterix, "an empty group is absent, never an empty list"
    item = obs[present][0]
    assert {**obs, present: [{**item, "type": "Lyre"}]} not in asterix
    assert {**obs, present: [{**item, "dist": 9}, {**item, "dist": 3}]} not in asterix, "nearest first"

    enduro = observation_space(get_game("enduro"))
    cars = _first_observation("enduro", steps=200, action=1)
    assert cars in enduro and "EnemyCars" in cars
    assert {k: v for k, v in cars.items() if k != "nearest_enemy_rel_x"} not in enduro, "present together"

    qbert = observation_space(get_game("qbert"))
    player = {"x": 77, "y": 40, "w": 8, "h": 20, "dx": 0, "dy": 0}
    assert {"lives": 4, "Player": player} in qbert
    assert {"lives": 4, "Player": {**player, "y": -40}} not in qbert, "off screen: dropped by derive"


def test_breakout_rows_take_single_bricks_and_merged_runs():
    """A row entry is one 8-px brick or one OCAtari Block (a run of n bricks, w = 8n)."""
    space = observation_space(get_game("breakout"))
    obs = _first_observation("breakout")
    assert obs in space
    bricks = sorted(obs["RB"], key=lambda b: b["x"])
    merged = {**bricks[0], "w": sum(b["w"] for b in bricks)}
    assert merged["w"] == 144 and {**obs, "RB": [merged]} in space
    assert {**obs, "RB": [{**merged, "w": 12}]} not in space
    assert {**obs, "RB": [{**merged, "w": 152}]} not in space
    assert {**obs, "RB": [{**merged, "y": 63}]} not in space, "a brick at another row's y"
    assert {**obs, "RB": bricks[:1] * 18} in space
    assert {**obs, "RB": bricks[:1] * 19} not in space, "more than a row holds"


def test_a_game_that_changes_its_observation_must_declare_its_space():
    """... when a space is asked for: a game module from outside without one still plays in codearcade."""
    game = dataclasses.replace(get_game("asterix"), derive_space=None)
    env = make_env(game)
    obs, _ = env.reset(seed=0)
    assert "lives" in obs
    with pytest.raises(TypeError, match="declares no derive_space: add Game"):
        env.observation_space
    env.close()


def test_the_documented_example_prints_what_it_says():
    """docs/games.md, section Environments: the example runs as printed; each ``print`` line's comment is its
    output."""
    section = (ROOT / "docs" / "games.md").read_text().split("\n## Environments\n", 1)[1].split("\n## ", 1)[0]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    expected = [line.split("  # ", 1)[1] for line in code.splitlines() if line.startswith("print(")]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "docs/games.md", "exec"), {})
    assert out.getvalue().splitlines() == expected
