"""The environments: paper settings, the observation conventions of each game, auto-fire, protocols."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest

from games import GAMES, UnknownGameError, get_game
from games.breakout import ROWS as BREAKOUT_ROWS
from games.breakout import ball_in_play
from games.envs import make_env, written_globals
from games.wrappers import AutoFire, ServeAgain
from games.spaces import observation_space
from tests.conftest import ROOT

FIELDS = {"x", "y", "w", "h", "dx", "dy"}


def _play(game: str, actions, steps: int, **kwargs):
    env = make_env(game, **kwargs)
    obs, info = env.reset(seed=0)
    seen = [obs]
    infos = [info]
    for i in range(steps):
        obs, reward, terminated, truncated, info = env.step(actions[i % len(actions)])
        seen.append(obs)
        infos.append(info)
        if terminated or truncated:
            break
    env.close()
    return seen, infos


def _objects(obs):
    """Every object of an observation (a dict, alone or in a list); derived values that are not objects
    (``lives``, ``enemy_lanes``, ``oxygen``) are skipped."""
    for key, value in obs.items():
        for o in value if isinstance(value, list) else [value]:
            if isinstance(o, dict):
                yield key, o


def test_unknown_game_lists_known_ones():
    with pytest.raises(UnknownGameError) as err:
        get_game("brekout")
    message = str(err.value)
    assert "brekout" in message and all(name in message for name in GAMES) and "Did you mean 'breakout'" in message


def test_game_name_spellings():
    assert get_game("SpaceInvaders").name == "space_invaders"
    assert get_game("space-invaders").name == "space_invaders"
    assert get_game("Pong") is GAMES["pong"]


@pytest.mark.parametrize("game", list(GAMES))
def test_paper_settings(game):
    env = make_env(game)
    ale_env = env.unwrapped
    assert env.spec is None or env.unwrapped.spec.id == get_game(game).env_id
    assert ale_env.spec.id == get_game(game).env_id
    assert ale_env._frameskip == 4
    assert ale_env.ale.getFloat("repeat_action_probability") == 0.0
    assert env.action_space.n == get_game(game).n_actions
    env.close()


@pytest.mark.parametrize("game", list(GAMES))
def test_every_object_has_int_fields(game):
    """Objects are {x, y, w, h, dx, dy} ints; a game's derive may add fields of its own (lane, type, dist)."""
    derived = get_game(game).derive is not None
    seen, _ = _play(game, [a for a in (0, 2, 3, 1) if a < get_game(game).n_actions], 300)
    assert any(len(list(_objects(o))) for o in seen)
    space = observation_space(get_game(game))
    assert all(obs in space for obs in seen), "every observation is in the env's observation_space"
    for obs in seen:
        for key, o in _objects(obs):
            assert FIELDS <= set(o) if derived else set(o) == FIELDS, key
            assert all(type(o[f]) is int for f in FIELDS), (key, o)


@pytest.mark.parametrize("game", list(GAMES))
def test_nothing_moves_on_the_first_observation(game):
    env = make_env(game)
    obs, _ = env.reset(seed=0)
    assert all(o["dx"] == 0 and o["dy"] == 0 for _, o in _objects(obs))
    env.close()


def test_pong_keys_and_absent_ball():
    seen, _ = _play("pong", [0], 200)
    assert all(set(obs) <= {"Player", "Ball", "Enemy"} for obs in seen)
    assert any("Ball" not in obs for obs in seen), "the ball is off screen between points: key must be absent"
    assert any("Ball" in obs for obs in seen)
    assert all(obs["Player"]["x"] == 140 for obs in seen if "Player" in obs)


def test_breakout_rows_hold_one_entry_per_run_of_bricks_as_the_authors_have_them():
    """OCAtari's Block is a run of adjacent bricks (w = 8 * n): one entry each, the rows in order after Player
    and Ball, then lives (the authors' observation, observation version 2; a cleared row is absent:
    tests/test_breakout_observation.py)."""
    seen, _ = _play("breakout", [2] * 10 + [3] * 10, 2000)  # sweeping: a brick goes from the middle of a row
    first = seen[0]
    assert list(first) == ["Player", "Ball", *BREAKOUT_ROWS.values(), "lives"]
    for row, y in zip(BREAKOUT_ROWS.values(), BREAKOUT_ROWS):
        assert first[row] == [{"x": 8, "y": y, "w": 144, "h": 6, "dx": 0, "dy": 0}], "a full row is one run"
    assert first["lives"] == 5 and "Block" not in first
    broken = [obs for obs in seen if any(len(obs.get(row, [])) > 1 for row in BREAKOUT_ROWS.values())]
    assert broken, "the test must see a row broken into runs"
    for obs in broken:
        keys = [k for k in obs if k in BREAKOUT_ROWS.values()]
        assert keys == [k for k in BREAKOUT_ROWS.values() if k in keys], "rows top to bottom"
        for row, y in zip(BREAKOUT_ROWS.values(), BREAKOUT_ROWS):
            runs = obs.get(row, [])
            assert all(b["y"] == y and b["w"] % 8 == 0 and b["w"] > 0 for b in runs)
            assert all(a["x"] + a["w"] < b["x"] for a, b in zip(runs, runs[1:])), "runs apart, left to right"


def test_breakout_under_observation_version_1_splits_the_runs_into_8_pixel_bricks():
    """The convention runs stored before observation versions were recorded replay with."""
    env = make_env("breakout", observation=1)
    obs, _ = env.reset(seed=0)
    env.close()
    assert list(obs) == [*BREAKOUT_ROWS.values(), "Player", "Ball"]
    for row, y in zip(BREAKOUT_ROWS.values(), BREAKOUT_ROWS):
        assert [(b["x"], b["w"]) for b in obs[row]] == [(8 + 8 * i, 8) for i in range(18)]


def test_breakout_fires_at_start_and_after_a_lost_life():
    seen, infos = _play("breakout", [0], 400)  # never moves: loses every ball
    assert "Ball" in seen[1], "the ball is launched without the policy pressing FIRE"
    lives = [info["lives"] for info in infos]
    lost_at = [i for i in range(1, len(lives)) if lives[i] < lives[i - 1]]
    assert len(lost_at) >= 2
    for i in lost_at:
        if lives[i] > 0:
            assert any("Ball" in obs for obs in seen[i : i + 3]), "relaunched after the lost life"


def _longest_without_ball(env, seeds, steps: int, lives_of_one_game: bool = False) -> tuple[int, int, int]:
    """NOOP-only Breakout games from ``seeds`` (RAM observations), each up to ``steps`` steps (with
    ``lives_of_one_game``, ``--one-life-continue``: episode after episode of the game): the longest run of steps
    without a ball in play, the serves seen (a ball in play after none) and the games that ended."""
    longest = serves = ended = 0
    for seed in seeds:
        ram, _ = env.reset(seed=seed)
        without, had = 0, False
        for _ in range(steps):
            ram, _, terminated, truncated, info = env.step(0)
            if ball_in_play(ram):
                serves += not had
                had, without = True, 0
            else:
                had, without = False, without + 1
                longest = max(longest, without)
            if terminated and lives_of_one_game and info["lives"] > 0:
                ram, _ = env.reset()  # the next life of the same game
            elif terminated or truncated:
                ended += 1
                break
    return longest, serves, ended


@pytest.mark.slow
@pytest.mark.parametrize("one_life", [False, "continue"])
def test_breakout_serves_again_when_sticky_actions_swallow_the_fire(one_life):
    """Under sticky actions ALE can repeat the previous action on all four frames of the FIRE step; the game then
    waits for a serve forever (before: 4 of 40 NOOP games of the standard protocol stalled, ~2% of serves, and
    an audit episode of CI's stalled at its cap). Swept over 40 seeds, whole games and the lives of one game (the
    authors' protocol, whose FIRE comes with each reset): no ball is ever out for long, and every game ends."""
    env = make_env("breakout", sticky=0.25, noop_max=30, objects=False, one_life=one_life)
    longest, serves, ended = _longest_without_ball(env, range(40), 800, lives_of_one_game=bool(one_life))
    env.close()
    assert serves >= 150 and ended == 40, (serves, ended)
    assert longest <= ServeAgain.AFTER + 7, longest


class _FirstFireLost(gym.Wrapper):
    """The raw game with its first FIRE turned into a NOOP: what sticky actions do to an unlucky press."""

    def __init__(self, env):
        super().__init__(env)
        self.lost = False

    def step(self, action):
        if action == AutoFire.FIRE and not self.lost:
            self.lost, action = True, 0
        return self.env.step(action)


def test_a_lost_press_is_pressed_again_after_the_wait_and_never_in_play():
    """The mechanism on its own: the serve's press lost, the ball comes ServeAgain.AFTER steps later; in the
    paper's protocol, where no press is lost, no ball is out longer than 7 steps (so no second press ever changes
    its play)."""
    raw = gym.make("BreakoutNoFrameskip-v4", obs_type="ram", frameskip=4, repeat_action_probability=0.0,
                   full_action_space=False)
    env = AutoFire(ServeAgain(_FirstFireLost(raw), ball_in_play))
    ram, _ = env.reset(seed=0)
    waited = 0
    while not ball_in_play(ram):
        ram, *_ = env.step(0)
        waited += 1
    assert ServeAgain.AFTER - 1 <= waited <= ServeAgain.AFTER + 7, waited  # the lost press's step counts too
    env.close()
    paper = make_env("breakout", objects=False)
    longest, serves, ended = _longest_without_ball(paper, [0], 2000)
    paper.close()
    assert serves == 5 and ended == 1 and longest <= 7, (longest, serves, ended)


def test_space_invaders_numbering_and_bullet_direction():
    seen, _ = _play("space_invaders", [1, 4, 5], 400)
    first = seen[0]
    aliens = sorted((k for k in first if k.startswith("Alien")), key=lambda k: int(k[5:]))
    assert aliens == [f"Alien{i}" for i in range(len(aliens))] and len(aliens) == 36
    assert {"Shield0", "Shield1", "Shield2", "Player"} <= set(first)
    dys = {"up": 0, "down": 0}
    for obs in seen:
        numbered = sorted((k for k in obs if k.startswith("Alien")), key=lambda k: int(k[5:]))
        assert numbered == [f"Alien{i}" for i in range(len(numbered))], "dense numbering"
        for key, o in obs.items():
            if key.startswith("Bullet") and o["dy"]:
                dys["up" if o["dy"] < 0 else "down"] += 1
    assert dys["up"] > 0 and dys["down"] > 0, "player bullets rise (dy<0), alien bullets fall (dy>0)"


def test_paper_protocol_is_deterministic_and_standard_protocol_is_not():
    a, _ = _play("pong", [2, 3, 0], 150)
    b, _ = _play("pong", [2, 3, 0], 150)
    assert a == b

    def run(seed):
        env = make_env("pong", sticky=0.25, noop_max=30)
        obs, _ = env.reset(seed=seed)
        trail = [obs]
        for i in range(150):
            obs, *_ = env.step([2, 3, 0][i % 3])
            trail.append(obs)
        return trail

    assert run(1) != run(2)


def test_bad_protocol_values():
    with pytest.raises(ValueError):
        make_env("pong", sticky=1.5)
    with pytest.raises(ValueError):
        make_env("pong", noop_max=-1)


def _trajectory(env, seed: int, actions: list[int], options: dict | None = None) -> list:
    """Everything an episode shows: observations, rewards, flags, info, and the emulator's screen and RAM."""
    ale = env.unwrapped.ale
    obs, info = env.reset(seed=seed, options=options)
    seen = [(obs, info, ale.getScreenRGB().tobytes(), ale.getRAM().tobytes())]
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(action)
        seen.append((obs, reward, terminated, truncated, info, ale.getScreenRGB().tobytes(), ale.getRAM().tobytes()))
        if terminated or truncated:
            break
    return seen


class _CountingALE:
    """An ALE that counts the resets it plays (``reset_game``) and passes everything else through."""

    def __init__(self, ale) -> None:
        self._ale = ale
        self.resets_played = 0

    def reset_game(self) -> None:
        self.resets_played += 1
        self._ale.reset_game()

    def __getattr__(self, name: str):
        return getattr(self._ale, name)


@pytest.mark.slow
@pytest.mark.parametrize("protocol", [{}, {"noop_max": 30, "one_life": True}], ids=["paper", "no-ops, one life"])
@pytest.mark.parametrize("game", sorted(GAMES))
def test_a_reset_from_the_loaded_snapshot_is_a_rom_load_byte_for_byte(game, protocol):
    """Without sticky actions a seeded reset restores the state the environment was built with instead of loading
    the ROM again (games.envs.reload_from_snapshot): after another episode, at other seeds, every step is the
    same as after a real ``loadROM``. A reset that reads no screen (``RESET_WITHOUT_SCREEN``, a game host's
    episode that logs no frames) of a game whose reset is restorable (``Game.restorable_reset``) restores the
    state ALE's reset leads to and plays no reset: the same steps again, only the screen before the first step
    is the one drawn last. A game that says its reset is not restorable plays it, and must: restored, it would
    play otherwise."""
    import numpy as np

    from games import get_game
    from games.envs import RESET_WITHOUT_SCREEN, reload_from_snapshot

    restorable = get_game(game).restorable_reset
    snapshot = make_env(game, **protocol)
    rom = make_env(game, **protocol)
    ale_env = rom.unwrapped
    ale_env.load_game = type(ale_env).load_game.__get__(ale_env)  # the class's own: loadROM
    without_screen = make_env(game, **protocol)
    if not restorable:  # what the game says must not be done: done here, to show that it plays otherwise
        forced = make_env(game, **protocol)
        reload_from_snapshot(forced.unwrapped, restorable_reset=True)
    counting = without_screen.unwrapped.ale = _CountingALE(without_screen.unwrapped.ale)
    rng = np.random.default_rng(7)
    n = snapshot.action_space.n
    mid_game = [int(a) for a in rng.integers(0, n, 120)]
    _trajectory(snapshot, 99, mid_game)  # leave the emulator mid-game
    _trajectory(without_screen, 99, mid_game, RESET_WITHOUT_SCREEN)
    if not restorable:
        _trajectory(forced, 99, mid_game, RESET_WITHOUT_SCREEN)
    for seed in (3, 11, 2**31 - 1):
        actions = [int(a) for a in rng.integers(0, n, 400)]
        real = _trajectory(rom, seed, actions)
        assert _trajectory(snapshot, seed, actions) == real, f"{game} seed {seed}"
        played = _trajectory(without_screen, seed, actions, RESET_WITHOUT_SCREEN)
        if restorable:
            (obs, info, _screen, ram), *steps = played
            assert (obs, info, ram) == (real[0][0], real[0][1], real[0][3]), f"{game} seed {seed}: at the reset"
            assert steps == real[1:] and len(steps) > 1, f"{game} seed {seed}"
        else:
            assert played == real, f"{game} seed {seed}"
            assert _trajectory(forced, seed, actions, RESET_WITHOUT_SCREEN)[1:] != real[1:], \
                f"{game} says its reset is not restorable, but a restored one plays the same: Game.restorable_reset"
    assert counting.resets_played == (0 if restorable else 4), "a reset that reads no screen plays none"
    _trajectory(without_screen, 5, [])
    assert counting.resets_played == (1 if restorable else 5), "a reset that may read the screen plays it"
    sticky = make_env(game, sticky=0.25)
    assert sticky.unwrapped.load_game.__func__ is type(sticky.unwrapped).load_game, \
        "with sticky actions the seed must reseed ALE's generator: a real loadROM"


def test_an_episode_that_logs_frames_starts_from_a_played_reset_and_one_that_does_not_from_its_state(tmp_path):
    """A game host's episode restores the state ALE's reset leads to (``RESET_WITHOUT_SCREEN``) only when it logs no
    screens: its first screen would otherwise be the last episode's, in the recording."""
    from games.envs import shared_env
    from pipeline.play.rollout import prepare_episode, run_episode
    from pipeline.play.spec import EpisodeSpec

    text = (Path(__file__).resolve().parents[1] / "games" / "scaffolds" / "pong.py").read_text()
    screen = shared_env("pong").unwrapped.ale.getScreenRGB
    fresh = make_env("pong")
    fresh.reset(seed=4)
    reset_screen = fresh.unwrapped.ale.getScreenRGB().tobytes()

    def screen_after_reset(**logging) -> tuple[bytes, bytes]:
        run_episode(EpisodeSpec("before", "r", "pong", text, "v", seed=3, max_steps=150))  # ends mid-game
        before = screen().tobytes()
        prepared = prepare_episode(EpisodeSpec("e", "r", "pong", text, "v", seed=4, max_steps=10, **logging))
        prepared.policy.finish()  # its timer and tracer end
        return before, screen().tobytes()

    before, after = screen_after_reset()
    assert after == before != reset_screen, "no frames logged: the reset was restored, not played"
    for logging in (dict(rerun=str(tmp_path)), dict(rerun=str(tmp_path), rerun_frames_every=1)):
        before, after = screen_after_reset(**logging)
        assert after == reset_screen != before, f"{logging}: the first frame logged is the reset's own"
    _, after = screen_after_reset(rerun=str(tmp_path), rerun_frames_every=0)
    assert after != reset_screen, "a recording without frames reads no screen"


@pytest.mark.parametrize("protocol", [dict(), dict(sticky=0.25, noop_max=30)])
def test_a_reused_environment_plays_episodes_like_a_fresh_one(protocol):
    from pipeline.play.rollout import run_episode
    from pipeline.play.spec import EpisodeSpec

    text = (Path(__file__).resolve().parents[1] / "games" / "scaffolds" / "space_invaders.py").read_text()
    specs = [EpisodeSpec(f"e{seed}", "r", "space_invaders", text, "v", seed=seed, max_steps=150, **protocol)
             for seed in (3, 4, 3)]
    first, other, again = (run_episode(s).steps for s in specs)
    assert first.equals(again), "the same seed after another episode on the shared environment"
    assert not first.equals(other) or not protocol


def _observations(env, seed: int, actions) -> list:
    obs, _ = env.reset(seed=seed)
    seen = [obs]
    for action in actions:
        obs, _, terminated, truncated, _ = env.step(action)
        seen.append(obs)
        if terminated or truncated:
            break
    return seen


@pytest.mark.parametrize("game", sorted(GAMES))
def test_two_environments_of_a_game_stepped_in_turn_see_what_each_sees_alone(game):
    """Some OCAtari extractors keep state in their module's globals (Q*bert's: an enemy of the other game came and
    went): every game's two environments stepped in turn, 400 random actions each, observe exactly what each
    observes alone."""
    import random

    n = get_game(game).n_actions
    plays = [(seed, [random.Random(seed * 7 + k).randrange(n) for k in range(400)]) for seed in (0, 1)]
    alone = [_observations(make_env(game), seed, actions) for seed, actions in plays]
    envs = [make_env(game) for _ in plays]
    together = [[env.reset(seed=seed)[0]] for env, (seed, _) in zip(envs, plays)]
    done = [False, False]
    for step in range(400):
        for k, (env, (_, actions)) in enumerate(zip(envs, plays)):
            if not done[k]:
                obs, _, terminated, truncated, _ = env.step(actions[step])
                together[k].append(obs)
                done[k] = terminated or truncated
    for k in range(2):
        first = next((i for i, (a, b) in enumerate(zip(together[k], alone[k])) if a != b), None)
        assert len(together[k]) == len(alone[k]) and first is None, (k, first)


def test_qbert_in_a_gymnasium_vector_env_sees_what_it_sees_alone():
    """The same through ``gymnasium.vector.SyncVectorEnv`` (its environments stepped in turn, as RL code runs them)."""
    import random

    from ocatari.ram import qbert

    assert {"coil_prev_x", "purple_i", "green_i"} <= set(written_globals(qbert))
    plays = [[random.Random(99).randrange(6) for _ in range(400)], [random.Random(1234).randrange(6) for _ in range(400)]]
    vector = gym.vector.SyncVectorEnv([lambda: gym.make("codearcade/Qbert-v0")] * 2)
    obs, _ = vector.reset(seed=[0, 0])
    seen, done = [[obs[0]], [obs[1]]], [False, False]
    for a, b in zip(*plays):
        obs, _, terminated, truncated, _ = vector.step([a, b])
        for k in (0, 1):
            if not done[k]:
                seen[k].append(obs[k])
                done[k] = bool(terminated[k] or truncated[k])
    vector.close()
    for k in (0, 1):
        alone = _observations(gym.make("codearcade/Qbert-v0"), 0, plays[k])
        first = next((i for i, (a, b) in enumerate(zip(seen[k], alone)) if a != b), None)
        assert first is None, (k, first)


LEAN_IMPORT = """
import sys
import numpy as np
import games.envs
games.envs.make_env("pong").close()
print(sorted(m for m in ("matplotlib", "matplotlib.pyplot", "skimage", "skimage.morphology", "scipy.optimize",
                         "pygame") if m in sys.modules))
from ocatari.vision import utils
made = utils.linear_sum_assignment  # a stand-in until a reader that matches objects is made ready
games.envs.make_env("enduro").close()
from scipy.optimize import linear_sum_assignment
print(type(made).__name__, utils.linear_sum_assignment is linear_sum_assignment, made([[1, 0], [0, 1]])[1].tolist())
from ocatari.vision import enduro, utils  # OCAtari's vision code, as it bound the deferred names
print(utils.disk(1).tolist(), utils.plt.cm.viridis.name, enduro.plt.pyplot.get_backend())
import matplotlib.pyplot as plt
import skimage.morphology
print(type(plt).__name__, type(skimage.morphology).__name__, np.array_equal(utils.disk(3), skimage.morphology.disk(3)))
"""


def test_ocatari_comes_without_its_vision_modes_plotting_imports_which_still_work_when_used():
    """OCAtari's package imports scikit-image's morphology, matplotlib and scipy's optimize for its vision mode and
    pygame for its window, which codearcade never uses but for Enduro's matching (~0.8-1.1 s of every game zygote's
    start: ``games/lean_ocatari.py``). An environment is made without them; Enduro's has scipy's function in place;
    OCAtari's vision code still gets the real functions at their first use, and a later import is the real module."""
    done = subprocess.run([sys.executable, "-c", LEAN_IMPORT], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    absent, matching, used, real = done.stdout.splitlines()[-4:]
    assert absent == "[]", "none of them was imported to make an environment"
    assert matching == "Forward True [1, 0]", "a reader that matches objects gets scipy's function once it is made"
    assert used == "[[0, 1, 0], [1, 1, 1], [0, 1, 0]] viridis agg", "the deferred names work as the real ones"
    assert real == "module module True", "a later import gets the real modules"


@pytest.mark.parametrize("game", ["pong", "enduro"])
def test_a_game_zygote_holds_what_its_hosts_use_and_nothing_of_ocataris_vision_mode(game):
    """By its effect on the process that forks every game host, once it has played an episode of ``game``: its
    memory maps hold ``ale_py`` and none of the compiled modules of matplotlib, scikit-image or pygame. scipy's
    ``optimize`` only for a game whose reader matches objects from step to step (Enduro's), and then in the zygote
    itself, before any host forks: a host would pay its import (~0.3 s) at its first matching step."""
    from pipeline.boundary import zygotes
    from pipeline.play.episodes import run_episodes
    from pipeline.play.spec import EpisodeSpec

    zygotes.stop_zygote()  # a fresh one: an earlier test of this process may have played Enduro with it
    policy = (ROOT / "games" / "scaffolds" / f"{game}.py").read_text()
    [(_, outcome)] = list(run_episodes([EpisodeSpec("e0", "r", game, policy, "v", max_steps=5)]))
    assert outcome.end_reason == "truncated", outcome.episode
    outer = zygotes.zygote("game").proc.pid  # it starts the zygote proper, in namespaces of its own
    [proper] = [int(pid) for task in Path(f"/proc/{outer}/task").iterdir() for pid in (task / "children").read_text().split()]
    pids, maps = [outer], ""
    while pids:  # the zygote's processes and those below them
        pid = pids.pop()
        try:
            maps += Path(f"/proc/{pid}/maps").read_text()
            for task in Path(f"/proc/{pid}/task").iterdir():
                pids += [int(child) for child in (task / "children").read_text().split()]
        except (FileNotFoundError, ProcessLookupError):  # a worker of the episode, gone as it was read
            continue
    assert "ale_py" in maps, "the emulator is loaded there"
    assert "matplotlib" not in maps and "skimage" not in maps and "pygame" not in maps
    matching = "scipy/optimize/_lsap" in Path(f"/proc/{proper}/maps").read_text()
    assert matching == (game == "enduro") and ("scipy/optimize" in maps) == matching
