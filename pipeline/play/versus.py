"""``codearcade compare A B`` of two policy versions: both played on the same seeds, and where they part.

Two versions of one game, each a policy file or ``RUN:VERSION`` (a version stored in a run: an id, a unique
prefix of one, or ``best``): both are evaluated with node capture (``pipeline/play/evaluate.py``, the same path as
``codearcade eval --trace``, so each is an eval run in the store) on the same seeds, and for each seed the
report names the first step where their actions differ, with both sides' actions, observations and node
outputs on the steps around it. Episodes are deterministic under the default protocol (sticky 0, no no-op
starts), so that step is where their behaviour really parts, not noise.

Beside where the actions part, it says whether the scores differ beyond the noise: each side's score by the one
rule of ``store/scores.py`` (mean of the episodes played out with its 95% t interval, forfeits named) and the
interval of the difference of their returns (seed by seed, the paired t: ``store.statistics.paired_difference``;
with ``--audit``, Welch's t: ``store.statistics.difference``). Under the paper's protocol every seed is the same
game, so that says little; ``--audit`` (``CompareConfig.audit``) plays each side on its own
audit seeds under the standard protocol instead (sticky 0.25, up to 30 no-op starts), independent draws whose
difference is the one that means something (and then no divergent step is looked for: the sides play different
games).

Everything shown is read back from the store (``store/comparisons.py``); this module only decides what to
play and assembles the report as plain data (``viewers/compare_report.py`` renders it). Two optimization runs
are compared by ``pipeline/optimizer/runs.py``.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from games import get_game, list_widths
from games.base import STANDARD_NOOP_MAX, STANDARD_STICKY, Game, draw_audit_seeds
from pipeline.play.config import CompareConfig, EvalConfig
from pipeline.play.evaluate import evaluate
from pipeline.play.runinfo import new_run_id
from pipeline.play.validate import checked_inspect
from store import Store
from store.comparisons import episode_rows, first_divergent_step, resolve_version
from store.readers import episode_steps, get_run, policy_text, run_episodes, step_outputs
from store.scores import Score, compare_scores, score_data, score_episodes, worst_return
from store.views import resolve_run_id
from tracing.line_diff import unified_diff as bounded_unified_diff
from tracing.policy_file import PolicyLoadError, read_policy_file

LABELS = ("A", "B")


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
    protocol: str = "paper"
    """``paper`` (both sides on the same seeds, sticky 0, no no-op starts) or ``audit`` (each on its own audit
    seeds under the standard protocol)."""
    scores: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per side: its seeds and returns, and its score (``store.scores.Score``) as plain data."""
    difference: dict[str, Any] = field(default_factory=dict)
    """A's mean minus B's with its 95% interval, whether that leaves out 0, and the verdict in words."""

    def as_dict(self) -> dict[str, Any]:
        return {"mode": "versions", "game": self.game, "protocol": self.protocol, "diff": self.diff,
                "episodes": self.episodes, "scores": self.scores, "difference": self.difference,
                "versions": [{"label": v.label, "ref": v.ref, "policy_version_id": v.policy_version_id,
                              "source_run": v.source_run, "eval_run": v.eval_run} for v in self.versions]}


def unified_diff(text_a: str, text_b: str, name_a: str, name_b: str) -> str:
    """The unified diff of two policy texts (empty when they are the same), at a cost bounded by their length
    (``tracing/line_diff.py``: two hostile 100 KB files took 84 s in difflib's)."""
    return "".join(bounded_unified_diff(text_a.splitlines(keepends=True), text_b.splitlines(keepends=True),
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
        raise PolicyLoadError(f"{ref!r}: not a policy file; give a file or RUN:VERSION (e.g. last:best)")
    with store.read() as con:
        run_id = resolve_run_id(con, run_text, store)
        version = resolve_version(con, run_id, version_text)
        text = policy_text(con, run_id, version)
        game = get_run(con, run_id)["game"]
    return Version(label, ref, text, game, version, source_run=run_id)


def compare_versions(store: Store, a: str, b: str, config: CompareConfig,
                     progress: Callable[[str], None] | None = None,
                     episodes_progress: Callable[[int, str], Any] | None = None) -> VersionComparison:
    """Play both versions on the same seeds (traced, into the store) and report where their actions part.
    ``progress`` gets a line as each side starts; ``episodes_progress(episodes, description)`` makes the watcher of
    one side's episodes (``update(index, steps)``, ``finished(index, length)``, ``close()``: the command line's
    ``EpisodeProgress``)."""
    versions = [load_version(store, label, ref, config.workers) for label, ref in zip(LABELS, (a, b))]
    games = [config.game or v.game for v in versions]
    if any(g is None for g in games):
        missing = versions[games.index(None)].ref
        raise PolicyLoadError(f"{missing} does not declare GAME = '...'; pass --game (`codearcade games` lists them)")
    if get_game(games[0]) != get_game(games[1]):
        raise PolicyLoadError(f"{a} plays {games[0]} but {b} plays {games[1]}: compare two versions of one game")
    game = get_game(games[0]).name
    # one random stream for both sides: on a seed, their policies draw the same numbers
    rng_key = config.rng_key or new_run_id()
    # --audit: each side's games drawn now, sealed (none of them knowable to either policy in advance), disjoint
    audit_seeds = draw_audit_seeds(2 * config.episodes) if config.audit else []
    with tempfile.TemporaryDirectory(prefix="codearcade-compare-") as scratch:
        for k, v in enumerate(versions):
            eval_config = _eval_config(game, config, audit_seeds[k * config.episodes:(k + 1) * config.episodes])
            eval_config.rng_key = rng_key
            path = v.path
            if path is None:  # a stored version is played from a file named after where it came from
                path = os.path.join(scratch, f"{v.source_run}.{v.policy_version_id}.py")
                Path(path).write_text(v.text)
            if progress is not None:
                progress(f"playing {v.label} = {v.ref} ({v.policy_version_id}) on "
                         + (f"{config.episodes} sealed audit seed(s), standard protocol" if config.audit else
                            f"{config.episodes} seed(s) from {eval_config.seed}, traced"))
            # marked as compare's own: `runs` and `last` count the runs a person started, not these
            watch = episodes_progress(eval_config.episodes, f"compare {v.label}") if episodes_progress else None
            try:
                v.eval_run = evaluate(path, eval_config, store, made_by="compare",
                                      progress=watch.update if watch else None,
                                      on_episode=watch.finished if watch else None).run_id
            finally:
                if watch is not None:
                    watch.close()
    diff = unified_diff(versions[0].text, versions[1].text, f"A {a} ({versions[0].policy_version_id})",
                        f"B {b} ({versions[1].policy_version_id})")
    result = VersionComparison(game, versions, diff, protocol="audit" if config.audit else "paper")
    with store.read() as con:
        played = [[e for e in run_episodes(con, v.eval_run) if e["kind"] == "eval"] for v in versions]
        if not config.audit:  # the same seed is the same game on both sides only under the paper's protocol
            for ep_a, ep_b in zip(*played):
                result.episodes.append(_divergence(con, game, ep_a, ep_b, config.context))
    scores = [score_episodes(episodes) for episodes in played]
    result.scores = {label: _score_data(score, episodes) for label, score, episodes in zip(LABELS, scores, played)}
    # the paper's protocol plays both sides on the same seeds with one random stream: seed by seed, a pair
    paired = not config.audit and [e["seed"] for e in played[0]] == [e["seed"] for e in played[1]]
    result.difference = difference_data(game, *scores, paired=paired)
    return result


def difference_data(game: str, a: Score, b: Score, paired: bool = False) -> dict[str, Any]:
    """Two sides' scores compared by the one rule (``store.scores.compare_scores``) as plain data: A's mean minus
    B's, its 95% interval (level, method and counts beside it; ``reason`` why there is none), whether that leaves
    out 0 (None: no interval to tell by, or a side forfeited) and the verdict in words; when a side forfeited, no
    verdict but why (``forfeited``), and ``sensitivity``: the difference with each forfeit counted at the game's
    worst return (``Game.worst_return``; else the lowest return played out here, and it says so). ``paired``: the
    sides played the same seeds in the same order with the same random draws (their difference is then the
    paired one, ``store.statistics.paired_difference``)."""
    worst, source = worst_return(get_game(game).worst_return, game, (a, b))
    return compare_scores(a, b, worst, source, LABELS, paired).data()


def _eval_config(game: str, config: CompareConfig, audit_seeds: list[int]) -> EvalConfig:
    """How one side plays: on ``seed`` on under the paper's protocol, traced; with ``audit``, on its own sealed
    ``audit_seeds`` under the standard protocol."""
    if not config.audit:
        return EvalConfig(game=game, episodes=config.episodes, max_steps=config.max_steps, seed=config.seed,
                          trace=True, workers=config.workers)
    return EvalConfig(game=game, episodes=len(audit_seeds), max_steps=config.max_steps, seed=audit_seeds[0],
                      seeds=tuple(audit_seeds), sticky=STANDARD_STICKY, noop_max=STANDARD_NOOP_MAX,
                      workers=config.workers)


def _score_data(score, episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """A side's :class:`store.scores.Score` as plain data, with the seeds, returns and end reasons of its episodes:
    ``score`` (None with any forfeit: ``no_score`` says why, and ``mean`` and its interval are None too)."""
    return {"seeds": [e["seed"] for e in episodes], "returns": [e["return"] for e in episodes],
            "end_reasons": [e["end_reason"] for e in episodes],
            **score_data(score), "score": score.ranked, "no_score": score.no_score,
            "forfeits": [f.describe() for f in score.forfeits],
            **({"played_out": {"mean": score.mean, "episodes": score.played, "note": "not a score"}}
               if score.forfeits else {}),
            "summary": score.summary()}


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
    played = get_game(game)
    # the steps the episodes have, whatever the context: `--context 4611686018427387904` was taken, and the list of
    # steps around the divergence grew without end (8.3 GB at 60 s, killed)
    start, stop = max(0, step - context), min(step + context, max(step, *(rows[i]["length"] or 0 for i in ids))) + 1
    sides = {}
    for label, episode_id in zip(LABELS, ids):
        steps = {r["step"]: r for r in episode_steps(con, episode_id, start, stop, list_widths(game),
                                                     get_game(game).derive)}
        outputs: dict[int, dict[str, Any]] = {}
        for node in step_outputs(con, episode_id, start, stop):  # each method's last call in a step, cut
            outputs.setdefault(node["step"], {})[node["function"]] = (
                node["output"] if node["exc_type"] is None else f"{node['exc_type']}: {node['exc_message']}")
        sides[label] = (steps, outputs)
    for s in range(start, stop):
        entry: dict[str, Any] = {"step": s}
        for label, (steps, outputs) in sides.items():
            row = steps.get(s)
            entry[label] = None if row is None else {
                "action": row["action"], "action_name": _meaning(played, row["action"]), "reward": row["reward"],
                "score": row["score"], "obs": row["obs"], "nodes": outputs.get(s, {})}
        out["around"].append(entry)
    at = next(e for e in out["around"] if e["step"] == step)
    out["actions"] = {label: None if at[label] is None else at[label]["action"] for label in LABELS}
    return out


def _meaning(game: Game, action: int | None) -> str | None:
    """An action's name as people read it: ALE's, with what it does on screen where that differs (``RIGHT (up)``)."""
    if action is None:
        return None
    if not 0 <= action < len(game.actions):
        return f"illegal {action}"
    move = game.action_moves.get(action)
    return f"{game.actions[action]} ({move})" if move else game.actions[action]
