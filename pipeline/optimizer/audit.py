"""The held-out audit: a run's best version and its starting policy, played on games the loop never saw.

The loop selects on its *tuning* seeds (``--seed`` and the seeds after it); under the paper's protocol (sticky
actions 0, no no-op starts) every one of them is the same game, so a version that only memorised that game's
moves scores there exactly like one that plays. The audit plays the best version and the starter on the same
``audit_episodes`` *audit* seeds, drawn when the audit runs from the OS's entropy over the seeds above every tuning
seed (``games.base.AUDIT_SEED_BASE`` up; ``validate_config`` keeps tuning seeds below it). They are **sealed**:
no code, doc or prompt holds them and no policy can know them in advance (a policy that replays moves recorded for
some games plays blind on these), and they are recorded only with the episodes they produced (and the ``audits``
row that lists them), so ``codearcade audit RUN --seeds ...`` can play the same games again. Two protocols:

- the **standard** protocol (sticky actions 0.25, up to 30 no-op starts): held out — the game does not always do
  what the policy asks, and each seed starts differently, so a memorised sequence falls apart; and
- the run's **own** protocol (``run``: its evaluation settings, ``--one-life`` and ``--one-life-continue``
  included, on the audit seeds). Held out only where the run's protocol is stochastic: under the paper's
  (sticky 0, no no-op starts) every seed is the same game, so this is the tuning game again, and says so.

Each set is scored by the one rule (``store/scores.py``: forfeits, an interval) and stored as an ``audits`` row
beside the version's tuning score; the episodes are stored too (kind ``audit``). The best's standard row carries
``overfit`` (:func:`store.scores.overfit`: less than half of its gain over the starter holds up; NULL, no reference,
when the starter forfeited its audit games). The audit never
changes what the loop chose, and no prompt reads an audit episode (prompts are built from the candidates' own
episodes). It runs when a run finishes (``OptimizeConfig.audit_episodes``, default 3) and on demand for any
stored run (``codearcade audit RUN``), replacing the run's earlier audit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

from games.base import (AUDIT_SEED_BASE, AUDIT_SEED_END, ONE_LIFE_CONTINUE, STANDARD_NOOP_MAX, STANDARD_STICKY,
                        draw_audit_seeds)
from pipeline.optimizer.config import OptimizeConfig
from pipeline.play.episodes import run_episodes
from pipeline.play.runinfo import audit_episode_id, new_audit_token
from pipeline.play.spec import EpisodeSpec
from pipeline.play.verify import checked_outcome
from store import Store
from store.readers import audit_subjects, get_run
from store.recorded import read_recorded
from store.scores import NO_REFERENCE, Score, overfit, score_episodes
from store.statistics import MEAN_METHOD, interval_text
from pipeline.stopping import uninterrupted
from store.writer import EpisodeWriter, delete_episodes, replace_audits

PROTOCOLS = {"standard": (STANDARD_STICKY, STANDARD_NOOP_MAX), "run": (0.0, 0)}
"""The audit's protocols: (sticky action probability, most no-op starts). ``run``: the run's own evaluation."""


@dataclass
class AuditResult:
    run_id: str
    rows: list[dict[str, Any]]
    """The ``audits`` rows written (role, protocol, score, interval, forfeit, tuning score, overfit)."""

    def row(self, role: str, protocol: str) -> dict[str, Any] | None:
        return next((r for r in self.rows if r["role"] == role and r["protocol"] == protocol), None)

    @property
    def overfit(self) -> bool | None:
        """The best's flag (:func:`store.scores.overfit`); None when there is no reference to tell by."""
        best = self.row("best", "standard")
        return False if best is None else best["overfit"]

    def lines(self) -> list[str]:
        """What a person reads: a line per audited version (the best, the starter; one when they are the same
        version) with both protocols' scores beside its tuning score, then the verdict."""
        out = []
        best = self.row("best", "standard")
        for role in ("best", "starter"):
            standard, own = self.row(role, "standard"), self.row(role, "run")
            if standard is None or (role == "starter" and standard["policy_version_id"] == best["policy_version_id"]):
                continue
            name = "best = starter" if role == "best" and standard["iteration"] == 0 else role
            games = len(set(standard["seeds"]))
            own_text = "" if own is None else f"; not held out, the run's own protocol (the tuning game again): " \
                                              f"{_shown(own)}"
            out.append(f"audit  {name} (iteration {standard['iteration']}): held out, the standard protocol on {games} "
                       f"sealed game{'s' * (games != 1)}: {_shown(standard)}{own_text}; tuning "
                       f"{_number(standard['tuning_score'])}")
        if self.overfit:
            out.append("audit  OVERFIT: less than half of the best version's gain over the starting policy holds up "
                       "on the held-out games (standard protocol)")
        elif best is not None and self.overfit is None:
            out.append(f"audit  overfit: {NO_REFERENCE}")
        return out


def _number(value: float | None) -> str:
    return "forfeit" if value is None else f"{value:.2f}".rstrip("0").rstrip(".")


def _shown(row: dict[str, Any]) -> str:
    """A score with its interval, level, method and n (``store.statistics.interval_text``; a score means no game was
    forfeited, so n is its games), or the forfeit."""
    if row["score"] is None:
        return f"forfeit ({row['forfeit']})"
    return interval_text(row["score"], row["score_low"], row["score_high"], len(row["seeds"]), MEAN_METHOD)


def check_audit_seeds(seeds: Sequence[int], one_game: bool | None = False) -> list[int]:
    """The seeds ``codearcade audit --seeds`` replays, checked: each in the audit's range (a seed below it may be
    a tuning seed, and those games are not held out), and distinct, but for a ``--one-life-continue`` run
    (``one_game``), whose audit is the lives of one game, one seed a life as its audits row lists them (None: not
    known yet, as the command line is read). ValueError with one line."""
    seeds = list(seeds)
    if not seeds:
        raise ValueError("--seeds needs at least one seed")
    outside = [s for s in seeds if not AUDIT_SEED_BASE <= s < AUDIT_SEED_END]
    if outside:
        raise ValueError(f"--seeds: {outside[0]} is not an audit seed (they are from {AUDIT_SEED_BASE:,} to "
                         f"{AUDIT_SEED_END - 1:,}; an audit's seeds are in its audits rows and its episodes)")
    distinct = len(set(seeds))
    if one_game and distinct > 1:
        raise ValueError("--seeds: the run plays --one-life-continue, so its audit is one game, its lives on one "
                         "seed: give that seed once a life, as its audits row lists it (1234567,1234567,1234567)")
    if not one_game and distinct != len(seeds) and (one_game is False or distinct > 1):
        raise ValueError("--seeds: each seed once (a seed twice is the same game twice)")
    return seeds


def audit_run(store: Store, run_id: str, episodes: int | None = None, workers: int | None = None,
              progress: Callable[[int, int], None] | None = None, on_demand: bool = False,
              seeds: Sequence[int] | None = None, on_play: Callable[[int], None] | None = None,
              on_episode: Callable[[int, int], None] | None = None) -> AuditResult:
    """Play the audit of ``run_id`` (see the module docstring) and store it; ``episodes`` and ``workers`` default
    to the run's own settings (``on_demand``, ``codearcade audit``: a run that turned its audit off, or was made
    before audits existed, gets the default number of games). ``seeds``: the games to play (an earlier audit's,
    to reproduce it; their number is the number of games), else drawn afresh (:func:`draw_audit_seeds`). A run
    without iterations has nothing to audit. ``on_play(n)`` is called before its n episodes play, ``progress(i,
    steps)`` as episode i plays and ``on_episode(i, length)`` as it ends (the command line's progress)."""
    with store.read() as con:
        run = get_run(con, run_id)
        if run is None:
            raise ValueError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
        subjects = audit_subjects(con, run_id)
    if run["kind"] == "eval":
        raise ValueError(f"run {run_id} is an eval run: only optimization runs have a best version to audit")
    recorded = read_recorded(run["config"], run_id)
    config = OptimizeConfig.from_record(recorded, run_id)
    one_game = config.one_life == ONE_LIFE_CONTINUE  # the run's episodes are the lives of one game: so the audit's
    if seeds is not None:
        seeds = check_audit_seeds(seeds, one_game)
        n = len(seeds)
    else:
        n = episodes if episodes is not None else (config.audit_episodes or (OptimizeConfig.audit_episodes
                                                                              if on_demand else 0))
    if n < 1 or not subjects:
        return AuditResult(run_id, [])
    if seeds is None:
        seeds = draw_audit_seeds(1 if one_game else n)
    audit = new_audit_token()
    specs: list[EpisodeSpec] = []
    groups: dict[tuple[str, str], list[int]] = {}  # (version, protocol) -> indices of its specs
    for subject in {s["policy_version_id"]: s for s in subjects}.values():  # the best may be the starter
        for protocol, (sticky, noop_max) in PROTOCOLS.items():
            indices = groups.setdefault((subject["policy_version_id"], protocol), [])
            for i in range(n):
                indices.append(len(specs))
                specs.append(EpisodeSpec(
                    episode_id=audit_episode_id(run_id, subject["iteration"], protocol, i, audit), run_id=run_id,
                    game=run["game"], policy_text=subject["policy_text"],
                    policy_version_id=subject["policy_version_id"], iteration=subject["iteration"], kind="audit",
                    index=i, seed=seeds[0] if one_game else seeds[i], max_steps=recorded["eval_max_steps"],
                    sticky=sticky, noop_max=noop_max, one_life=config.one_life, observation=config.observation,
                    continues=audit_episode_id(run_id, subject["iteration"], protocol, i - 1, audit)
                    if one_game and i else None,
                    call_time_limit_s=config.call_time_limit_s, episode_time_limit_s=config.episode_time_limit_s,
                    rng_key=recorded.get("rng_key")))
    audited = False
    try:
        outcomes: list[dict[str, Any] | None] = [None] * len(specs)
        if on_play is not None:
            on_play(len(specs))
        with EpisodeWriter(store, replace=True) as writer:
            for i, outcome in run_episodes(specs, workers=max(1, workers or config.workers), progress=progress):
                outcome = checked_outcome(specs[i], outcome)
                writer.add(outcome.episode, outcome.steps, outcome.nodes)
                outcomes[i] = outcome.episode
                if on_episode is not None:
                    on_episode(i, outcome.episode["length"])
        result = AuditResult(run_id, _audit_rows(subjects, specs, groups, outcomes))
        best, starter = result.row("best", "standard"), result.row("starter", "standard")
        if best is not None and starter is not None:
            best["overfit"] = overfit(best["tuning_score"], starter["tuning_score"], best["score"], starter["score"])
        with uninterrupted():  # a press in the write that replaces the earlier audit lands after it
            with store.write() as con:
                replace_audits(con, run_id, result.rows)
            audited = True
    except BaseException:
        if not audited:  # the earlier audit stands, with its games; this one's, played or not, go
            _forget_games(store, [spec.episode_id for spec in specs])
        raise
    return result


def _audit_rows(subjects: list[dict[str, Any]], specs: list[EpisodeSpec], groups: dict[tuple[str, str], list[int]],
                outcomes: list[dict[str, Any] | None]) -> list[dict[str, Any]]:
    """The ``audits`` rows of the games played: one per subject (best, starter) and protocol (``overfit`` None:
    the caller sets the best's against the starter)."""
    scores: dict[tuple[str, str], Score] = {key: score_episodes(outcomes[i] for i in indices)
                                            for key, indices in groups.items()}
    rows = []
    for subject in subjects:
        for protocol in PROTOCOLS:
            key = (subject["policy_version_id"], protocol)
            score = scores[key]
            rows.append(dict(role=subject["role"], protocol=protocol, policy_version_id=subject["policy_version_id"],
                             iteration=subject["iteration"], seeds=[specs[i].seed for i in groups[key]],
                             episode_ids=[specs[i].episode_id for i in groups[key]], score=score.ranked,
                             score_low=score.low if score.ranked is not None else None,
                             score_high=score.high if score.ranked is not None else None, forfeit=score.forfeit,
                             tuning_score=subject["tuning_score"], overfit=None))
    return rows


def _forget_games(store: Store, episode_ids: list[str]) -> None:
    """Delete the games of an audit that did not replace the run's earlier one (stopped, or failed): ``kind =
    'audit'`` keeps only the games the ``audits`` rows list. Never raises: the caller re-raises what stopped it (a
    killed process leaves them, and the next audit deletes them)."""
    try:
        with uninterrupted(), store.write() as con:
            delete_episodes(con, episode_ids)
    except Exception:  # noqa: BLE001 - the store's own failure; what stopped the audit says what happened
        pass
