"""``codearcade compare A B``: two optimization runs side by side, or two policy versions played on the same seeds.

Two runs (ids or unique prefixes): their learning curves, a budget-matched table (the best score each run had
reached within the same number of LLM calls, thousand tokens and wall seconds; only budgets both runs spent
are matched, so neither is credited with spending it never made) and the unified diff of their best versions.

Two versions of one game, each a policy file or ``RUN:VERSION`` (a version stored in a run: an id, a unique
prefix of one, or ``best``): both are evaluated with node capture (``pipeline/play/evaluate.py``, the same path as
``codearcade eval --trace``, so each is an eval run in the store) on the same seeds, and for each seed the
report names the first step where their actions differ, with both sides' actions, observations and node
outputs on the steps around it. Episodes are deterministic under the default protocol (sticky 0, no no-op
starts), so that step is where their behaviour really parts, not noise.

Everything shown is read back from the store (``store/comparisons.py``); this module only decides what to
compare and assembles the report as plain data (``viewers/compare_report.py`` renders it).
"""

from __future__ import annotations

import difflib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from games import get_game, list_widths
from pipeline.play.evaluate import EvalConfig, evaluate
from pipeline.play.validate import checked_inspect
from store import Store
from store.comparisons import best_version, episode_rows, first_divergent_step, learning_curve, resolve_version
from store.readers import episode_steps, get_run, policy_text, run_episodes, step_nodes
from store.views import resolve_run_id
from tracing.policy_file import PolicyLoadError, read_policy_file

LABELS = ("A", "B")


@dataclass
class CompareConfig:
    """Options of ``codearcade compare`` for two versions (two runs are only read)."""

    game: str | None = None
    """Game both versions play; None takes it from the stored runs or the files' ``GAME``."""
    episodes: int = 1
    """Seeds to play: ``seed``, ``seed + 1``, ...; each version plays each of them once."""
    seed: int = 0
    """The first seed."""
    max_steps: int = 4000
    """Step cap of each episode (the paper's 4000)."""
    context: int = 3
    """Steps shown before and after the first divergent step."""
    workers: int = 1
    """Episode worker processes (``codearcade eval --workers``)."""


@dataclass
class Version:
    """One side of a version comparison: where its code came from, and the code."""

    label: str
    ref: str
    text: str
    game: str
    policy_version_id: str
    source_run: str | None = None
    eval_run: str | None = None
    path: str | None = None


@dataclass
class VersionComparison:
    game: str
    versions: list[Version]
    diff: str
    episodes: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"mode": "versions", "game": self.game, "diff": self.diff, "episodes": self.episodes,
                "versions": [{"label": v.label, "ref": v.ref, "policy_version_id": v.policy_version_id,
                              "source_run": v.source_run, "eval_run": v.eval_run} for v in self.versions]}


@dataclass
class RunComparison:
    game: str
    runs: list[dict[str, Any]]
    curves: dict[str, list[dict[str, Any]]]
    budgets: list[dict[str, Any]]
    diff: str

    def as_dict(self) -> dict[str, Any]:
        return {"mode": "runs", "game": self.game, "runs": self.runs, "curves": self.curves,
                "budgets": self.budgets, "diff": self.diff}


def is_version_ref(text: str) -> bool:
    """A policy file that exists, or ``RUN:VERSION``; anything else is taken for a run id."""
    return Path(text).is_file() or ":" in text


def compare(store: Store, a: str, b: str, config: CompareConfig | None = None,
            progress: Callable[[str], None] | None = None) -> RunComparison | VersionComparison:
    """Compare ``a`` and ``b``: two runs, or two versions (see the module docstring)."""
    config = config or CompareConfig()
    for ref in (a, b):
        if ref.endswith(".py") and not Path(ref).is_file():
            raise PolicyLoadError(f"policy file '{ref}' does not exist")
    kinds = [is_version_ref(x) for x in (a, b)]
    if all(kinds):
        return compare_versions(store, a, b, config, progress)
    if not any(kinds):
        return compare_runs(store, a, b)
    run, other = (a, b) if not kinds[0] else (b, a)
    raise ValueError(f"{other!r} is a policy version but {run!r} is not (no such file): compare two runs "
                     f"(two run ids) or two versions (policy files or RUN:VERSION, e.g. {run}:best)")


# ------------------------------------------------------------------------------------------------- two runs

def compare_runs(store: Store, a: str, b: str) -> RunComparison:
    """Learning curves, budget-matched table and best-version diff of two optimization runs."""
    with store.read() as con:
        ids = [resolve_run_id(con, x, store) for x in (a, b)]
        runs, curves, texts = [], {}, []
        for label, run_id in zip(LABELS, ids):
            run = get_run(con, run_id)
            curve = learning_curve(con, run_id)
            best = best_version(con, run_id)
            if not curve or best is None:
                raise ValueError(f"run {run_id} is an {run['kind']} run without iterations: compare optimization "
                                 f"runs, or play its policy against another version with {run_id}:best")
            texts.append(policy_text(con, run_id, best["policy_version_id"]))
            curves[label] = [_curve_point(row) for row in _cumulative_calls(curve)]
            last = curves[label][-1]
            runs.append({"label": label, "run_id": run_id, "kind": run["kind"], "game": run["game"],
                         "model": run["model"], "status": run["status"], "iterations": len(curve) - 1,
                         "llm_calls": last["llm_calls"], "total_tokens": last["tokens"], "elapsed_s": last["elapsed_s"],
                         "best_score": best["score"], "best_iteration": best["iteration"],
                         "best_version_id": best["policy_version_id"]})
    games = {r["game"] for r in runs}
    if len(games) > 1:
        raise ValueError(f"runs {ids[0]} ({runs[0]['game']}) and {ids[1]} ({runs[1]['game']}) play different games; "
                         "scores of different games do not compare")
    names = [f"{r['run_id']}:{r['best_version_id']} (best, iteration {r['best_iteration']}, score {r['best_score']:g})"
             for r in runs]
    return RunComparison(games.pop(), runs, curves, budget_table(curves), unified_diff(texts[0], texts[1], *names))


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


def unified_diff(text_a: str, text_b: str, name_a: str, name_b: str) -> str:
    """The unified diff of two policy texts (empty when they are the same)."""
    return "".join(difflib.unified_diff(text_a.splitlines(keepends=True), text_b.splitlines(keepends=True),
                                        fromfile=name_a, tofile=name_b))


# --------------------------------------------------------------------------------------------- two versions

def load_version(store: Store, label: str, ref: str, workers: int) -> Version:
    """A policy file, or ``RUN:VERSION`` read from the store; its game from the run or the file's ``GAME``."""
    if Path(ref).is_file():
        text = read_policy_file(ref)
        info = checked_inspect(text, Path(ref).name, workers=1 if workers else 0)
        return Version(label, ref, text, info.game, info.version_id, path=ref)
    run_text, _, version_text = ref.rpartition(":")
    if not run_text:
        raise PolicyLoadError(f"{ref!r}: not a policy file; give a file or RUN:VERSION (e.g. 01JD:best)")
    with store.read() as con:
        run_id = resolve_run_id(con, run_text, store)
        version = resolve_version(con, run_id, version_text)
        text = policy_text(con, run_id, version)
        game = get_run(con, run_id)["game"]
    return Version(label, ref, text, game, version, source_run=run_id)


def compare_versions(store: Store, a: str, b: str, config: CompareConfig,
                     progress: Callable[[str], None] | None = None) -> VersionComparison:
    """Play both versions on the same seeds (traced, into the store) and report where their actions part."""
    versions = [load_version(store, label, ref, config.workers) for label, ref in zip(LABELS, (a, b))]
    games = [config.game or v.game for v in versions]
    if any(g is None for g in games):
        missing = versions[games.index(None)].ref
        raise PolicyLoadError(f"{missing} does not declare GAME = '...'; pass --game (`codearcade games` lists them)")
    if get_game(games[0]) != get_game(games[1]):
        raise PolicyLoadError(f"{a} plays {games[0]} but {b} plays {games[1]}: compare two versions of one game")
    game = get_game(games[0]).name
    eval_config = EvalConfig(game=game, episodes=config.episodes, max_steps=config.max_steps, seed=config.seed,
                             trace=True, workers=config.workers)
    with tempfile.TemporaryDirectory(prefix="codearcade-compare-") as scratch:
        for v in versions:
            path = v.path
            if path is None:  # a stored version is played from a file named after where it came from
                path = os.path.join(scratch, f"{v.source_run}.{v.policy_version_id}.py")
                Path(path).write_text(v.text)
            if progress is not None:
                progress(f"playing {v.label} = {v.ref} ({v.policy_version_id}) on {config.episodes} seed(s) from "
                         f"{config.seed}, traced")
            v.eval_run = evaluate(path, eval_config, store).run_id
    diff = unified_diff(versions[0].text, versions[1].text, f"A {a} ({versions[0].policy_version_id})",
                        f"B {b} ({versions[1].policy_version_id})")
    result = VersionComparison(game, versions, diff)
    with store.read() as con:
        played = [[e for e in run_episodes(con, v.eval_run) if e["kind"] == "eval"] for v in versions]
        for ep_a, ep_b in zip(*played):
            result.episodes.append(_divergence(con, game, ep_a, ep_b, config.context))
    return result


def _divergence(con, game: str, ep_a: dict[str, Any], ep_b: dict[str, Any], context: int) -> dict[str, Any]:
    """Where two episodes of the same seed part: the first step whose actions differ, and the steps around it."""
    ids = (ep_a["episode_id"], ep_b["episode_id"])
    rows = episode_rows(con, list(ids))
    step = first_divergent_step(con, *ids)
    out: dict[str, Any] = {
        "seed": ep_a["seed"], "first_divergent_step": step,
        **{label: {k: rows[i][k] for k in ("episode_id", "return", "length", "end_reason")}
           for label, i in zip(LABELS, ids)},
        "actions": None, "around": [],
    }
    if step is None:
        return out
    meanings = get_game(game).actions
    start, stop = max(0, step - context), step + context + 1
    sides = {}
    for label, episode_id in zip(LABELS, ids):
        steps = {r["step"]: r for r in episode_steps(con, episode_id, start, stop, list_widths(game),
                                                     get_game(game).derive)}
        outputs: dict[int, dict[str, Any]] = {}
        for node in step_nodes(con, episode_id, start, stop):  # a method called twice in a step: the last call
            outputs.setdefault(node["step"], {})[node["function"]] = (
                node["output"] if node["exc_type"] is None else f"{node['exc_type']}: {node['exc_message']}")
        sides[label] = (steps, outputs)
    for s in range(start, stop):
        entry: dict[str, Any] = {"step": s}
        for label, (steps, outputs) in sides.items():
            row = steps.get(s)
            entry[label] = None if row is None else {
                "action": row["action"], "action_name": _meaning(meanings, row["action"]), "reward": row["reward"],
                "score": row["score"], "obs": row["obs"], "nodes": outputs.get(s, {})}
        out["around"].append(entry)
    at = next(e for e in out["around"] if e["step"] == step)
    out["actions"] = {label: None if at[label] is None else at[label]["action"] for label in LABELS}
    return out


def _meaning(meanings: tuple[str, ...], action: int | None) -> str | None:
    if action is None:
        return None
    return meanings[action] if 0 <= action < len(meanings) else f"illegal {action}"
