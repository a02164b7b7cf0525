"""The SQL views of migration 3: documented column by column, correct on a real run and on edge cases."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.play.evaluate import EvalConfig, evaluate
from store import Store
from store.migrations import LATEST, MIGRATIONS
from store.views import VIEWS, run_query, run_user_query
from tests.conftest import COMPETENT_REPLY, EXAMPLES, json_reply, old_store

ROOT = Path(__file__).resolve().parents[1]

ALWAYS_UP = json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return 2\n"})
KEY_ERROR = json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return obs['Nope']\n"})
WRONG_SIGNATURE = json_reply({"select_action": "def select_action(self, obs):\n    return 0\n"})
# iteration: 1 competent (accepted), 2 always-up (accepted, regresses: rolled back), 3 unusable reply (parse),
# 4 raises on recorded observations (runtime), 5 changes the parameters (static)
SCRIPT = [COMPETENT_REPLY, ALWAYS_UP, "Sorry, I cannot help with that.", KEY_ERROR, WRONG_SIGNATURE]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One store with a real optimize run (scripted model, 5 iterations, short episodes) and an eval run."""
    from tests.scripted_llm import ScriptedModel

    tmp = tmp_path_factory.mktemp("views")
    store = Store(tmp / "views.duckdb", lock_timeout_s=20)
    with ScriptedModel(SCRIPT, tmp / "model") as model:
        client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
        config = OptimizeConfig(game="pong", iterations=5, rollout_steps=100, eval_max_steps=200, eval_episodes=2,
                                workers=2, token_budget=8000, repairs=0, rng_key="views")  # one scripted reply per update (repairs: tests/test_repairs.py)
        result = optimize(config, store, client)
    assert result.status == "finished", result.error
    ev = evaluate(EXAMPLES / "pong.py", EvalConfig(episodes=3, max_steps=200, workers=2), store)
    return store, result.run_id, ev.run_id


def _dicts(store: Store, sql: str, params=None) -> list[dict]:
    result = run_query(store, sql, params)
    return [dict(zip(result.columns, row)) for row in result.rows]


def _view_columns(store: Store) -> dict[str, list[str]]:
    rows = store.query("SELECT table_name, column_name FROM information_schema.columns c "
                       "JOIN duckdb_views() v ON v.view_name = c.table_name AND NOT v.internal "
                       "WHERE c.table_schema = 'main' ORDER BY table_name, ordinal_position")
    out: dict[str, list[str]] = {}
    for view, column in rows:
        out.setdefault(view, []).append(column)
    return out


def test_migrations_create_exactly_the_documented_views(store):
    with store.write():
        pass
    assert LATEST == MIGRATIONS[-1][0] >= 3
    assert set(_view_columns(store)) == set(VIEWS)


def test_schema_doc_describes_every_view_column(store):
    """Each view has its own section in docs/schema.md whose table lists exactly the view's columns."""
    doc = (ROOT / "docs" / "schema.md").read_text()
    with store.write():
        pass
    for view, columns in _view_columns(store).items():
        match = re.search(rf"^### `{view}`.*?$(.*?)(?=^#)", doc, re.S | re.M)
        assert match, f"docs/schema.md has no section for the view {view}"
        documented = re.findall(r"^\| `(\w+)` \|", match.group(1), re.M)
        assert documented == columns, f"docs/schema.md's table for {view} does not match its columns"


def test_views_reach_a_store_written_by_an_older_codearcade(tmp_path):
    """A store at schema version 2 gets the views the first time codearcade opens it (here: `codearcade sql`)."""
    from pipeline.cli import main

    path = tmp_path / "old.duckdb"
    old_store(path, 2).close()
    assert main(["sql", "SELECT count(*) AS n FROM run_summary", "--csv", "--store", str(path)]) == 0
    assert Store(path).query("SELECT max(version) FROM schema_migrations")[0][0] == LATEST


@pytest.mark.slow
def test_learning_curve(runs):
    store, run_id, _ = runs
    curve = _dicts(store, "SELECT * FROM learning_curve WHERE run_id = ? ORDER BY iteration", [run_id])
    assert [r["iteration"] for r in curve] == [0, 1, 2, 3, 4, 5]
    assert [r["update_status"] for r in curve] == ["initial", "accepted", "accepted", "rejected", "rejected",
                                                   "rejected"]
    assert [r["rolled_back"] for r in curve] == [False, False, True, False, False, False], \
        "always-up regressed below the competent version's score"
    # an iteration's evaluation: its own episodes, or an earlier assessment's (the evaluation cache)
    evals = dict(store.query("SELECT i.iteration, avg(e.return) FROM iterations i JOIN episodes e "
                             "ON list_contains(i.eval_episode_ids, e.episode_id) WHERE i.run_id = ? "
                             "GROUP BY i.iteration", [run_id]))
    calls = {i: (a, b) for i, a, b in store.query(
        "SELECT iteration, input_tokens, output_tokens FROM llm_calls WHERE run_id = ?", [run_id])}
    total = 0
    for r in curve:
        assert r["score"] == pytest.approx(evals[r["iteration"]])
        assert r["best_score"] == max(x["score"] for x in curve[: r["iteration"] + 1])
        assert (r["input_tokens"], r["output_tokens"]) == calls.get(r["iteration"], (0, 0))
        total += r["total_tokens"]
        assert r["cumulative_tokens"] == total
        assert r["llm_calls"] == (0 if r["iteration"] == 0 else 1)
    assert curve[0]["total_tokens"] == 0 and curve[1]["input_tokens"] > 1000
    assert curve[-1]["elapsed_s"] == pytest.approx(sum(r["wall_s"] for r in curve))


def test_code_metrics_counts_a_recurring_version_once(runs):
    store, run_id, _ = runs
    rows = _dicts(store, "SELECT * FROM code_metrics WHERE run_id = ? ORDER BY iteration", [run_id])
    versions = store.query("SELECT policy_version_id, loc, complexity FROM policy_versions WHERE run_id = ? AND "
                           "produced_by = 'llm' AND iteration = 1", [run_id])[0]
    assert store.query("SELECT count(*) FROM policy_versions WHERE run_id = ? AND policy_version_id = ? AND "
                       "validation = 'accepted'", [run_id, versions[0]])[0][0] == 2, "the rollback recorded it again"
    assert [r["iteration"] for r in rows] == [0, 1, 2, 3, 4, 5], "one row per iteration, no duplicates"
    after = rows[3:]
    assert all(r["policy_version_id"] == versions[0] and r["version_iteration"] == 1 for r in after), \
        "after the rollback the competent version of iteration 1 is evaluated again"
    assert all((r["loc"], r["complexity"]) == versions[1:] for r in after)
    assert rows[1]["complexity"] > rows[0]["complexity"] and rows[1]["trainable_sloc"] > rows[0]["trainable_sloc"]
    assert rows[2]["complexity"] < rows[1]["complexity"], "always-up is simpler"
    assert all(r["trainable_sloc"] < r["sloc"] <= r["loc"] for r in rows)


def test_rejected_candidates_have_stage_and_reason(runs):
    store, run_id, _ = runs
    rows = _dicts(store, "SELECT * FROM rejected_candidates WHERE run_id = ? ORDER BY iteration", [run_id])
    assert [(r["iteration"], r["stage"]) for r in rows] == [(3, "parse"), (4, "runtime"), (5, "static")]
    assert "neither a JSON suggestion" in rows[0]["reason"] and rows[0]["policy_version_id"] is None
    assert "KeyError" in rows[1]["reason"] and rows[1]["policy_version_id"] is not None
    assert rows[2]["reason"].startswith("select_action must keep its parameters")
    assert rows[2]["policy_version_id"] is None
    call_ids = dict(store.query("SELECT iteration, call_id FROM llm_calls WHERE run_id = ?", [run_id]))
    assert all(r["llm_call_id"] == call_ids[r["iteration"]] for r in rows)


def test_llm_usage_and_run_summary(runs):
    store, run_id, eval_id = runs
    usage = {r["run_id"]: r for r in _dicts(store, "SELECT * FROM llm_usage")}
    u = usage[run_id]
    assert (u["calls"], u["errors"], u["parse_errors"], u["retries"], u["replayed"]) == (5, 0, 1, 0, 0)
    tokens = store.query("SELECT sum(input_tokens), sum(output_tokens) FROM llm_calls")[0]
    assert (u["input_tokens"], u["output_tokens"]) == tokens and u["total_tokens"] == sum(tokens)
    assert u["request_models"] == "openai/scripted" and u["cost_usd"] is None
    assert u["mean_latency_s"] == pytest.approx(u["latency_s"] / 5)
    assert usage[eval_id]["calls"] == 0 and usage[eval_id]["total_tokens"] == 0

    summary = {r["run_id"]: r for r in _dicts(store, "SELECT * FROM run_summary")}
    s, e = summary[run_id], summary[eval_id]
    assert (s["kind"], s["game"], s["model"], s["status"]) == ("optimize", "pong", "openai/scripted", "finished")
    assert (s["iterations_done"], s["iterations_planned"], s["best_iteration"]) == (5, 5, 1)
    assert s["best_score"] == max(r[0] for r in store.query("SELECT score FROM iterations"))
    played = store.query("SELECT count(*) FROM episodes WHERE run_id = ? AND kind <> 'audit'", [run_id])[0][0]
    assert played == 3 * 3, "iterations 0-2 played; 3-5 fell back to the best version and reused its episodes"
    audited = store.query("SELECT count(*) FROM episodes WHERE run_id = ? AND kind = 'audit'", [run_id])[0][0]
    assert audited == 2 * 2 * 3, "the held-out audit: the best and the starter, two protocols, three games each"
    assert s["episodes"] == played + audited and s["total_tokens"] == sum(tokens) and s["duration_s"] > 0
    assert s["audit_score"] is not None and s["overfit"] is not None
    returns = [r[0] for r in store.query("SELECT return FROM episodes WHERE run_id = ?", [eval_id])]
    assert (e["kind"], e["model"], e["iterations_done"], e["iterations_planned"]) == ("eval", None, 0, None)
    assert e["best_score"] == pytest.approx(sum(returns) / 3) and e["steps"] == 3 * 200 and e["total_tokens"] == 0


def test_run_summary_tells_runs_apart(runs):
    store, run_id, eval_id = runs
    summary = {r["run_id"]: r for r in _dicts(store, "SELECT * FROM run_summary")}
    s, e = summary[run_id], summary[eval_id]
    assert (s["name"], s["policy"], s["strategy"], s["feedback"], s["batch"], s["made_by"]) == (
        None, None, "greedy", "staged", None, None), "an optimize run from the scaffold"
    assert (e["policy"], e["strategy"], e["feedback"]) == (str(EXAMPLES / "pong.py"), None, None)


def _doc_sql_examples() -> list[tuple[str, list[str]]]:
    """Every `codearcade sql` command docs/schema.md prints: (query, --param values)."""
    import shlex

    doc = (ROOT / "docs" / "schema.md").read_text()
    examples = []
    for line in re.findall(r"^codearcade sql .*$", doc, re.M):
        argv = shlex.split(line, comments=True)
        params = [argv[k + 1] for k, arg in enumerate(argv) if arg == "--param"]
        examples.append((argv[2], params))
    return examples


def test_schema_doc_examples_run_as_printed(runs):
    """Each example runs as printed, its `?` filled by its --param values (`last` is here the eval run made last:
    the examples about an optimization are given the one before it, `last~1`)."""
    store, run_id, _ = runs
    examples = _doc_sql_examples()
    assert len(examples) >= 12 and sum(bool(p) for _, p in examples) >= 9
    for sql, params in examples:
        result = run_user_query(store, sql.replace("run('last')", "run('last~1')"),
                                ["last~1" if p == "last" else p for p in params])
        assert result.columns, sql
        # a Breakout example; lines every call ran; an ensemble's choices (these runs have one model each)
        empty_here = "'RB'" in sql or "unrun_lines" in sql or "model_choices" in sql
        assert result.rows or empty_here, f"no rows: {sql}"
        if "ORDER BY" not in sql and "run_matches" not in sql:
            raise AssertionError(f"an example without ORDER BY: {sql}")


def test_usage_of_failed_retried_and_priced_calls(store):
    """Counts that a scripted run does not produce: errors, retries, costs, two models, an llm_error iteration."""
    from store.db import utcnow
    from store.writer import insert_run

    with store.write() as con:
        insert_run(con, "R1", "optimize", "pong", {"iterations": 2}, "x = 1\n", "v0", {}, model="m/a")
        for call_id, it, model, tokens, cost, attempts, error in (
            ("C1", 1, "m/a", (100, 10), 0.5, 3, None),
            ("C2", 2, "m/a", (None, None), None, 4, "RateLimitError"),
            ("C3", 2, "m/b", (200, 20), 0.25, 1, None),
        ):
            con.execute("INSERT INTO llm_calls (call_id, run_id, iteration, purpose, created_at, operation_name, "
                        "request_model, prompt_hash, input_tokens, output_tokens, cost_usd, latency_s, attempts, "
                        "error_type, replayed) VALUES (?, 'R1', ?, 'update', ?, 'chat', ?, 'h', ?, ?, ?, 2.0, ?, ?, "
                        "false)", [call_id, it, utcnow(), model, *tokens, cost, attempts, error])
        for it, status in ((0, "initial"), (1, "accepted"), (2, "llm_error")):
            con.execute("INSERT INTO iterations (run_id, iteration, policy_version_id, update_status, rolled_back, "
                        "score, best_score, wall_s) VALUES ('R1', ?, 'v0', ?, false, ?, ?, 1.0)",
                        [it, status, float(it), float(it)])
    u = _dicts(store, "SELECT * FROM llm_usage")[0]
    assert (u["calls"], u["errors"], u["attempts"], u["retries"]) == (3, 1, 8, 5)
    assert (u["input_tokens"], u["output_tokens"], u["cost_usd"]) == (300, 30, 0.75)
    assert u["request_models"] == "m/a, m/b" and u["max_latency_s"] == 2.0
    curve = _dicts(store, "SELECT iteration, llm_calls, input_tokens, total_tokens FROM learning_curve ORDER BY 1")
    assert [(r["llm_calls"], r["input_tokens"], r["total_tokens"]) for r in curve] == [(0, 0, 0), (1, 100, 110),
                                                                                       (2, 200, 220)]
    assert store.query("SELECT count(*) FROM rejected_candidates")[0][0] == 0, "an LLM error is not a rejection"
    s = _dicts(store, "SELECT * FROM run_summary")[0]
    assert (s["iterations_done"], s["iterations_planned"], s["best_score"], s["llm_calls"]) == (2, 2, 2.0, 3)
    assert s["status"] == "running" and s["duration_s"] is None and json.loads(
        store.query("SELECT config FROM runs")[0][0]) == {"iterations": 2}
