"""``codearcade eval``: play a policy file for N episodes and put everything in the store.

The whole job in one place: read and check the policy statically (a broken file fails here with one line;
policy code itself only ever runs in the workers), check the store (a damaged one is refused before anything
plays), create a run (kind ``eval``) with its policy version, play the episodes (each by a game host with a
confined policy process: ``pipeline/play/episodes.py``; the host computes the score, the policy only chooses
actions), clean what came from policy code (``pipeline/play/verify.py``), write each episode in its own
transaction, and mark the run finished, failed or interrupted.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

from games import get_game
from games.base import ONE_LIFE_CONTINUE, one_life_setting
from pipeline.play.episodes import run_episodes
from pipeline.play.rollout import EpisodeOutcome
from pipeline.play.runinfo import episode_id, new_run_id, package_versions
from pipeline.play.spec import EpisodeSpec
from pipeline.play.validate import checked_inspect, resolve_game
from pipeline.play.verify import checked_outcome
from pipeline.play.versions import policy_version_row
from pipeline.play.config import EvalConfig  # noqa: F401  (its home; callers import it from here too)
from pipeline.settings import check_settings
from pipeline.stopping import uninterrupted
from store import Store
from store.db import StoreError, is_ctrl_c
from store.locks import run_lock
from store.scores import Score, score_episodes, score_json
from store.writer import EpisodeWriter, finish_run, insert_policy_version, insert_run
from tracing.policy_file import read_policy_file


@dataclass
class EvalResult:
    run_id: str
    game: str
    policy_version_id: str
    outcomes: list[EpisodeOutcome]
    """Each episode's row (``episode``, ``end_reason``, ``printed``); its steps and node rows are in the store."""

    @property
    def score(self) -> Score:
        """The episodes' score (``store/scores.py``): the mean of those played out, its interval, the forfeits."""
        return score_episodes(o.episode for o in self.outcomes)

    def summary(self) -> dict:
        """The machine-readable summary printed by ``codearcade eval --json``."""
        score = self.score
        return {
            "run_id": self.run_id,
            "game": self.game,
            "policy_version_id": self.policy_version_id,
            # by the one rule (store/scores.py): score is null with any forfeit, and the forfeits are listed
            **score_json(score),
            "headline": score.summary(),
            "episodes": [
                {
                    "episode_id": o.episode["episode_id"],
                    "seed": o.episode["seed"],
                    "return": o.episode["return"],
                    "length": o.episode["length"],
                    "end_reason": o.end_reason,
                    "error": o.episode["error"],
                }
                for o in self.outcomes
            ],
        }


def evaluate(
    policy_path: str | Path,
    config: EvalConfig,
    store: Store,
    progress: Callable[[int, int], None] | None = None,
    on_episode: Callable[[int, int], None] | None = None,
    *,
    run_name: str | None = None,
    made_by: str | None = None,
    on_start: Callable[[str], None] | None = None,
) -> EvalResult:
    """Evaluate the policy file at ``policy_path``; see the module docstring. Raises PolicyLoadError,
    UnknownGameError or StoreError with one-line messages for bad input, before anything is stored.

    ``run_name`` labels the run and ``made_by`` marks one a command plays for its own use (``runs.name``,
    ``runs.made_by``); ``on_start`` gets the run id once its row is stored."""
    check_settings(config)
    one_life = one_life_setting(config.one_life)
    text = read_policy_file(policy_path)
    name = Path(policy_path).name
    info = checked_inspect(text, name, workers=config.workers)  # parsed in a confined worker first
    game = resolve_game(info.game, config.game, name)
    get_game(game).check_one_life(one_life)

    store.make_ready()  # creates or upgrades the store, and refuses a damaged one, before anything plays
    run_id = new_run_id()
    rng_key = config.rng_key or run_id  # the policy's random stream (EpisodeSpec.rng_key)
    one_game = one_life == ONE_LIFE_CONTINUE  # the authors' protocol: the episodes are the lives of one game
    specs = [
        EpisodeSpec(
            episode_id=episode_id(run_id, 0, "eval", i), run_id=run_id, game=game, policy_text=text,
            policy_version_id=info.version_id, policy_name=name, iteration=0, kind="eval", index=i,
            seed=config.seed if one_game else config.seeds[i] if config.seeds else config.seed + i,
            max_steps=config.max_steps, sticky=config.sticky,
            noop_max=config.noop_max, one_life=one_life, observation=config.observation, trace=config.trace,
            trace_lines=config.trace_lines,
            call_time_limit_s=config.call_time_limit_s, episode_time_limit_s=config.episode_time_limit_s,
            rerun=config.rerun, continues=episode_id(run_id, 0, "eval", i - 1) if one_game and i else None,
            rng_key=rng_key,
        )
        for i in range(config.episodes)
    ]

    def create_run() -> None:  # runs while the first episodes play
        # a press as the run is made lands once it is whole (as optimize's does): the run's end below then marks it
        # interrupted. Cut inside its transaction, a Ctrl-C to the process group left an eval's run 'running'
        with uninterrupted():
            with store.write() as con:
                insert_run(con, run_id, "eval", game, {**asdict(config), "game": game, "policy": str(policy_path),
                                                       "rng_key": rng_key},
                           text, info.version_id, package_versions(), seed=config.seed, name=run_name,
                           made_by=made_by)
                insert_policy_version(con, policy_version_row(info, run_id, 0, produced_by="file",
                                                              validation="unvalidated"))
            if on_start is not None:
                on_start(run_id)

    outcomes: list[EpisodeOutcome | None] = [None] * len(specs)
    status, error = "failed", None
    with ExitStack() as held:
        try:  # held while the run is "running", so `runs` and `doctor` tell a live eval from a killed one
            held.enter_context(run_lock(store.path, run_id))
        except (OSError, StoreError):  # a read-only or full directory (the store's own one-line error says so
            pass  # below), or its locks folder a file: an evaluation is one process's, the lock only shows it live
        writer = EpisodeWriter(store)
        try:
            for i, outcome in run_episodes(specs, workers=config.workers, progress=progress, started=create_run):
                outcome = checked_outcome(specs[i], outcome, hosted=config.workers > 0)
                writer.add(outcome.episode, outcome.steps, outcome.nodes)
                # the row is kept, its steps and node rows only until written: a run of many traced episodes
                # held them all (40 episodes of ~31 KB of node rows a step took the process to 1.2 GB)
                outcomes[i] = replace(outcome, steps=outcome.steps.slice(0, 0), nodes=None)
                if on_episode is not None:
                    on_episode(i, outcome.episode["length"])
            status = "finished"
        except KeyboardInterrupt:
            status, error = "interrupted", "interrupted by the user"
            raise
        except BaseException as exc:
            if is_ctrl_c(exc):  # DuckDB's own word for a Ctrl-C that reached it past the store's conversion
                status, error = "interrupted", "interrupted by the user"
                raise KeyboardInterrupt from None
            status, error = "failed", f"{type(exc).__name__}: {exc}"
            raise
        finally:  # the episodes not yet written and the run's end, in one transaction (a press in it had rolled
            # it back: a run whose games were all played left 'running')
            with uninterrupted():
                writer.flush(also=lambda con: finish_run(con, run_id, status, error))
    return EvalResult(run_id, game, info.version_id, [o for o in outcomes if o is not None])
