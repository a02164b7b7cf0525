"""The settings of an optimization run (``codearcade optimize``, batch files, ``--resume``) and their checks.

:class:`OptimizeConfig` declares every setting once (``pipeline/settings.py``): its default, the help of its flag,
its checks, whether ``--resume`` may change it, whether it is a budget, what it does to a batch run's key. What
the rest of the code needs is derived here: :func:`validate_config` (the one check the command line, batch files
and ``--resume`` share), :data:`RESUME_OVERRIDES`, :data:`BUDGET_FIELDS`, :data:`BEFORE_RECORDED`; the flags of
``codearcade optimize`` and a batch file's keys are derived from the same declarations where they are used.
:func:`model_defaults` applies the model's own defaults (the offline model's shorter replies and prompts), for
the command line and for batches alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from games import GAMES
from games.base import AUDIT_SEED_BASE, OBSERVATION_VERSION, UNRECORDED_OBSERVATION, one_life_setting
from games.generic import GENERIC_EVAL_MAX_STEPS
from pipeline.llm.client import MAX_TOKENS, OFFLINE_MAX_TOKENS, OFFLINE_TOKEN_BUDGET
from pipeline.optimizer.ensemble import MODEL_CHOICES, check_choice, check_models, model_entries
from pipeline.optimizer.strategies import STRATEGIES, make_strategy
from pipeline.play.config import MAX_EPISODES
from pipeline.settings import (MAX_STEPS, Switch, before_recorded, budgets, check_settings, declarations, limit,
                               recorded_problem, resumable, setting)

FEEDBACK_MODES = ("staged", "rollout")
"""What the feedback of an iteration is made from (``pipeline/optimizer/feedback.py``): the evaluation score (the
paper's method) or the rollout reward only (the ablation)."""

PROTOCOLS = ("deterministic", "standard")
"""What a score can be measured under: the paper's protocol, or the standard one (``games.base``)."""

_TASK_EVAL_CAPS = "; ".join([str(GENERIC_EVAL_MAX_STEPS)] + [
    f"{name} {game.task.eval_max_steps}" for name, game in GAMES.items()
    if game.task.eval_max_steps != GENERIC_EVAL_MAX_STEPS])
"""The evaluation caps the games' tasks set (``games/<game>.py``: most the paper's, the generic games' too; the
games whose authors set another, by name), as ``--eval-max-steps``'s help names them."""

FLAG_GROUPS = {
    "search": "how versions are chosen for improvement (pipeline/optimizer/strategies.py)",
    "budgets": "the run stops with status 'budget' before it would exceed one; --resume with a larger budget "
               "continues it",
}
"""The groups of ``codearcade optimize --help`` beside its own options (a setting's ``group``; budgets go in
``budgets``), with the line that introduces each."""


MAX_ITERATIONS = 100_000
"""The most iterations a run may plan (the views read the planned count as an INTEGER; no run comes near)."""

MAX_REPLY_TOKENS = 1_000_000
"""The longest reply a run may ask for (``--max-tokens``; models write at most a few hundred thousand): the store's
``llm_calls.request_max_tokens`` is an INTEGER, and ``--max-tokens 4611686018427387904`` was taken and ended the
run in a DuckDB conversion error (a traceback) when its first call was stored."""

MAX_CANDIDATES = 1_000
"""The most proposals per parent and iteration (``--candidates``): each is an LLM call of the iteration, planned
before the first is sent; ``--strategy best-of-n --candidates 4611686018427387904`` was taken and its first
iteration planned proposals without end (killed after 60 s, no call sent)."""

@dataclass
class OptimizeConfig:
    """Options of an optimization run (the flags of ``codearcade optimize``, the keys of a batch file)."""

    game: str | None = setting(
        None, f"game: {', '.join(GAMES)}, or any game OCAtari reads (default: the file's GAME)", run_key="always")
    """Game; None takes the policy file's ``GAME``."""
    policy: str | None = setting(
        None, "starting policy file (default: the game's scaffold in games/scaffolds/)", positional=True,
        metavar="POLICY.py", run_key="always")
    """Starting policy file; None starts from the game's scaffold in ``games/scaffolds/``."""
    model: str | None = setting(
        None, "litellm model: anthropic/claude-sonnet-4-5 (ANTHROPIC_API_KEY), openai/gpt-4o (OPENAI_API_KEY), "
        "gemini/..., mistral/..., ollama_chat/NAME (a local Ollama), hosted_vllm/NAME or openai/NAME with "
        "--api-base (your own server) (default: the offline SmolLM2 server); give it several times for an "
        "ensemble, each as MODEL[,weight=W][,api_base=URL] (see --model-choice)", resumable=True, run_key="always",
        repeat=True)
    """litellm model string (``anthropic/...``, ``openai/...``); None: the offline SmolLM2 server."""
    api_base: str | None = setting(
        None, "the provider's endpoint: your own OpenAI-compatible, vLLM or Ollama server, or a proxy",
        metavar="URL", resumable=True, run_key="always")
    """Base URL of an OpenAI-compatible server (use with ``--model openai/NAME``)."""
    models: list | None = setting(
        None, "an ensemble: several models, each a litellm model string or 'MODEL[,weight=W][,api_base=URL]'",
        cli=False, resumable=True, check=check_models)
    """An ensemble (``pipeline/optimizer/ensemble.py``): ``--model`` given several times, or a batch entry's
    ``models``; each entry ``{"model", "weight", "api_base"}`` (and, once the run starts, litellm's ``price``).
    ``model`` is then the first entry's. None: one model (``model``)."""
    model_choice: str = setting(
        "fixed", "with --model given several times, how each call's model is chosen: fixed (shares by each "
        "model's weight, default), ucb or thompson (a bandit over the improvement each model's candidates bring "
        "per dollar)", choices=MODEL_CHOICES, metavar="RULE")
    """How an ensemble chooses each call's model (``pipeline/optimizer/ensemble.py``): ``fixed`` weights, or a
    bandit, ``ucb`` or ``thompson``."""
    iterations: int = setting(
        20, "LLM updates after evaluating the starting policy (default: 20; with --resume, a larger number extends "
        "the run)", minimum=0, maximum=MAX_ITERATIONS, resumable=True, run_key="always")
    """Optimization iterations (LLM updates) after the evaluation of the starting policy (paper: 20)."""
    memory: int = setting(5, "earlier iterations in the prompt (default: 5)", minimum=0, run_key="always")
    """Earlier iterations shown in the prompt (paper: 5)."""
    token_budget: int = setting(
        16_000, f"hard limit on prompt tokens (default: 16000; {OFFLINE_TOKEN_BUDGET} with the offline model)",
        minimum=500, resumable=True, run_key="always")
    """Hard limit on the prompt's tokens; the trace slice is chosen to fit."""
    eval_episodes: int = setting(
        1, "evaluation episodes per iteration, in parallel (default: 1)", minimum=1, maximum=MAX_EPISODES,
        run_key="always")
    """Evaluation episodes per iteration, played in parallel; the score is their mean return."""
    feedback: str = setting(
        "staged", "staged: from the evaluation score (paper, default); rollout: rollout reward only (ablation)",
        choices=FEEDBACK_MODES, run_key="always")
    """``staged`` (from the evaluation score; the paper's method) or ``rollout`` (rollout reward only: the ablation)."""
    rollback: bool = setting(
        True, "never go back to the best version after a regression", run_key="always")
    """Send the next update back to the best version after a regression (``--no-rollback``: never)."""
    rollback_fraction: float = setting(
        0.5, "roll back below best - (1-F)*max(|best|,1) (default: 0.5)", minimum=0.0, maximum=1.0,
        run_key="always")
    """Regression threshold: below ``best - (1 - f) * max(|best|, 1)``."""
    seed: int = setting(0, "seed (default: 0)", run_key="always")
    """Seed of the training rollout; evaluation episode i uses ``seed + i``."""
    rng_key: str | None = setting(
        None, "key of the policy's own random stream: its random and NumPy generators are seeded from this key and "
        "each game's seed, never with the seed (default: the run's id, which the policy cannot know); give two "
        "runs the same key to have their policies draw the same numbers", metavar="KEY")
    """The key of the policies' random stream (``pipeline/play/runinfo.py``, ``policy_rng_seed``); None: the run's
    id. A run records the key it used; runs recorded before the key existed seeded policies with the game's seed."""
    temperature: float = setting(
        0.0, "LLM temperature, 0 to 2 (default: 0; not sent to models that take none)", minimum=0.0, maximum=2.0,
        run_key="always")
    """Sampling temperature of the LLM."""
    max_tokens: int = setting(
        MAX_TOKENS, f"longest reply (default: {MAX_TOKENS}; {OFFLINE_MAX_TOKENS} with the offline model)", minimum=1,
        maximum=MAX_REPLY_TOKENS, resumable=True, run_key="always")
    """Longest reply asked for (the offline model's: :func:`model_defaults`)."""
    rollout_steps: int | None = setting(
        None, "training rollout horizon (default: the task's)", minimum=1, maximum=MAX_STEPS, run_key="always")
    """Training rollout horizon; None: the task's (400 Pong, 300 Breakout, 15 Space Invaders)."""
    eval_max_steps: int | None = setting(
        None, f"evaluation cap (default: the game's, {_TASK_EVAL_CAPS})", minimum=1, maximum=MAX_STEPS,
        run_key="always")
    """Evaluation cap; None: the task's (``games/<game>.py``)."""
    workers: int = setting(
        2, "episode worker processes (default: cores)", minimum=1, resumable=True, run_key="never", reproduce=False)
    """Worker processes for the episodes of an iteration (the command line's default: the machine's cores)."""
    call_time_limit_s: float = limit("call_time_limit_s", resumable=True, run_key="always")
    """Time limit of one policy call (``EpisodeLimits``)."""
    episode_time_limit_s: float = limit("episode_time_limit_s", cli=False, resumable=True, run_key="always")
    """Wall-clock limit of one episode (``EpisodeLimits``); a batch key, no flag of ``optimize``."""
    max_cost_usd: float | None = setting(
        None, "LLM cost, at litellm's price for the model (each call counted at its worst case: the prompt plus a "
        "reply of --max-tokens)", flag="--max-cost", metavar="USD", above=0, budget=True)
    """Stop (status ``budget``) before an LLM call that could take the run's cost past this many USD, counting
    the prompt and a reply of ``max_tokens`` at litellm's price; None: no limit. Needs a model litellm prices."""
    max_total_tokens: int | None = setting(
        None, "LLM input + output tokens", metavar="N", above=0, budget=True)
    """Stop (status ``budget``) before an LLM call that could take the run's input + output tokens past this."""
    max_llm_calls: int | None = setting(
        None, "LLM calls (an equal budget for comparing strategies)", metavar="N", above=0, budget=True)
    """Stop (status ``budget``) before LLM calls that would take the run's count of calls past this (an equal
    budget for comparing strategies: greedy makes one call per iteration, best-of-n N)."""
    max_wall_minutes: float | None = setting(
        None, "wall-clock time of the run's iterations", flag="--max-wall", metavar="MINUTES", above=0, budget=True)
    """Stop (status ``budget``) before an iteration that, lasting as long as the last one, would take the run's
    wall time (the sum of its iterations) past this many minutes; an LLM call in flight when that time runs out
    is given up on (``llm_calls.error_type`` ``OutOfTime``), and games still playing are stopped (their iteration
    is not committed)."""
    strategy: str = setting(
        "greedy", "greedy: the paper's loop, one proposal from the last version, rollback after a regression "
        "(default); best-of-n: N proposals from the best version, keep the best; beam: expand the --beam-width best "
        "versions; map-elites: improve random elites of an archive over code complexity x game length, with other "
        "elites as inspirations", choices=STRATEGIES, group="search")
    """Search strategy (``pipeline/optimizer/strategies.py``): ``greedy`` (the paper's loop), ``best-of-n``, ``beam``,
    ``map-elites``."""
    candidates: int | None = setting(
        None, "proposals per iteration (best-of-n, map-elites: default 4) or per beam member (beam: default 1)",
        metavar="N", minimum=1, maximum=MAX_CANDIDATES, group="search")
    """Proposals per parent and iteration: best-of-n's N (default 4), beam's proposals per beam member (default
    1); greedy makes one."""
    beam_width: int = setting(
        3, "beam: versions kept (default: 3)", metavar="K", minimum=1,
        group="search")
    """``beam``: how many of the best versions are kept and expanded."""
    max_concurrent_calls: int = setting(
        4, "LLM calls in flight at once (default: 4)", metavar="N", minimum=1, group="search", resumable=True,
        run_key="never")
    """At most this many LLM calls in flight at once (an iteration's proposals are requested concurrently)."""
    robust_episodes: int = setting(
        0, "also evaluate every version in N games under the standard protocol (sticky actions 0.25, up to 30 "
        "no-op starts; seeded), beside the paper's deterministic one (default: 0)", metavar="N", minimum=0,
        maximum=MAX_EPISODES, group="search")
    """Evaluation episodes under the standard protocol (sticky actions 0.25, up to 30 no-op starts; seeded, so
    reproducible) added to every assessment, beside the ``eval_episodes`` under the paper's; 0: none."""
    optimize_protocol: str = setting(
        "deterministic", "the score the strategy optimizes: deterministic (the paper's protocol, default) or "
        "standard (needs --robust-episodes)", flag="--optimize-for", choices=PROTOCOLS, group="search")
    """The score the strategy optimizes: ``deterministic`` (the paper's protocol) or ``standard`` (needs
    ``robust_episodes``): policies good under sticky actions, not only on one replayed trajectory."""
    screen_steps: int | None = setting(
        None, "cascade evaluation: a new version first plays N steps of the first evaluation game, and is assessed "
        "fully only if it keeps up with its parent there (default: off)", metavar="N", minimum=1, maximum=MAX_STEPS,
        group="search")
    """Cascade evaluation: before its full assessment, a new version plays the first evaluation game for this many
    steps; if it then trails its parent's score at the same step by more than ``screen_margin``, it is screened
    out (rejected, with both scores in its feedback) and never fully played. None: off."""
    screen_margin: float = setting(
        0.0, "how far behind its parent a screened version may be (default: 0)", metavar="POINTS", minimum=0,
        group="search")
    """How far behind its parent a screened version may be and still be assessed fully."""
    one_life: bool | str = setting(
        False, "every episode ends at a lost life", check=one_life_setting, group="search", switches=(
            Switch("--one-life", True, "every episode, training rollouts included, ends at a lost life: each the "
                   "first life of its own seeded game (default: whole games)"),
            Switch("--one-life-continue", "continue", "the authors' protocol for Asterix, Breakout, Q*bert and "
                   "Seaquest exactly: as --one-life, but the evaluation episodes are the lives of one game, each "
                   "going on where the one before ended")))
    """The authors' protocol for Asterix, Breakout, Q*bert and Seaquest (``Task.one_life_episodes``): every
    episode, training rollouts included, ends at a lost life. ``"continue"`` (``--one-life-continue``) is theirs
    exactly: the evaluation episodes of an assessment are the lives of one game from ``seed``, each going on where
    the one before ended (``games.wrappers.EpisodicLife``; the training rollout is that game's first life, the
    ``robust`` episodes each the first life of its own game); ``True`` (``--one-life``): every episode the first
    life of its own seeded game. Off: whole games (the paper's)."""
    observation: int = setting(
        OBSERVATION_VERSION, "the version of the observation conventions the run plays", cli=False,
        before_recorded=UNRECORDED_OBSERVATION)
    """The version of the observation conventions the run plays (``games.base.OBSERVATION_VERSION``): today's,
    recorded so that the run is read back and replayed with it after the conventions change."""
    collapse_repeats: bool = setting(
        True, "show repeated steps of the prompt's trace as one line", cli=False, before_recorded=False)
    """In the prompt's trace, show a run of consecutive steps whose calls, outputs and actions repeat as one line
    with its step range (more of the steps that matter fit the token budget)."""
    audit_episodes: int = setting(
        3, "when the run finishes, play the best version and the starting policy in N held-out games each (sealed "
        "seeds drawn then from the OS's entropy, never played by the loop nor shown to the model), under the "
        "standard protocol and the run's own; 0: no audit (default: 3)", metavar="N", minimum=0,
        maximum=MAX_EPISODES, group="search",
        resumable=True, run_key="never")
    """The held-out audit (``pipeline/optimizer/audit.py``): games per version and protocol on sealed audit seeds
    (drawn above ``games.base.AUDIT_SEED_BASE``), played when the run finishes; it never changes what the loop
    chose."""
    pool: bool = setting(
        False, "the asynchronous proposal pool (best-of-n, beam, map-elites): keep --max-concurrent-calls calls in "
        "flight across iterations, play each candidate as soon as its reply is in, and start the next call from the "
        "iterations committed by then; no iteration waits for its slowest call (default: off)", group="search")
    """The proposal pool (``pipeline/optimizer/pool.py``): candidates start as call slots free, each from the
    iterations committed when it starts (recorded: ``llm_calls.history_iterations``), are played as soon as they are
    ready, and iterations commit in order. Greedy keeps its strict order and refuses it."""
    repairs: int = setting(
        1, "when a reply is rejected before it is played (it does not parse, has the wrong methods or signatures, or "
        "raises or returns an invalid action on the recorded observations), send the model the exact error in the "
        "same conversation and take its corrected reply, up to N times (default: 1; 0: off)", metavar="N",
        minimum=0, maximum=5, group="search", before_recorded=0)
    """Repair turns (``pipeline/optimizer/propose.py``): each is its own LLM call, linked to the call it repairs
    (``llm_calls.repair_of``) and counted by every budget; the corrected reply is validated exactly as a first reply
    is. Runs recorded before repairs existed made none (``before_recorded``), so they replay call for call."""
    eval_cache: bool = setting(
        True, "play every version's episodes again instead of reusing those of an earlier assessment",
        group="search")
    """Reuse the stored episodes of a version already assessed in the run instead of playing them again (episodes
    are deterministic given the code and the run's settings)."""

    @classmethod
    def from_record(cls, recorded: dict[str, Any], run_id: str) -> "OptimizeConfig":
        """The config run ``run_id`` recorded (``runs.config``, as ``store.recorded.read_recorded`` reads it). A
        setting added after the run was made takes the value that reproduces what the run did
        (:data:`BEFORE_RECORDED`), not today's default. A store is anyone's file: each recorded setting is checked
        as its flag is (a string where a number goes, NaN, a huge number had ended ``--resume`` in a TypeError; an
        ensemble's price that is no number, ``models``), and one that is not what the setting takes is an
        ``unreadable_settings`` error naming it; keys that are no setting (the task's, a replay's) are left to
        their readers."""
        from store.recorded import unreadable_settings  # here: the command line's flags need no store

        problem = recorded_problem(cls, recorded)
        if problem is not None:
            raise unreadable_settings(run_id, problem)
        config = cls(**{**BEFORE_RECORDED, **{k: recorded[k] for k in cls.__dataclass_fields__ if k in recorded}})
        if config.models is not None:  # each entry as the loop reads it (a dict), whichever form passed the check
            config.models = model_entries(config.models)
        return config


BEFORE_RECORDED: dict[str, Any] = before_recorded(OptimizeConfig)
"""Settings that change prompts, as runs behaved before the setting existed: an old run replays prompt for
prompt (each setting's ``before_recorded``)."""

BUDGET_FIELDS = budgets(OptimizeConfig)
"""Limits of how far a run goes, not of what it does: ``--resume`` may change them, batch keys ignore them."""

RESUME_OVERRIDES = resumable(OptimizeConfig)
"""Settings that ``--resume`` takes from the command line (the resumable ones and the budgets); every other
setting is the run's own."""


def validate_config(config: OptimizeConfig) -> None:
    """ValueError (one line naming the flag) for a setting out of range: the one check the CLI, batch files and
    ``--resume`` share. Each setting's own checks are declared with it; here are those between settings."""
    check_settings(config)
    tuning_seeds = max(config.eval_episodes, config.robust_episodes, 1)
    if config.seed < 0 or config.seed + tuning_seeds > AUDIT_SEED_BASE:
        raise ValueError(f"--seed must be from 0 to {AUDIT_SEED_BASE - tuning_seeds}: the tuning "
                         f"seeds (--seed and the seeds after it) stay below the held-out audit seeds, which start at "
                         f"{AUDIT_SEED_BASE:,}")
    if config.pool and config.strategy == "greedy":
        raise ValueError("--pool is for best-of-n, beam and map-elites: greedy's next prompt needs the outcome of "
                         "the update before it (give --strategy best-of-n, beam or map-elites)")
    if config.optimize_protocol == "standard" and config.robust_episodes < 1:
        raise ValueError("--optimize-for standard needs --robust-episodes N (N >= 1): the episodes its score is "
                         "the mean of")
    check_choice(config.models, config.model_choice)
    if config.models and config.model != config.models[0]["model"]:
        raise ValueError("models: the run's model is the ensemble's first (give the ensemble as --model several "
                         "times)")
    make_strategy(config)
    if config.max_cost_usd is not None:
        from pipeline.llm.providers import price  # litellm: only when a cost budget needs its prices

        models = [entry["model"] for entry in config.models] if config.models else [config.model]
        unpriced = [model or "the offline model" for model in models if model is None or price(model) is None]
        if unpriced:
            raise ValueError(f"--max-cost needs litellm's price of every model, and it has none for "
                             f"{', '.join(unpriced)} (a local or unknown model): give --max-total-tokens or "
                             f"--max-llm-calls instead")


def model_defaults(settings: dict[str, Any]) -> dict[str, Any]:
    """``settings`` (an optimize run's, as given: the command line's flags or a batch entry) with the model's own
    defaults for what they leave out: the offline model (no ``model``) gets replies of ``OFFLINE_MAX_TOKENS`` and
    prompts of ``OFFLINE_TOKEN_BUDGET`` tokens (SmolLM2 on the CPU reads ~200 and writes ~80 tokens/s: this keeps
    an iteration near a minute). The command line and batch workers both start runs through it, so the same
    settings give the same run."""
    if settings.get("model"):
        return dict(settings)
    return {"max_tokens": OFFLINE_MAX_TOKENS, "token_budget": OFFLINE_TOKEN_BUDGET, **settings}


def fit_to_model(config: OptimizeConfig, prompt_cap: int | None) -> None:
    """Hold the prompt's token budget to what the model's context leaves beside the reply (``prompt_cap``, from
    ``open_client``; None: no cap), for the command line and batch workers alike. ValueError when that is less than
    the least budget: ``--max-tokens 9000`` with the offline model said "--token-budget must be at least 500, got
    -448", a setting the user had not given."""
    if prompt_cap is None or config.token_budget <= prompt_cap:
        return
    least = declarations(OptimizeConfig)["token_budget"][1].minimum
    if prompt_cap < least:
        raise ValueError(f"--max-tokens {config.max_tokens} leaves the model's context room for a prompt of "
                         f"{max(prompt_cap, 0):,} tokens, less than the least --token-budget ({least:,}): give a "
                         "smaller --max-tokens")
    config.token_budget = prompt_cap
