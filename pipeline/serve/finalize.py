"""The end of a served run (``codearcade serve``, ``pipeline/serve/protocol.py``): its sealed pools played and scored.

Once the budget is spent (or ``codearcade serve --finalize RUN``), every accepted submission plays the
**validation** pool, and the best by validation, beside the starter, plays the **held-out** pool. Both pools are
drawn now, in one draw so they are disjoint (``games.base.draw_audit_seeds``), from the audit's range, so they
never meet a training instance; every game is played under the run's standard protocol, untraced, stored like any
run's and scored by the one rule (``store/scores.py``: a forfeit has no score).

What is written are ``audits`` rows: ``role = 'submission N', protocol = 'validation'`` per accepted submission,
and ``best`` / ``starter`` with protocol ``standard`` for the held-out pool, so ``runs``, ``report`` and ``audit``
show the held-out score where they show an audit's. The best's row carries ``overfit`` by the audit's rule
(``store.scores.overfit``), its training gain measured against the starter's held-out score (the starter plays no
training instance); None (no reference) when the starter forfeited its held-out games. No response to the agent
carries the pools' seeds or scores.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

from games.base import draw_audit_seeds
from pipeline.play.episodes import run_episodes
from pipeline.play.runinfo import episode_id
from pipeline.play.spec import EpisodeSpec
from pipeline.play.verify import checked_outcome
from store import Store
from store.readers import get_run, policy_text
from store.scores import overfit, score_episodes
from store.serve import served_submissions
from store.writer import EpisodeWriter, finish_run, replace_audits


class Stopped(Exception):
    """The server stopped while this request played: its games ended with the server, not with their policies, so
    nothing of what they showed is kept (a finalize is not: the run stays open)."""


def finalize_run(store: Store, run_id: str, record: dict[str, Any],
                 progress: Callable[[int, int], None] | None = None,
                 stopping: threading.Event | None = None) -> list[dict[str, Any]]:
    """The end of a served run (see the module docstring): the ``audits`` rows it wrote. ``stopping``: set when
    the server stops; games played then ended with it (a Ctrl-C reaches their workers), and a validation game
    stored as crashed made a submission read as forfeited and the run finished: :class:`Stopped` instead, the
    run left open, nothing audited."""

    def played(scores):
        if stopping is not None and stopping.is_set():
            raise Stopped("the server stopped while the run was being finalized: nothing was audited, and "
                          "`codearcade serve --finalize RUN` finalizes it")
        return scores

    s = record["serve"]
    with store.read() as con:
        subs = [x for x in served_submissions(con, run_id) if x["update_status"] == "accepted"]
        starter_id = get_run(con, run_id)["starter_version_id"]
        texts = {x["policy_version_id"]: policy_text(con, run_id, x["policy_version_id"]) for x in subs}
        texts[starter_id] = policy_text(con, run_id, starter_id)
    n_val, n_held = s["validation_episodes"], s["heldout_episodes"]
    seeds = draw_audit_seeds(n_val + n_held)  # one draw: the two pools are disjoint
    validation, heldout = seeds[:n_val], seeds[n_val:]
    first = {}  # a version submitted twice plays once, as its first submission
    for x in subs:
        first.setdefault(x["policy_version_id"], x)

    def spec(version: str, iteration: int, kind: str, tag: str, i: int, seed: int) -> EpisodeSpec:
        return EpisodeSpec(episode_id=episode_id(run_id, iteration, tag, i), run_id=run_id, game=record["game"],
                           policy_text=texts[version], policy_version_id=version, iteration=iteration, kind=kind,
                           index=i, seed=seed, max_steps=s["max_steps"], sticky=s["sticky"], noop_max=s["noop_max"],
                           call_time_limit_s=s["call_time_limit_s"], episode_time_limit_s=s["episode_time_limit_s"],
                           observation=record["observation"], rng_key=record.get("rng_key"))

    val_specs = [spec(v, x["iteration"], "validation", "validation", i, seed)
                 for v, x in first.items() for i, seed in enumerate(validation)]
    val_scores = played(_play_scored(store, val_specs, progress, stopping))
    rows = []
    for v, x in first.items():
        score, ids = val_scores[v]
        rows.append(_audit_row(f"submission {x['iteration']}", "validation", v, x["iteration"], validation, ids,
                               score, x["score"]))
    ranked = [(val_scores[v][0].ranked, -x["iteration"], v) for v, x in first.items()
              if val_scores[v][0].ranked is not None]
    if ranked:
        _, neg_it, best = max(ranked)
        subjects = {"best": (best, -neg_it, first[best]["score"]), "starter": (starter_id, 0, None)}
        held_specs = [spec(v, it, "audit", "audit-standard" if role == "best" else "audit-starter", i, seed)
                      for role, (v, it, _) in subjects.items() for i, seed in enumerate(heldout)]
        if best == starter_id:
            held_specs = held_specs[:n_held]
        held_scores = played(_play_scored(store, held_specs, progress, stopping))
        for role, (v, it, tuning) in subjects.items():
            score, ids = held_scores[v]
            rows.append(_audit_row(role, "standard", v, it, heldout, ids, score, tuning))
        best_row, starter_row = rows[-2], rows[-1]
        # the starter never plays the training instances (its tuning score is None, which the rule reads as no
        # gain claimed: nothing was ever flagged); every game here is the standard protocol, so its held-out
        # score stands in for what it would have scored there. The starter itself as best claims no gain.
        # a starter that forfeited its held-out games leaves no reference: its gain is not known (None, said as
        # "no reference" as the audit says it), where the rule read the missing score as no gain claimed (False)
        best_row["overfit"] = (False if best == starter_id else None if starter_row["score"] is None
                               else overfit(best_row["tuning_score"], starter_row["score"], best_row["score"],
                                            starter_row["score"]))
    with store.write() as con:
        replace_audits(con, run_id, rows)
        finish_run(con, run_id, "finished")
    return rows


def _play_scored(store: Store, specs: list[EpisodeSpec], progress,
                 stopping: threading.Event | None = None) -> dict[str, tuple[Any, list[str]]]:
    """Play ``specs`` (untraced), store them, and score each version's episodes by the one rule; no more once
    ``stopping`` is set (the caller then keeps nothing of them)."""
    by_version: dict[str, list[dict[str, Any]]] = {}
    with EpisodeWriter(store, replace=True) as writer:
        for i, outcome in run_episodes(specs, workers=1, progress=progress):
            if stopping is not None and stopping.is_set():
                break
            outcome = checked_outcome(specs[i], outcome)
            writer.add(outcome.episode, outcome.steps, outcome.nodes)
            by_version.setdefault(specs[i].policy_version_id, []).append(outcome.episode)
    return {v: (score_episodes(eps), [e["episode_id"] for e in sorted(eps, key=lambda e: e["episode_id"])])
            for v, eps in by_version.items()}


def _audit_row(role: str, protocol: str, version: str, iteration: int, seeds: list[int], episode_ids: list[str],
               score, tuning: float | None) -> dict[str, Any]:
    ranked = score.ranked
    return dict(role=role, protocol=protocol, policy_version_id=version, iteration=iteration, seeds=list(seeds),
                episode_ids=episode_ids, score=ranked, score_low=score.low if ranked is not None else None,
                score_high=score.high if ranked is not None else None, forfeit=score.forfeit, tuning_score=tuning,
                overfit=None)
