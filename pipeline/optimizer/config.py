"""The settings of an optimization run (``codearcade optimize``, batch files, ``--resume``) and their checks.

:class:`OptimizeConfig` holds every setting with its default; :func:`validate_config` is the one check of their
ranges that the command line, batch files and ``--resume`` share; :data:`RESUME_OVERRIDES` and
:data:`BUDGET_FIELDS` say which settings may change when a run is resumed, and which are budgets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from games.base import OBSERVATION_VERSION, UNRECORDED_OBSERVATION, one_life_setting
from pipeline.optimizer.feedback import FEEDBACK_MODES
from pipeline.optimizer.strategies import STRATEGIES, make_strategy

PROTOCOLS = ("deterministic", "standard")
"""What a score can be measured under: the paper's protocol, or the standard one (``games.base``)."""


@dataclass
class OptimizeConfig:
    """Options of an optimization run (the CLI flags of ``codearcade optimize``)."""

    game: str | None = None
    """Game; None takes the policy file's ``GAME``."""
    policy: str | None = None
    """Starting policy file; None starts from the game's scaffold in ``games/scaffolds/``."""
    model: str | None = None
    """litellm model string (``anthropic/...``, ``openai/...``); None: the offline SmolLM2 server."""
    api_base: str | None = None
    """Base URL of an OpenAI-compatible server (use with ``--model openai/NAME``)."""
    iterations: int = 20
    """Optimization iterations (LLM updates) after the evaluation of the starting policy (paper: 20)."""
    memory: int = 5
    """Earlier iterations shown in the prompt (paper: 5)."""
    token_budget: int = 16_000
    """Hard limit on the prompt's tokens; the trace slice is chosen to fit."""
    eval_episodes: int = 1
    """Evaluation episodes per iteration, played in parallel; the score is their mean return."""
    feedback: str = "staged"
    """``staged`` (from the evaluation score; the paper's method) or ``rollout`` (rollout reward only: the ablation)."""
    rollback: bool = True
    """Send the next update back to the best version after a regression."""
    rollback_fraction: float = 0.5
    """Regression threshold: below ``best - (1 - f) * max(|best|, 1)``."""
    seed: int = 0
    """Seed of the training rollout; evaluation episode i uses ``seed + i``."""
    temperature: float = 0.0
    """Sampling temperature of the LLM."""
    max_tokens: int = 4096
    """Longest reply asked for."""
    rollout_steps: int | None = None
    """Training rollout horizon; None: the task's (400 Pong, 300 Breakout, 15 Space Invaders)."""
    eval_max_steps: int | None = None
    """Evaluation cap; None: the task's (4000)."""
    workers: int = 2
    """Worker processes for the episodes of an iteration."""
    call_time_limit_s: float = 1.0
    """Time limit of one policy call."""
    episode_time_limit_s: float = 900.0
    """Wall-clock limit of one episode."""
    max_cost_usd: float | None = None
    """Stop (status ``budget``) before an LLM call that could take the run's cost past this many USD, counting
    the prompt and a reply of ``max_tokens`` at litellm's price; None: no limit. Needs a model litellm prices."""
    max_total_tokens: int | None = None
    """Stop (status ``budget``) before an LLM call that could take the run's input + output tokens past this."""
    max_llm_calls: int | None = None
    """Stop (status ``budget``) before LLM calls that would take the run's count of calls past this (an equal
    budget for comparing strategies: greedy makes one call per iteration, best-of-n N)."""
    max_wall_minutes: float | None = None
    """Stop (status ``budget``) before an iteration that, lasting as long as the last one, would take the run's
    wall time (the sum of its iterations) past this many minutes."""
    strategy: str = "greedy"
    """Search strategy (``pipeline/optimizer/strategies.py``): ``greedy`` (the paper's loop), ``best-of-n``, ``beam``."""
    candidates: int | None = None
    """Proposals per parent and iteration: best-of-n's N (default 4), beam's proposals per beam member (default
    1); greedy makes one."""
    beam_width: int = 3
    """``beam``: how many of the best versions are kept and expanded."""
    max_concurrent_calls: int = 4
    """At most this many LLM calls in flight at once (an iteration's proposals are requested concurrently)."""
    robust_episodes: int = 0
    """Evaluation episodes under the standard protocol (sticky actions 0.25, up to 30 no-op starts; seeded, so
    reproducible) added to every assessment, beside the ``eval_episodes`` under the paper's; 0: none."""
    optimize_protocol: str = "deterministic"
    """The score the strategy optimizes: ``deterministic`` (the paper's protocol) or ``standard`` (needs
    ``robust_episodes``): policies good under sticky actions, not only on one replayed trajectory."""
    screen_steps: int | None = None
    """Cascade evaluation: before its full assessment, a new version plays the first evaluation game for this many
    steps; if it then trails its parent's score at the same step by more than ``screen_margin``, it is screened
    out (rejected, with both scores in its feedback) and never fully played. None: off."""
    screen_margin: float = 0.0
    """How far behind its parent a screened version may be and still be assessed fully."""
    one_life: bool | str = False
    """The authors' protocol for Asterix, Breakout, Q*bert and Seaquest (``Task.one_life_episodes``): every
    episode, training rollouts included, ends at a lost life. ``"continue"`` (``--one-life-continue``) is theirs
    exactly: the evaluation episodes of an assessment are the lives of one game from ``seed``, each going on where
    the one before ended (``games.envs.EpisodicLife``; the training rollout is that game's first life, the
    ``robust`` episodes each the first life of its own game); ``True`` (``--one-life``): every episode the first
    life of its own seeded game. Off: whole games (the paper's)."""
    observation: int = OBSERVATION_VERSION
    """The version of the observation conventions the run plays (``games.base.OBSERVATION_VERSION``): today's,
    recorded so that the run is read back and replayed with it after the conventions change."""
    collapse_repeats: bool = True
    """In the prompt's trace, show a run of consecutive steps whose calls, outputs and actions repeat as one line
    with its step range (more of the steps that matter fit the token budget)."""
    eval_cache: bool = True
    """Reuse the stored episodes of a version already assessed in the run instead of playing them again (episodes
    are deterministic given the code and the run's settings)."""


    @classmethod
    def from_record(cls, recorded: dict[str, Any]) -> "OptimizeConfig":
        """The config a run recorded (``runs.config``). A setting added after the run was made takes the value
        that reproduces what the run did (:data:`BEFORE_RECORDED`), not today's default."""
        values = {**BEFORE_RECORDED, **{k: recorded[k] for k in cls.__dataclass_fields__ if k in recorded}}
        return cls(**values)


BEFORE_RECORDED: dict[str, Any] = {"collapse_repeats": False, "observation": UNRECORDED_OBSERVATION}
"""Settings that change prompts, as runs behaved before the setting existed: an old run replays prompt for
prompt."""

BUDGET_FIELDS = ("max_cost_usd", "max_total_tokens", "max_llm_calls", "max_wall_minutes")
"""Limits of how far a run goes, not of what it does: ``--resume`` may change them, batch keys ignore them."""

RESUME_OVERRIDES = BUDGET_FIELDS + ("model", "api_base", "iterations", "token_budget", "max_tokens", "workers",
                                    "call_time_limit_s", "episode_time_limit_s", "max_concurrent_calls")
"""Settings that ``--resume`` takes from the command line; every other setting is the run's own."""


def validate_config(config: OptimizeConfig) -> None:
    """ValueError (one line naming the flag) for a setting out of range: the one check the CLI, batch files and
    ``--resume`` share."""
    if config.iterations < 0:
        raise ValueError("--iterations must be 0 or more")
    if config.memory < 0:
        raise ValueError("--memory must be 0 or more")
    if config.token_budget < 500:
        raise ValueError("--token-budget must be at least 500 tokens")
    if config.eval_episodes < 1:
        raise ValueError("--eval-episodes must be at least 1")
    if config.feedback not in FEEDBACK_MODES:
        raise ValueError(f"--feedback must be one of {', '.join(FEEDBACK_MODES)}")
    if not 0.0 <= config.rollback_fraction <= 1.0:
        raise ValueError("--rollback-fraction must be within [0, 1]")
    for name, flag in (("max_cost_usd", "--max-cost"), ("max_total_tokens", "--max-total-tokens"),
                       ("max_llm_calls", "--max-llm-calls"), ("max_wall_minutes", "--max-wall")):
        value = getattr(config, name)
        if value is not None and value <= 0:
            raise ValueError(f"{flag} must be above 0, got {value:g}")
    if config.robust_episodes < 0:
        raise ValueError("--robust-episodes must be 0 or more")
    if config.optimize_protocol not in PROTOCOLS:
        raise ValueError(f"--optimize-for must be one of {', '.join(PROTOCOLS)}, not {config.optimize_protocol!r}")
    if config.optimize_protocol == "standard" and config.robust_episodes < 1:
        raise ValueError("--optimize-for standard needs --robust-episodes N (N >= 1): the episodes its score is "
                         "the mean of")
    if config.screen_steps is not None and config.screen_steps < 1:
        raise ValueError("--screen-steps must be at least 1")
    if config.screen_margin < 0:
        raise ValueError("--screen-margin must be 0 or more")
    one_life_setting(config.one_life)
    if config.strategy not in STRATEGIES:
        raise ValueError(f"--strategy must be one of {', '.join(STRATEGIES)}, not {config.strategy!r}")
    for name, flag in (("candidates", "--candidates"), ("beam_width", "--beam-width"),
                       ("max_concurrent_calls", "--max-concurrent-calls")):
        value = getattr(config, name)
        if value is not None and value < 1:
            raise ValueError(f"{flag} must be at least 1, got {value}")
    make_strategy(config)
