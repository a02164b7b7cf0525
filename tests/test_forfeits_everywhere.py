"""One rule, every reader (issue 37, item 1): a set of episodes with a forfeit has no ranked score, in ``eval``,
``runs``, ``compare`` (of versions, ``--audit`` too, and of runs), ``report``, the SQL views, the OTLP export and
every ``--json`` (``store/scores.py``).

The end-to-end tests play tests/policies/pong_quitter.py: the competent Pong policy, which raises at step 300
whenever its own count of the points says it is not ahead, against its honest twin (tests/policies/pong_competent.py,
the same play without the raise), 600 steps a game, under the standard protocol (sticky actions 0.25, up to 30
no-op starts; the games are fixed by their seeds). On seeds 16-23 the quitter forfeits 5 games; the 3 it plays out
average 1, above its twin's 0.5 over all 8: averaging only the survivors is what ranked it above its twin. In
``compare --audit --seed 8`` it forfeits 2 of 4; its 2 survivors (2, 1) against the twin's 4 games (0, -2, -2, 0)
make Welch's t say "+2.5 [+0.2, +4.8]: a difference beyond the noise" if the forfeits are dropped.
"""

from __future__ import annotations

import json
import math

import pytest

from store import Store
from store.scores import compare_scores, score_data, score_episodes, score_json, worst_return
from store.statistics import difference
from tests.conftest import POLICIES, old_store, run_main

QUITTER = POLICIES / "pong_quitter.py"
TWIN = POLICIES / "pong_competent.py"
STANDARD = ("--sticky", "0.25", "--noop-max", "30", "--max-steps", "600", "--rng-key", "forfeits")


def _episodes(returns: list[float], forfeits: int, step: int = 300) -> list[dict]:
    played = [{"return": r, "end_reason": "truncated", "length": 600} for r in returns]
    return played + [{"return": 0.0, "end_reason": "policy_error", "length": step,
                      "error": "RuntimeError: not ahead at step 300: quitting"}] * forfeits


# --------------------------------------------------------------------------------------------- the rule itself

def test_a_set_with_a_forfeit_has_no_score_and_says_why():
    quitter = score_episodes(_episodes([0, 2, 1], forfeits=5))
    assert quitter.ranked is None and quitter.no_score == (
        "no score: 5 of 8 episodes forfeited (RuntimeError at step 300 in all 5)")
    assert quitter.summary() == ("no score: 5 of 8 episodes forfeited (RuntimeError at step 300 in all 5); "
                                 "the 3 played out averaged 1, not a score")
    assert "mean return" not in quitter.summary(), "nothing a reader could take for its score"
    data = score_json(quitter)
    assert data["score"] is None and data["no_score"] == quitter.no_score
    assert [f["describe"] for f in data["forfeits"]] == ["RuntimeError at step 300"] * 5
    assert data["played_out"] == {"mean": 1.0, "episodes": 3, "note": "not a score"}
    plain = score_data(quitter)
    assert plain["mean"] is None and plain["interval"] is None and plain["reason"] == "forfeited"
    twin = score_episodes(_episodes([2, -1, 0, 2, 2, -1, 1, -1], forfeits=0))
    assert twin.ranked == 0.5 and twin.no_score is None and twin.summary().startswith("mean return 0.5 [")
    assert score_json(twin)["score"]["mean"] == 0.5 and "played_out" not in score_json(twin)
    mixed = score_episodes([*_episodes([3], 0), {"return": 1.0, "end_reason": "timeout", "length": 40},
                            *_episodes([], 1)])
    assert mixed.no_score == "no score: 2 of 3 episodes forfeited (timeout at step 40, RuntimeError at step 300)"


NAMED = [
    ("Boom: kaboom at line 18: `raise Boom('kaboom')`", "Boom"),
    ("Quit at line 3: `raise Quit`", "Quit"),
    ("Halt", "Halt"),
    ("Ошибка: нет", "Ошибка"),
    ("RuntimeError: not ahead at step 300: quitting", "RuntimeError"),
    ("ValueError: illegal action 7: legal actions are 0..5", "ValueError"),
    ("malformed trace at step 3: a node's output is not JSON", None),
    ("trace missing: the policy process sent no node rows", None),
    ("policy.py:12: NameError: name 'x' is not defined", None),
    ("the policy process ended at this step (killed by signal 9)", None),
]


@pytest.mark.parametrize("error, name", NAMED, ids=[e[:24] for e, _ in NAMED])
def test_a_forfeit_is_named_by_the_policys_exception_whatever_its_name_ends_with(error, name):
    """The name is read by the structure the policy's errors are written in (``Name: message at line N``, ``Name at
    line N``, ``Name``: ``describe_exception``), not by a suffix: ``class Boom(Exception)`` was ``policy_error``.
    The host's own errors name no exception: the end reason stands for them."""
    score = score_episodes([{"return": 0.0, "end_reason": "policy_error", "length": 2, "error": error}])
    assert score.forfeits[0].describe() == f"{name or 'policy_error'} at step 2"


def test_compare_never_calls_a_side_that_forfeited_better():
    quitter = score_episodes(_episodes([2, 1], forfeits=2))
    twin = score_episodes(_episodes([0, -2, -2, 0], forfeits=0))
    assert difference(quitter.returns, twin.returns).significant is True, \
        "dropping the forfeits would call the quitter better beyond the noise"
    worst, source = worst_return(-21, "pong", (quitter, twin))
    found = compare_scores(quitter, twin, worst, source)
    assert found.difference is None and found.significant is None
    assert found.verdict() == ("cannot compare: A forfeited 2 of 4 games: no score to compare (a forfeit is never "
                               "scored, so neither side is called better)")
    assert found.sensitivity_text() == (
        "sensitivity, not a score: with each forfeit counted at -21 (the game's worst return, games/pong.py), "
        f"A - B = {found.sensitivity.interval.text(signed=True)}")
    assert found.sensitivity.delta == pytest.approx((2 + 1 - 42) / 4 - (-1.0))
    data = found.data()
    assert (data["delta"], data["significant"], data["reason"]) == (None, None, "forfeited")
    assert data["forfeited"] == {"A": "2 of 4 games forfeited (RuntimeError at step 300 in both)"}
    assert data["sensitivity"]["worst"] == -21 and "beyond the noise" not in json.dumps(data)
    # both sides: both named; no worst return in the game module: the lowest one played out here, said so
    both = compare_scores(twin, quitter, *worst_return(None, "tennis", (twin, quitter)), labels=("A", "B"))
    assert both.refusal() == "B forfeited 2 of 4 games: no score to compare"
    assert both.worst == -2 and both.worst_source == ("the lowest return played out here: games/tennis.py gives no "
                                                      "worst return")
    assert compare_scores(score_episodes(_episodes([1], 1)), score_episodes(_episodes([], 2))).refusal() == (
        "A forfeited 1 of 2 games and B forfeited 2 of 2 games: no score to compare")
    clean = compare_scores(twin, score_episodes(_episodes([14, 11, 17, 12], 0)))
    assert clean.significant is True and clean.verdict() == clean.difference.verdict()


def test_an_eval_run_that_forfeited_has_no_score_in_sql_after_the_migration(tmp_path):
    """Migration 17 on a store written before it: the eval run with a forfeit loses its score, the other keeps it."""
    path = tmp_path / "old.duckdb"
    con = old_store(path, 16)
    for run_id, episodes in (("quitter", _episodes([0, 2, 1], 5)), ("twin", _episodes([2, -1, 0, 2, 2, -1, 1, -1], 0))):
        con.execute("INSERT INTO runs (run_id, created_at, kind, game, config, status) VALUES (?, now(), 'eval', "
                    "'pong', '{}', 'finished')", [run_id])
        for i, e in enumerate(episodes):
            con.execute("INSERT INTO episodes (episode_id, run_id, iteration, kind, episode_index, game, seed, "
                        "policy_version_id, return, length, lives_lost, end_reason, traced, duration_s) VALUES "
                        "(?, ?, 0, 'eval', ?, 'pong', ?, 'v', ?, ?, 0, ?, false, 1.0)",
                        [f"{run_id}.{i}", run_id, i, 16 + i, e["return"], e["length"], e["end_reason"]])
    before = dict(con.execute("SELECT run_id, best_score FROM run_summary").fetchall())
    con.close()
    assert before["quitter"] == 1.0, "before: the mean of the three it played out"
    store = Store(path)
    rows = store.query("SELECT run_id, best_score, forfeits FROM run_summary ORDER BY best_score DESC NULLS LAST")
    assert rows == [("twin", 0.5, 0), ("quitter", None, 5)]
    assert store.query("SELECT max(best_score) FROM run_summary") == [(0.5,)]


def test_the_report_draws_forfeits_as_marks_never_at_their_partial_return():
    from viewers.report_figures import episode_returns_figure, lineage_figure, scores_figure

    run = {"run_id": "R", "game": "pong", "kind": "optimize", "model": "m", "name": None}
    curve = [{"iteration": i, "score": score, "score_low": None, "score_n": 1, "best_score": -20.0,
              "best_iteration": 0, "update_status": status, "rolled_back": i == 1, "repairs": 0,
              "forfeit": forfeit, "forfeit_score": partial}
             for i, score, status, forfeit, partial in (
                 (0, -20.0, "initial", None, None),
                 (1, None, "accepted", "1 of 2 episodes forfeited: RuntimeError at step 300 (policy_error)", -7.0))]
    episodes = [{"iteration": 1, "kind": "eval", "return": r, "end_reason": end, "length": 300}
                for r, end in ((-19.0, "truncated"), (-2.0, "policy_error"))]
    fig = scores_figure({"run": run, "curve": curve, "episodes": episodes})
    (ax,) = fig.axes
    drawn = [(float(x), float(y)) for line in ax.get_lines() for x, y in zip(line.get_xdata(), line.get_ydata())
             if not (isinstance(y, float) and math.isnan(y))]
    drawn += [(float(x), float(y)) for c in ax.collections for x, y in c.get_offsets()]
    assert (1.0, -7.0) not in drawn and (1.0, -2.0) not in drawn, "a forfeit is no return: not at its partial one"
    marks = [line for line in ax.get_lines() if line.get_label() == "forfeited a game: no score"]
    assert len(marks) == 1 and list(marks[0].get_xdata()) == [1] and marks[0].get_transform() != ax.transData

    run = {**run, "kind": "eval"}
    eval_episodes = [{"kind": "eval", "episode_index": i, "seed": 16 + i, "return": e["return"], "length": e["length"],
                      "end_reason": e["end_reason"], "max_steps": 600}
                     for i, e in enumerate(_episodes([0, 2, 1], 5))]
    fig = episode_returns_figure({"run": run, "episodes": eval_episodes})
    (ax,) = fig.axes
    assert sorted(p.get_x() + p.get_width() / 2 for p in ax.patches) == [0, 1, 2], "a bar only where it played out"
    levels = [set(line.get_ydata()) for line in ax.get_lines()]
    means = [line for line in ax.get_lines() if "mean" in line.get_label()]
    assert not means and {1.0} not in levels and {0.375} not in levels, "no mean through a set with a forfeit"
    assert "no score: 5 of 8 forfeited" in ax.get_title()
    assert [list(line.get_xdata()) for line in ax.get_lines() if line.get_marker() == "X"] == [[3, 4, 5, 6, 7]]
    clean = episode_returns_figure({"run": run, "episodes": eval_episodes[:3]})
    assert [line.get_label() for line in clean.axes[0].get_lines() if "mean" in line.get_label()] == [
        "score: mean 1.0 [-1.5, 3.5] 95% t, n=3"]

    # the lineage: a candidate that forfeited is on the lane below every score, as a forfeit
    def node(i: int, score: float | None, decision: str, forfeit: str | None = None) -> dict:
        return {"iteration": i, "candidate": 0, "parent_iteration": i - 1 if i else None,
                "parent_candidate": 0 if i else None, "score": score, "decision": decision,
                "update_status": "initial" if i == 0 else "accepted", "proposed_version_id": f"v{i}",
                "policy_version_id": f"v{i}", "evaluation": "played", "standard_score": None, "strategy": "greedy",
                "forfeit": forfeit}

    lineage = [node(0, -20.0, "best"), node(1, None, "rolled_back", "1 of 1 episode forfeited: RuntimeError at step "
                                                                     "300 (policy_error)"), node(2, -18.0, "best")]
    (ax,) = lineage_figure({"run": {**run, "kind": "optimize"}, "lineage": lineage}).axes
    at = {c.get_label(): c.get_offsets().tolist() for c in ax.collections}
    assert at["new best"] == [[0.0, -20.0], [2.0, -18.0]]
    assert len(at["forfeited a game: no score"]) == 1 and at["forfeited a game: no score"][0][1] < -20


def test_runs_prints_no_score_where_a_forfeit_leaves_none():
    from pipeline.cli.runs import _best

    assert _best({"best_score": None, "forfeits": 5}) == "no score"
    assert _best({"best_score": 0.5, "forfeits": 0}) == 0.5 and _best({"best_score": None, "forfeits": 0}) is None


# ------------------------------------------------------------------------------------------------ end to end

@pytest.mark.slow
def test_eval_runs_report_and_export_give_the_quitter_no_score(tmp_path):
    store = Store(tmp_path / "s.duckdb", lock_timeout_s=20)
    code, out, _ = run_main("eval", QUITTER, "--episodes", 8, "--seed", 16, *STANDARD, "--store", store.path)
    assert code == 1, "forfeited episodes fail the command"
    assert ("no score: 5 of 8 episodes forfeited (RuntimeError at step 300 in all 5); the 3 played out averaged 1, "
            "not a score; ") in out, out
    assert "mean return" not in out
    code, out, _ = run_main("eval", TWIN, "--episodes", 8, "--seed", 16, *STANDARD, "--store", store.path,
                            "--json")
    twin = json.loads(out)
    assert code == 0 and twin["score"]["mean"] == 0.5 and twin["forfeits"] == [], twin["score"]
    code, out, _ = run_main("eval", QUITTER, "--episodes", 4, "--seed", 16, *STANDARD, "--store", store.path,
                            "--json")
    quitter = json.loads(out)
    assert quitter["score"] is None and quitter["no_score"] == (
        "no score: 2 of 4 episodes forfeited (RuntimeError at step 300 in both)")
    assert [f["step"] for f in quitter["forfeits"]] == [300, 300]
    assert quitter["played_out"]["note"] == "not a score" and quitter["played_out"]["mean"] > twin["score"]["mean"], \
        "its survivors average more than its twin: a reader that averaged them would rank it first"

    # runs: no score where the quitter's best would be, and nothing ranks it above its twin
    code, out, _ = run_main("runs", "--json", "--store", store.path)
    rows = {r["policy"].rsplit("/", 1)[-1] + str(r["episodes"]): r for r in json.loads(out)}
    assert rows["pong_quitter.py8"]["best_score"] is None and rows["pong_quitter.py8"]["forfeits"] == 5
    assert rows["pong_quitter.py4"]["best_score"] is None and rows["pong_competent.py8"]["best_score"] == 0.5
    code, out, _ = run_main("runs", "--store", store.path)
    lines = [line.split() for line in out.splitlines()[2:]]
    best = {(cells[5], cells[-1]): " ".join(cells[8:-2]) for cells in lines}
    assert best == {("pong_quitter.py", "4"): "no score", ("pong_competent.py", "8"): "0.5",
                    ("pong_quitter.py", "8"): "no score"}, out
    ranked = store.query("SELECT json_extract_string(config, '$.policy') FROM run_summary JOIN runs USING (run_id) "
                         "ORDER BY best_score DESC NULLS LAST LIMIT 1")
    assert ranked[0][0].endswith("pong_competent.py")

    # the report: no score in words, no mean in the figure, the forfeits as marks
    quitter_run = store.query("SELECT run_id FROM run_summary WHERE forfeits = 5")[0][0]
    code, _, _ = run_main("report", quitter_run, "--out", tmp_path / "report", "--store", store.path)
    readme = (tmp_path / "report" / "README.md").read_text()
    assert code == 0 and "no score: 5 of 8 episodes forfeited" in readme and "not a score" in readme
    assert "mean return" not in readme.split("## Episodes")[0]
    from viewers.report import collect
    from viewers.report_figures import episode_returns_figure

    (ax,) = episode_returns_figure(collect(store, quitter_run)).axes
    assert not [line for line in ax.get_lines() if "mean" in line.get_label()]
    marks = [len(line.get_xdata()) for line in ax.get_lines() if line.get_marker() == "X"]
    assert len(ax.patches) == 3 and marks == [5], "three bars played out, five forfeits marked"

    # the OTLP export's run span: no score, the forfeits counted
    from store.run_trace import run_trace_rows
    from viewers.otlp_export import build_spans

    with store.read() as con:
        rows = run_trace_rows(con, quitter_run)
    root = next(s for s in build_spans(rows) if s.parent is None)
    assert "codearcade.run.score" not in root.attributes and "codearcade.run.mean_return" not in root.attributes
    assert root.attributes["codearcade.run.forfeits"] == 5
    assert root.attributes["codearcade.run.no_score"].startswith("no score: 5 of 8 episodes forfeited")


@pytest.mark.slow
def test_eval_names_a_forfeit_by_the_policys_own_exception_class(tmp_path):
    path = tmp_path / "boom.py"
    path.write_text((POLICIES / "pong_competent.py").read_text().replace(
        "        predicted_ball_y = self.predict_ball_trajectory(obs)\n",
        "        class Boom(Exception):\n            pass\n        raise Boom('kaboom')\n", 1))
    code, out, err = run_main("eval", path, "--max-steps", "5", "--store", tmp_path / "s.duckdb")
    assert "no score: 1 of 1 episode forfeited (Boom at step 0)" in out + err


@pytest.mark.slow
def test_compare_does_not_call_the_quitter_better_and_says_why(tmp_path, pinned_audit_seeds):
    from games.base import AUDIT_SEED_BASE

    pinned_audit_seeds(AUDIT_SEED_BASE + 8)  # games where the quitter forfeits 2 of 4 (docs/compare.md's figures)
    store = Store(tmp_path / "s.duckdb", lock_timeout_s=20)
    code, out, _ = run_main("compare", QUITTER, TWIN, "--audit", "--episodes", 4, "--max-steps", 600,
                            "--rng-key", "forfeits", "--out", tmp_path / "cmp", "--json", "--store", store.path)
    data = json.loads(out)
    sides, found = data["scores"], data["difference"]
    assert code == 0 and sides["A"]["score"] is None and sides["B"]["score"] == -1.0, sides
    survivors = [r for r, end in zip(sides["A"]["returns"], sides["A"]["end_reasons"]) if end == "truncated"]
    assert difference(survivors, sides["B"]["returns"]).significant is True, \
        "without the rule this is 'a difference beyond the noise' in the quitter's favour"
    assert found["significant"] is None and found["delta"] is None
    assert found["verdict"].startswith("cannot compare: A forfeited 2 of 4 games: no score to compare")
    assert found["sensitivity"]["worst"] == -21 and found["sensitivity"]["delta"] < 0
    from viewers.compare_report import text_lines

    text = "\n".join(text_lines(data))
    assert "beyond the noise" not in text and "  A: no score: 2 of 4 episodes forfeited" in text, text
    assert "the 2 played out averaged 1.5, not a score" in text and "returns forfeit, 2, 1, forfeit" in text
    assert "sensitivity, not a score: with each forfeit counted at -21 (the game's worst return, games/pong.py)" in text
    readme = (tmp_path / "cmp" / "README.md").read_text()
    assert "cannot compare: A forfeited 2 of 4 games" in readme and "beyond the noise" not in readme


@pytest.mark.slow
def test_compare_of_two_runs_gives_a_forfeited_best_no_score(tmp_path):
    """Two optimization runs with no LLM update, started from the quitter and from its twin and scored under the
    standard protocol: the quitter's starter forfeits 2 of its 4 games, so its run's best has no score."""
    from pipeline.llm.client import LiteLLMClient
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.loop import optimize
    from pipeline.optimizer.runs import compare_runs
    from viewers.compare_report import text_lines

    store = Store(tmp_path / "s.duckdb", lock_timeout_s=20)
    ids = []
    for policy in (QUITTER, TWIN):
        config = OptimizeConfig(game="pong", policy=str(policy), iterations=0, rollout_steps=50, eval_max_steps=600,
                                robust_episodes=4, optimize_protocol="standard", audit_episodes=0, seed=16, workers=2,
                                rng_key="forfeits")
        result = optimize(config, store, LiteLLMClient("openai/unused", api_base="http://127.0.0.1:9"))
        assert result.status == "finished", result.error
        ids.append(result.run_id)
    data = compare_runs(store, *ids).as_dict()
    a, b = data["runs"]
    assert a["best_score"] is None and a["best_forfeited"] and b["best_score"] == 0.75
    assert data["difference"]["significant"] is None
    assert data["difference"]["verdict"].startswith("cannot compare: A forfeited 2 of 4 games: no score to compare")
    text = "\n".join(text_lines(data))
    assert "no score (forfeited)" in text and "beyond the noise" not in text
    assert store.query("SELECT run_id FROM run_summary ORDER BY best_score DESC NULLS LAST LIMIT 1") == [(ids[1],)]
