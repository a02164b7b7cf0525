"""What one episode is: :class:`EpisodeSpec`, the contract between whoever asks for an episode and the game host
that plays it (``pipeline/play/rollout.py``). Every field is a primitive, so a spec crosses to a worker as JSON and
the policy travels as its text."""

from __future__ import annotations

from dataclasses import dataclass

from games.base import OBSERVATION_VERSION
from pipeline.play.runinfo import policy_rng_seed
from pipeline.settings import EpisodeLimits


@dataclass
class EpisodeSpec:
    """Everything needed to play one episode; every field a primitive, so that it crosses to a worker as JSON."""

    episode_id: str
    run_id: str
    game: str
    policy_text: str
    policy_version_id: str
    policy_name: str = "policy.py"
    iteration: int = 0
    kind: str = "eval"
    """``eval`` (evaluation episode) or ``train`` (traced training rollout of the optimizer)."""
    index: int = 0
    seed: int = 0
    max_steps: int = EpisodeLimits.max_steps
    sticky: float = 0.0
    noop_max: int = 0
    one_life: bool | str = False
    """End the episode at a lost life: ``True``, the first life of the game reset from ``seed``
    (``games.wrappers.OneLife``); ``"continue"``, the authors' protocol exactly (``games.wrappers.EpisodicLife``)."""
    continues: str | None = None
    """The episode whose game this one goes on with (``one_life="continue"``): it is played right after that one,
    by the same game host and policy process, from where it ended (one NOOP, Breakout a FIRE); None: it starts
    from ``reset(seed)``. ``seed`` is then the seed of the game."""
    observation: int = OBSERVATION_VERSION
    """The version of the observation conventions the run plays (``games.base.OBSERVATION_VERSION``)."""
    trace: bool = False
    """Record a node for every call of a bundled method (slower; steps are always recorded)."""
    trace_lines: bool = True
    """With ``trace``: record in each node the lines of the method that ran (``nodes.lines_run``)."""
    call_time_limit_s: float = EpisodeLimits.call_time_limit_s
    """Limit for one policy call, ``policy(obs)``, including every bundled method it calls."""
    episode_time_limit_s: float = EpisodeLimits.episode_time_limit_s
    """Wall-clock limit for the whole episode."""
    memory_limit_mb: int | None = EpisodeLimits.memory_limit_mb
    """Extra address space a worker process may take beyond what it had at start (None: unlimited)."""
    rerun: str | None = None
    """Live Rerun recording: a directory (``DIR/<episode_id>.rrd``) or a ``rerun+http://…/proxy`` URL; None: off.
    Rerun is imported only inside the process that plays the episode (``viewers/rerun_live.py``)."""
    rerun_frames_every: int = 4
    """With ``rerun``: log the screen every this many steps (0: no frames)."""
    keep_printed: bool = False
    """Keep what the policy prints to its stdout (its first ``policy.MAX_PRINTED_BYTES`` bytes) and return it with
    the outcome (:attr:`EpisodeOutcome.printed`, never stored with the episode); off: it goes to ``/dev/null``."""
    rng_key: str | None = None
    """The key of the run's random stream for policies (``runinfo.policy_rng_seed``): the policy process's
    generators are seeded from it and the game's seed, never with the game's seed itself. None: a run recorded
    before the key existed, whose policies' generators were seeded with the game's seed (kept, so it replays)."""

    @property
    def policy_seed(self) -> int:
        """The seed of the policy's ``random`` and NumPy generators in this episode."""
        return policy_rng_seed(self.rng_key, self.seed) if self.rng_key else self.seed

    @property
    def logs_frames(self) -> bool:
        """Whether the episode's live Rerun recording logs screens (the first one right after the reset)."""
        return bool(self.rerun) and self.rerun_frames_every > 0
