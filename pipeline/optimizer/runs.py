"""``codearcade compare A B`` of two optimization runs: their learning curves side by side, a budget-matched table
(the best score each run had reached within the same number of LLM calls, thousand tokens and wall seconds;
only budgets both runs spent are matched, so neither is credited with spending it never made), the unified
diff of their best versions, each best score with its 95% interval (``store.scores.score_episodes`` of the
episodes that scored it, computed now: a store made before issue 37 holds percentile-bootstrap intervals), and
whether the two bests differ beyond the noise (:func:`best_difference`).

That verdict rests on held-out games only. Each best is its run's highest-scoring version, picked on the very
episodes that scored it, so a test on those episodes is biased: identical policies, the best of 20 against a
starter, were called different 10-19% of the time at 3-10 episodes by a 5% test (tests/test_compare_selection.py).
So when both bests have a held-out audit (``codearcade audit RUN``: sealed seeds, the standard protocol), the
verdict is ``store.scores.compare_scores`` (Welch's t) of those games, with the tuning figures beside; when either
has none, the tuning difference and its interval are shown but no verdict is given, only which audit would give
one. By the one rule, a best whose games include a forfeit has no score, and then there is no verdict, only why,
and the sensitivity line.

Everything is read back from the store (``store/comparisons.py``) and returned as plain data
(``viewers/compare_report.py`` renders it). It lives beside the optimizer because what it weighs is the
optimizer's spending; two policy versions are played against each other by ``pipeline/play/versus.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

from pipeline.optimizer.config import OptimizeConfig
from pipeline.play.versus import LABELS, difference_data, unified_diff
from pipeline.settings import recorded_settings
from store import Store
from store.comparisons import best_evaluation, best_version, held_out_evaluation, learning_curve
from store.readers import get_run, policy_text
from store.runs import kind_phrase, shown_status
from store.scores import Score, score_data, score_episodes
from store.statistics import interval_text
from store.views import resolve_run_id


@dataclass
class RunComparison:
    game: str
    runs: list[dict[str, Any]]
    curves: dict[str, list[dict[str, Any]]]
    budgets: list[dict[str, Any]]
    diff: str
    difference: dict[str, Any]
    """A's best minus B's best with its 95% interval, whether that leaves out 0, and the verdict in words, on the
    bests' held-out games when both have them, else on the tuning episodes without a verdict
    (:func:`best_difference`)."""
    cautions: list[str]
    """The settings that change what a score is (:data:`SCORE_SETTINGS`) where the two runs differ, in words."""

    def as_dict(self) -> dict[str, Any]:
        return {"mode": "runs", "game": self.game, "runs": self.runs, "curves": self.curves,
                "budgets": self.budgets, "diff": self.diff, "difference": self.difference, "cautions": self.cautions}


SCORE_SETTINGS = {"eval_max_steps": "the evaluation's step cap", "eval_episodes": "the evaluation games per score",
                  "one_life": "the one-life protocol", "optimize_protocol": "the protocol scored",
                  "robust_episodes": "the standard-protocol games per score", "observation": "the observation"}
"""Settings of a run that change what its scores are: two runs that differ in one score different things."""


def _cautions(configs: list[dict[str, Any]]) -> list[str]:
    return [f"the runs differ in {what} ({name}: A {configs[0].get(name)!r}, B {configs[1].get(name)!r}): their "
            "scores measure different things" for name, what in SCORE_SETTINGS.items()
            if configs[0].get(name) != configs[1].get(name)]


def compare_runs(store: Store, a: str, b: str) -> RunComparison:
    """Learning curves, budget-matched table and best-version diff of two optimization runs."""
    with store.read() as con:
        ids = [resolve_run_id(con, x, store) for x in (a, b)]
        runs, curves, texts, scores, configs, held_out = [], {}, [], [], [], []
        for label, run_id in zip(LABELS, ids):
            run = get_run(con, run_id)
            curve = learning_curve(con, run_id)
            best = best_version(con, run_id)
            if not curve or best is None:
                raise ValueError(f"run {run_id} is {kind_phrase(run['kind'])} without iterations: compare optimization "
                                 f"runs, or play its policy against another version with {run_id}:best")
            if best["policy_version_id"] is None:  # a finalized served run whose validation picked none
                raise ValueError(f"run {run_id} has no best: every submission forfeited a validation game")
            texts.append(policy_text(con, run_id, best["policy_version_id"]))
            # a store is anyone's file: settings that do not read are one line naming the run and the setting
            configs.append(recorded_settings(OptimizeConfig, run["config"], run_id, tuple(SCORE_SETTINGS)))
            assessed = best_evaluation(con, run_id) or {"episodes": []}
            scored = score_episodes(assessed["episodes"])
            scores.append(scored)
            audit = held_out_evaluation(con, run_id)
            audited = audit is not None and audit["policy_version_id"] == best["policy_version_id"]
            held = score_episodes(audit["episodes"]) if audited else None
            held_out.append(held)
            curves[label] = [_curve_point(row) for row in _cumulative_calls(curve)]
            last = curves[label][-1]
            runs.append({"label": label, "run_id": run_id, "kind": run["kind"], "game": run["game"],
                         "model": run["model"], "status": shown_status(store.path, run_id, run["status"]),
                         "iterations": len(curve) - 1,
                         "llm_calls": last["llm_calls"], "total_tokens": last["tokens"], "elapsed_s": last["elapsed_s"],
                         "best_score": None if scored.forfeited else best["score"],
                         "best_forfeited": scored.forfeited, "best_no_score": scored.no_score,
                         "best_low": scored.low if scored.ranked is not None else None,
                         "best_high": scored.high if scored.ranked is not None else None,
                         "best_episodes": len(assessed["episodes"]),
                         # the protocol of those episodes: the paper's replays one game (optimize_protocol); a
                         # served run plays every game under the standard one
                         "best_protocol": "standard" if run["kind"] == "serve"
                         else configs[-1].get("optimize_protocol") or "deterministic",
                         # what picked the best and scored it: validation for a finalized served run
                         "best_by": best["best_by"],
                         "best_iteration": best["iteration"],
                         "best_version_id": best["policy_version_id"],
                         "held_out": None if held is None else {
                             **score_data(held), "score": held.ranked, "no_score": held.no_score,
                             "seeds": [e["seed"] for e in audit["episodes"]], "summary": held.summary()},
                         "held_out_missing": None if audited else (
                             "never audited" if audit is None else
                             f"its audit played an earlier best (iteration {audit['iteration']})")})
    games = {r["game"] for r in runs}
    if len(games) > 1:
        raise ValueError(f"runs {ids[0]} ({runs[0]['game']}) and {ids[1]} ({runs[1]['game']}) play different games; "
                         "scores of different games do not compare")
    names = [f"{r['run_id']}:{r['best_version_id']} (best{' by validation' * (r['best_by'] == 'validation')}, "
             f"iteration {r['best_iteration']}, "
             + (f"score {r['best_score']:g})" if r["best_score"] is not None else "no score)") for r in runs]
    game = games.pop()
    return RunComparison(game, runs, curves, budget_table(curves), unified_diff(texts[0], texts[1], *names),
                         best_difference(game, scores, held_out), _cautions(configs))


NOT_TESTED = ("not tested: each best was picked on the episodes that scored it, which flatters it (the more so the "
              "more versions its run tried); `codearcade audit` of {which} scores {them} on sealed held-out games")
"""The verdict when a best has no held-out score: the tuning difference is shown, never called a finding."""
TUNING_NOTE = "not a test: each best was picked on these episodes"


def best_difference(game: str, tuning: Sequence[Score], held_out: Sequence[Score | None]) -> dict[str, Any]:
    """Whether two runs' bests differ beyond the noise, as plain data (``store.scores.Comparison.data``'s fields).
    ``tuning``: each best's episodes that scored it (and picked it); ``held_out``: each best's held-out audit games
    (None: it has none). With both held out, the verdict is theirs (``basis`` ``held_out``); else the figures are
    the tuning episodes' with ``significant`` None and a verdict that says it is not tested and which runs' audit
    would test it (``basis`` ``tuning``; a forfeit's refusal stays as it is).
    ``tuning`` holds the tuning figures either way, beside the verdict, and ``to_audit`` the labels of the runs
    whose best has no held-out score. A pure function of the numbers, so a simulation can weigh it."""
    found = difference_data(game, *tuning)
    figures = {key: found[key] for key in ("delta", "low", "high", "level", "method", "n", "reason", "forfeited")}
    figures["interval"] = None if found["delta"] is None else interval_text(
        found["delta"], found["low"], found["high"], tuple(found["n"]), found["method"], found["level"],
        found["reason"], signed=True)
    figures["note"] = TUNING_NOTE
    missing = [label for label, score in zip(LABELS, held_out) if score is None]
    if not missing:
        return {**difference_data(game, *held_out), "basis": "held_out", "tuning": figures,
                "to_audit": []}
    if found["delta"] is not None:  # a forfeit's refusal says more than "not tested" and stays
        which = " and ".join(f"run {label}" for label in missing)
        found["verdict"] = (f"{LABELS[0]} - {LABELS[1]} = {figures['interval']}: "
                            + NOT_TESTED.format(which=which, them="its best" if len(missing) == 1 else "their bests"))
    return {**found, "significant": None, "basis": "tuning", "tuning": figures,
            "to_audit": missing}


def _cumulative_calls(curve: list[dict[str, Any]]) -> list[dict[str, Any]]:
    total = 0
    for row in curve:
        total += row["llm_calls"] or 0
        row["cumulative_calls"] = total
    return curve


def _curve_point(row: dict[str, Any]) -> dict[str, Any]:
    return {"iteration": row["iteration"], "score": row["score"], "best_score": row["best_score"],
            "update_status": row["update_status"], "llm_calls": row["cumulative_calls"],
            "tokens": int(row["cumulative_tokens"] or 0), "elapsed_s": float(row["elapsed_s"] or 0.0)}


BUDGET_UNITS = (("LLM calls", "llm_calls", 1.0), ("1k tokens", "tokens", 1000.0), ("wall seconds", "elapsed_s", 1.0))
"""Budget axes of the matched table: label, cumulative column of a curve point, the unit it is counted in."""


def best_within(curve: list[dict[str, Any]], key: str, budget: float) -> float | None:
    """The best score a run had reached once it had spent at most ``budget`` (in ``key``'s raw unit)."""
    scores = [p["score"] for p in curve if p[key] <= budget + 1e-9 and p["score"] is not None]
    return max(scores) if scores else None


def budget_table(curves: dict[str, list[dict[str, Any]]], points: int = 4) -> list[dict[str, Any]]:
    """Rows ``{unit, budget, A, B}``: per budget axis, the best score of each run within the same spending, at
    ``points`` evenly spaced budgets from the first at which both runs have a score (their starting policies'
    evaluations) up to what both runs spent (every call count when there are few), then a row ``all`` with each
    run's own total and final best."""
    rows: list[dict[str, Any]] = []
    for unit, key, scale in BUDGET_UNITS:
        common = min(curve[-1][key] for curve in curves.values())
        first = min(max(curve[0][key] for curve in curves.values()), common)
        if common <= first:
            budgets = [common]
        elif key == "llm_calls" and common - first <= 12:
            budgets = [float(c) for c in range(int(first), int(common) + 1)]
        else:
            budgets = [first + (common - first) * i / (points - 1) for i in range(points)]
        for budget in budgets:
            rows.append({"unit": unit, "budget": round(budget / scale, 3),
                         **{label: best_within(curve, key, budget) for label, curve in curves.items()}})
        rows.append({"unit": unit, "budget": "all", "spent": {label: round(curve[-1][key] / scale, 3)
                                                            for label, curve in curves.items()},
                     **{label: best_within(curve, key, float("inf")) for label, curve in curves.items()}})
    return rows
