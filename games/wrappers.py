"""The Gymnasium wrappers of the play protocols, one concern each, under which ``games.envs.make_env`` builds a game
(the order there): :class:`NoopReset` (the standard protocol's random NOOPs), :class:`AutoFire` (FIRE after a
reset and each lost life), :class:`ServeAgain` (FIRE again when sticky actions swallowed a press),
:class:`OneLife` (the first life of a seeded game) and :class:`EpisodicLife` (the authors' one-life protocol,
each life an episode of one game). None reads objects: they see ALE's RAM observation (or whatever the wrapper
under them returns), its rewards and ``lives``.
"""

from __future__ import annotations

from typing import Any, Callable

import gymnasium as gym

from games.base import Game


class AutoFire(gym.Wrapper):
    """Press FIRE after reset and after each lost life, so the ball is always launched (Breakout).

    The extra FIRE step is part of the agent's step that lost the life: its reward is added and its
    observation returned, so step counts stay the agent's own.
    """

    FIRE = 1

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self._lives = 0

    def reset(self, **kwargs):
        self.env.reset(**kwargs)
        obs, _, terminated, truncated, info = self.env.step(self.FIRE)
        if terminated or truncated:  # cannot happen on a fresh game; reset again rather than start dead
            obs, info = self.env.reset(**kwargs)
        self._lives = info.get("lives", 0)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        lives = info.get("lives", 0)
        if lives < self._lives and not (terminated or truncated):
            obs, extra, terminated, truncated, info = self.env.step(self.FIRE)
            reward += extra
            lives = info.get("lives", 0)
        self._lives = lives
        return obs, reward, terminated, truncated, info


class ServeAgain(gym.Wrapper):
    """Press FIRE again when no ball has been in play for :attr:`AFTER` steps (Breakout, ``Game.ball_in_play``
    on the RAM observation), under whichever wrapper pressed the first.

    Under sticky actions ALE can repeat the previous action on all four frames of the FIRE step, and the press is
    lost: the game then waits for a serve that never comes, and the episode stalls to its step cap (4 of 40
    NOOP games of the standard protocol, ~2% of serves; an audit episode of a CI run, 2026-12-05). In play a
    ball is out for at most 7 steps (a lost ball to the next serve's ball on screen), so the paper's protocol,
    where no press is lost, never reaches this press and plays exactly as before.

    The extra FIRE step is part of the agent's step that waited too long: its reward is added and its
    observation returned, so step counts stay the agent's own.
    """

    FIRE = 1
    AFTER = 30
    """Steps without a ball in play after which FIRE is pressed again (4x the longest wait seen in play)."""

    def __init__(self, env: gym.Env, ball_in_play: Callable[[Any], bool]):
        super().__init__(env)
        self._ball_in_play = ball_in_play
        self._without_ball = 0

    def reset(self, **kwargs):
        self._without_ball = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        ram, reward, terminated, truncated, info = self.env.step(action)
        self._without_ball = 0 if self._ball_in_play(ram) else self._without_ball + 1
        if self._without_ball >= self.AFTER and not (terminated or truncated):
            ram, extra, terminated, truncated, info = self.env.step(self.FIRE)
            reward += extra
            self._without_ball = 0
        return ram, reward, terminated, truncated, info


def may_predate_serve_again(game: Game, sticky: float) -> bool:
    """Whether a stored game of ``game`` under ``sticky`` may have been played before :class:`ServeAgain` existed
    (2026-12-05) and play differently today: a serve swallowed then went on without a ball. A replay that
    disagrees tries ``make_env(..., serve_again=False)`` for it (``pipeline/play/verify.py``, the viewer's frames)."""
    return game.ball_in_play is not None and sticky > 0


class OneLife(gym.Wrapper):
    """End the episode (``terminated``) at the first lost life: the first life of a game reset from its seed.

    Their environments (``trace_envs/{asterix,breakout,qbert,seaquest}.py`` of ameliakuang/LLM-Game-Playing-Agents,
    baselines' ``EpisodicLifeEnv``) report ``terminated`` on the step whose ``lives`` fell below the previous
    step's while still above 0 (the last life ends the game anyway), and their evaluation sums the rewards up
    to that step: one life is one episode. Their *next* episode goes on with the same game (:class:`EpisodicLife`);
    here every episode is the first life of a game reset from its seed, so that an episode stays reproducible on
    its own (the same for one evaluation episode; for their 3 x 20,000 Asterix evaluation, lives 1-3 of one game,
    these are the first life of three).
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self._lives = 0

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._lives = info.get("lives", 0)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        lost = self._lost_a_life(info)
        return obs, reward, terminated or lost, truncated, info

    def _lost_a_life(self, info: dict) -> bool:
        """Whether this step lost a life that did not end the game (the last one ends it anyway)."""
        lives = info.get("lives", 0)
        lost = 0 < lives < self._lives
        self._lives = lives
        return lost


class EpisodicLife(OneLife):
    """The authors' one-life protocol exactly: baselines' ``EpisodicLifeEnv`` as their
    ``trace_envs/{asterix,breakout,qbert,seaquest}.py`` (ameliakuang/LLM-Game-Playing-Agents) implement it.

    - ``step``: ``terminated`` on the step whose ``lives`` fell below the previous step's while still above 0
      (:class:`OneLife`'s rule, inherited); the game itself goes on underneath.
    - ``reset()`` without a seed after a step that did not end the game (a lost life, or an episode cut at its
      step cap) *continues* it: one NOOP, whose reward is dropped (a real reset if that NOOP ended the game);
      after a game over, a real reset, not reseeded (the environment's RNG goes on, so the whole sequence stays
      reproducible from the first seed and the actions).
    - ``reset(seed=...)`` always starts a new game from that seed (theirs never pass one: their first reset is
      a fresh environment's).
    - ``fire`` (Breakout): every reset then presses FIRE, its reward dropped too (their ``FireResetEnv`` phase;
      a real reset if it ended the game). Breakout is built without :class:`AutoFire` under this protocol: their
      step that loses a life presses nothing more (:class:`ServeAgain` stays: it presses only where sticky
      actions lost a press, which their protocol, sticky 0, never does).

    It wraps :class:`ObjectObservation` (when built with objects), so that the NOOP and FIRE are ordinary steps of
    the object extraction, as in their OCAtari environment: the first observation of a continued episode is that
    of the NOOP (or FIRE) step, its ``dx/dy`` the movement since the step before. ``continued`` says whether the
    last reset went on with a game.
    """

    NOOP = 0
    FIRE = 1

    def __init__(self, env: gym.Env, fire: bool = False):
        super().__init__(env)
        self.fire = fire
        self._real_done = True
        self.continued = False

    @property
    def object_rows(self) -> list[tuple]:
        """The inner :class:`ObjectObservation`'s rows of the last observation (AttributeError without one)."""
        return self.env.object_rows

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None or self._real_done:
            obs, info = self.env.reset(seed=seed, options=options)
            self._real_done, self.continued = True, False  # as their fresh environment: a second reset is real too
        else:
            obs, _, terminated, truncated, info = self.env.step(self.NOOP)
            self.continued = True
            if terminated or truncated:
                obs, info = self.env.reset(options=options)
        if self.fire:
            obs, _, terminated, truncated, info = self.env.step(self.FIRE)
            if terminated or truncated:
                obs, info = self.env.reset(options=options)
        self._lives = self.env.unwrapped.ale.lives()
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._real_done = bool(terminated or truncated)  # the game's own end, before a lost life ends the episode
        lost = self._lost_a_life(info)
        return obs, reward, terminated or lost, truncated, info


class NoopReset(gym.Wrapper):
    """Take 1..noop_max NOOPs after reset, drawn from the env's seeded RNG (standard Atari protocol)."""

    def __init__(self, env: gym.Env, noop_max: int):
        super().__init__(env)
        self.noop_max = noop_max

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        for _ in range(int(self.np_random.integers(1, self.noop_max + 1))):
            obs, _, terminated, truncated, info = self.env.step(0)
            if terminated or truncated:
                obs, info = self.env.reset()
        return obs, info
