"""The held-out audit: a run's best version and its starting policy, played on games the loop never saw.

The loop selects on its *tuning* seeds (``--seed`` and the seeds after it); under the paper's protocol (sticky
actions 0, no no-op starts) every one of them is the same game, so a version that only memorised that game's
moves scores there exactly like one that plays. The audit plays the best version and the starter on the *audit*
seeds, ``games.base.AUDIT_SEED_BASE + i`` (disjoint from every tuning seed, which ``validate_config`` keeps below
them), ``audit_episodes`` games each under

- the **standard** protocol (sticky actions 0.25, up to 30 no-op starts): the game does not always do what the
  policy asks, and each seed starts differently, so a memorised sequence falls apart; and
- the run's **own** protocol (``run``: its evaluation settings on the new seeds).

Each set is scored by the one rule (``store/scores.py``: forfeits, a 95% interval) and stored as an ``audits``
row beside the version's tuning score; the episodes are stored too (kind ``audit``). The best's standard row
carries ``overfit`` (:func:`store.scores.overfit`: less than half of its gain over the starter holds up). The
audit never changes what the loop chose, and no prompt reads an audit episode (prompts are built from the
candidates' own episodes). It runs when a run finishes (``OptimizeConfig.audit_episodes``, default 3) and on
demand for any stored run (``codearcade audit RUN``), replacing the run's earlier audit.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Callable

from games.base import AUDIT_SEED_BASE, STANDARD_NOOP_MAX, STANDARD_STICKY
from pipeline.optimizer.config import OptimizeConfig
from pipeline.play.episodes import run_episodes
from pipeline.play.rollout import EpisodeSpec
from pipeline.play.runinfo import episode_id
from pipeline.play.verify import checked_outcome
from store import Store
from store.readers import audit_subjects, get_run
from store.scores import Score, overfit, score_episodes
from store.writer import EpisodeWriter, replace_audits

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
    def overfit(self) -> bool:
        best = self.row("best", "standard")
        return bool(best and best["overfit"])

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
            games = len(standard["seeds"])
            out.append(f"audit  {name} (iteration {standard['iteration']}) on {games} held-out game"
                       f"{'s' * (games != 1)}: standard protocol {_shown(standard)}, the run's own {_shown(own)}; "
                       f"tuning {_number(standard['tuning_score'])}")
        if self.overfit:
            out.append("audit  OVERFIT: less than half of the best version's gain over the starting policy holds up "
                       "on the held-out games (standard protocol)")
        return out


def _number(value: float | None) -> str:
    return "forfeit" if value is None else f"{value:.2f}".rstrip("0").rstrip(".")


def _shown(row: dict[str, Any]) -> str:
    """A score with its 95% interval when it has width, or the forfeit."""
    if row["score"] is None:
        return f"forfeit ({row['forfeit']})"
    band = row["score_low"] is not None and row["score_low"] != row["score_high"]
    return _number(row["score"]) + (f" [{_number(row['score_low'])}, {_number(row['score_high'])}]" if band else "")


def audit_run(store: Store, run_id: str, episodes: int | None = None, workers: int | None = None,
              progress: Callable[[int, int], None] | None = None, on_demand: bool = False) -> AuditResult:
    """Play the audit of ``run_id`` (see the module docstring) and store it; ``episodes`` and ``workers`` default
    to the run's own settings (``on_demand``, ``codearcade audit``: a run that turned its audit off, or was made
    before audits existed, gets the default number of games). A run without iterations has nothing to audit."""
    with store.read() as con:
        run = get_run(con, run_id)
        if run is None:
            raise ValueError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
        subjects = audit_subjects(con, run_id)
    if run["kind"] == "eval":
        raise ValueError(f"run {run_id} is an eval run: only optimization runs have a best version to audit")
    recorded = json.loads(run["config"])
    config = OptimizeConfig.from_record(recorded)
    n = episodes if episodes is not None else (config.audit_episodes or (OptimizeConfig.audit_episodes
                                                                          if on_demand else 0))
    if n < 1 or not subjects:
        return AuditResult(run_id, [])
    specs: list[EpisodeSpec] = []
    groups: dict[tuple[str, str], list[int]] = {}  # (version, protocol) -> indices of its specs
    for subject in {s["policy_version_id"]: s for s in subjects}.values():  # the best may be the starter
        for protocol, (sticky, noop_max) in PROTOCOLS.items():
            indices = groups.setdefault((subject["policy_version_id"], protocol), [])
            for i in range(n):
                indices.append(len(specs))
                specs.append(EpisodeSpec(
                    episode_id=episode_id(run_id, subject["iteration"], f"audit-{protocol}", i), run_id=run_id,
                    game=run["game"], policy_text=subject["policy_text"],
                    policy_version_id=subject["policy_version_id"], iteration=subject["iteration"], kind="audit",
                    index=i, seed=AUDIT_SEED_BASE + i, max_steps=recorded["eval_max_steps"], sticky=sticky,
                    noop_max=noop_max, one_life=bool(config.one_life), observation=config.observation,
                    call_time_limit_s=config.call_time_limit_s, episode_time_limit_s=config.episode_time_limit_s,
                    rng_key=recorded.get("rng_key")))
    outcomes: list[dict[str, Any] | None] = [None] * len(specs)
    with EpisodeWriter(store, replace=True) as writer:
        for i, outcome in run_episodes(specs, workers=max(1, workers or config.workers), progress=progress):
            outcome = checked_outcome(specs[i], outcome)
            writer.add(outcome.episode, outcome.steps, outcome.nodes)
            outcomes[i] = outcome.episode
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
    result = AuditResult(run_id, rows)
    best, starter = result.row("best", "standard"), result.row("starter", "standard")
    if best is not None and starter is not None:
        best["overfit"] = overfit(best["tuning_score"], starter["tuning_score"], best["score"], starter["score"])
    with store.write() as con:
        replace_audits(con, run_id, rows)
    return result
