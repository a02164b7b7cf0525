"""The settings of playing: ``codearcade eval``'s (:class:`EvalConfig`) and ``codearcade compare``'s for two
versions (:class:`CompareConfig`), each declared once with its flag (``pipeline/settings.py``); the episode limits
are :class:`~pipeline.settings.EpisodeLimits`'. A module of its own, light to import: the command line builds its
flags from it before anything plays.
"""

from __future__ import annotations

from dataclasses import dataclass

from games import GAMES
from games.base import (OBSERVATION_VERSION, STANDARD_NOOP_MAX, STANDARD_STICKY,
                        one_life_setting)
from pipeline.settings import Switch, limit, same_as, setting

MAX_EPISODES = 100_000
"""The most episodes one command plays (eval, compare): each is planned before the first plays, so a typo of
99,999,999,999 held gigabytes before anything started (100,000 short Pong games are about a day on two cores)."""
MAX_NOOPS = 10_000
"""The most random no-ops after a reset (the standard protocol's 30; 10,000 steps are 11 minutes of game time, a
few seconds to emulate): ``eval --noop-max 4611686018427387904`` was taken, and its episode never ended."""


@dataclass
class EvalConfig:
    """Options of an evaluation (the flags of ``codearcade eval``, declared here: ``pipeline/settings.py``)."""

    game: str | None = setting(None, f"game to play: {', '.join(GAMES)}, or any game OCAtari reads (`codearcade "
                               "games` lists them) (default: the file's GAME)")
    """Game to play; None takes the policy file's ``GAME``. Both given and different is an error."""
    episodes: int = setting(1, "evaluation episodes (default: %(default)s)", minimum=1, maximum=MAX_EPISODES)
    """Number of evaluation episodes."""
    max_steps: int = limit("max_steps")
    """Steps after which an episode is cut off (reported as ``truncated``; ``EpisodeLimits``)."""
    seed: int = setting(0, "seed of the first episode; episode i uses seed+i (default: %(default)s)", minimum=0,
                        maximum=2**62)  # Gymnasium refuses a negative seed; the store's seed is a BIGINT
    """Seed of the first episode; episode i uses ``seed + i`` (``one_life="continue"``: the seed of the one game)."""
    seeds: tuple[int, ...] | None = setting(None, "the seed of each episode, in place of seed+i", cli=False)
    """The seed of each episode, one each, in place of ``seed + i`` (None: from ``seed`` on). Not a flag: only
    ``codearcade compare --audit`` sets them, to the sealed audit seeds it drew for a side; ``episodes`` is then
    their number."""
    rng_key: str | None = setting(
        None, "key of the policy's own random stream: its random and NumPy generators are seeded from this key and "
        "each game's seed, never with the seed (default: the run's id, which the policy cannot know); give two "
        "runs the same key to have their policies draw the same numbers", metavar="KEY")
    trace: bool = setting(False, "record a node for every call of a bundled method")
    """Record a node event for every call of a bundled method."""
    trace_lines: bool = setting(True, "record the lines each traced call ran", cli=False)
    """With ``trace``: record in each node the lines of the method that ran (``nodes.lines_run``). Only a
    measurement turns it off (``bench/lines.py`` prices it): it costs little, so ``--trace`` always records them."""
    sticky: float = setting(0.0, "sticky-action probability (default: 0.0, the paper's; 0.25 with --noop-max 30 is "
                            "the standard stochastic protocol)", minimum=0.0, maximum=1.0)
    """Sticky-action probability (paper: 0.0; standard Atari protocol: 0.25)."""
    noop_max: int = setting(0, "up to this many random NOOPs after reset (default: %(default)s)", minimum=0,
                            maximum=MAX_NOOPS)
    """Up to this many random NOOPs after reset (paper: 0; standard protocol: 30)."""
    one_life: bool | str = setting(False, "end each episode at a lost life", check=one_life_setting, switches=(
        Switch("--one-life", True, "end each episode at the first lost life of its own seeded game (default: whole "
               "games, the paper's)"),
        Switch("--one-life-continue", "continue", "the authors' protocol for Asterix, Breakout, Q*bert and Seaquest "
               "exactly: the episodes are the lives of one game from --seed, each going on where the one before "
               "ended")))
    """End each episode at a lost life, as the authors' follow-up evaluates Asterix, Breakout, Q*bert and Seaquest
    (``Task.one_life_episodes``): ``"continue"`` (``--one-life-continue``) exactly as theirs, the episodes the
    lives of one game from ``seed``, each going on where the one before ended (``games.wrappers.EpisodicLife``);
    ``True`` (``--one-life``) the first life of each episode's own seeded game (``games.wrappers.OneLife``).
    Off: whole games (the paper's)."""
    observation: int = setting(OBSERVATION_VERSION, "the version of the observation conventions", cli=False)
    """The version of the observation conventions (``games.base.OBSERVATION_VERSION``), recorded in the run."""
    workers: int = setting(1, "episodes played at once in worker processes (default: min(episodes, cores)); 0 plays "
                           "in this process without isolation, for debugging", minimum=0, flag_default=None,
                           reproduce=False)
    """Worker processes playing episodes at once; 0 plays in this process (no isolation, for debugging)."""
    call_time_limit_s: float = limit("call_time_limit_s")
    """Time limit of one policy call (``EpisodeLimits``)."""
    episode_time_limit_s: float = limit("episode_time_limit_s")
    """Wall-clock limit of one episode (``EpisodeLimits``)."""
    rerun: str | None = setting(None, "live Rerun recording of each episode", cli=False, reproduce=False)
    """Live Rerun recording of each episode (``EpisodeSpec.rerun``): a directory or a gRPC url; None: off."""


@dataclass
class CompareConfig:
    """Options of ``codearcade compare`` for two versions (two runs are only read); its flags say ``versions:``."""

    game: str | None = setting(None, "the game both play (default: their runs' or files' GAME)")
    """Game both versions play; None takes it from the stored runs or the files' ``GAME``."""
    episodes: int = setting(1, "seeds to play, from --seed on (default: %(default)s)", minimum=1, maximum=MAX_EPISODES)
    """Seeds to play: ``seed``, ``seed + 1``, ...; each version plays each of them once."""
    seed: int = setting(0, "the first seed, under the paper's protocol (default: %(default)s; --audit draws its own)")
    """The first seed (the paper's protocol; ``audit`` draws sealed seeds instead)."""
    rng_key: str | None = same_as(EvalConfig, "rng_key")
    """The key of both sides' random stream (None: a new one each time); on a seed, their policies draw alike."""
    max_steps: int = limit("max_steps", help="step cap (default: %(default)s)")
    """Step cap of each episode (``EpisodeLimits``)."""
    audit: bool = setting(False, f"play each side on its own audit seeds, drawn now from the OS's entropy, under the "
                          f"standard protocol (sticky {STANDARD_STICKY}, up to {STANDARD_NOOP_MAX} no-op starts): the "
                          "scores then say whether the versions differ beyond the noise, on games neither could know "
                          "in advance (default: both on the same seeds under the paper's protocol, every seed the same "
                          "game, to find where their actions part)")
    """Play A and B each on its own ``episodes`` sealed audit seeds (``pipeline.optimizer.audit.draw_audit_seeds``:
    drawn when the comparison runs, over the whole audit range, recorded only with the episodes they produced), under
    the standard protocol (``games.base.STANDARD_STICKY``/``STANDARD_NOOP_MAX``). Under the paper's protocol every
    seed is the same game, so a difference of scores there measures only the policies' own random draws; here each
    side's episodes are independent draws and ``store.statistics.difference`` of their returns says whether the
    versions differ. No divergent step is looked for: the two sides play different games. ``seed`` is then
    unused."""
    context: int = setting(3, "steps shown before and after the first divergent step (default: %(default)s)",
                           minimum=0)
    """Steps shown before and after the first divergent step."""
    workers: int = setting(1, "episode worker processes (default: min(episodes, cores))", minimum=0,
                           flag_default=None)
    """Episode worker processes (``codearcade eval --workers``)."""
