"""Search strategies (pipeline/optimizer/strategies.py): greedy replays the paper's loop as it was, best-of-n asks for its
proposals at once, beam keeps its best versions, lineage is data, and the evaluation cache saves steps, not scores."""

from __future__ import annotations

import gzip
import json
import re
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.optimizer.replay import replay
from store import Store
from tests.conftest import COMPETENT_PREDICT, COMPETENT_REPLY, COMPETENT_SELECT, ROOT, json_reply

FIXTURE = Path(__file__).parent / "fixtures" / "greedy_run.duckdb.gz"
ALWAYS_UP = json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return 2\n"})
RAISES = json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return obs['Nope']\n"})
HALF = json_reply({"predict_ball_trajectory": COMPETENT_PREDICT,
                   "select_action": COMPETENT_SELECT.replace("target - 3", "target - 30")})
POOL = [COMPETENT_REPLY, ALWAYS_UP, RAISES, HALF, "no code today"]
"""Candidate policies of mixed quality, as a model sampling at a high temperature might write them."""


@pytest.fixture(autouse=True)
def history_is_what_the_store_reads_back(monkeypatch):
    """The loop keeps its history in memory (``RunState.history``), extended by each commit with the rows it
    wrote: after every commit of every run here, it must equal what the store reads back."""
    from pipeline.optimizer import conclude as loop  # where the commit is
    from pipeline.optimizer.strategies import History
    from store.readers import candidates, iterations

    commit, checked = loop._commit, []

    def commit_and_compare(store, state, iteration, *args, **kwargs):
        commit(store, state, iteration, *args, **kwargs)
        with store.read() as con:
            stored = History(iterations(con, state.run_id, iteration + 1), candidates(con, state.run_id, iteration + 1))
        assert state.history.iterations == stored.iterations
        assert state.history.candidates == stored.candidates
        checked.append(iteration)

    monkeypatch.setattr(loop, "_commit", commit_and_compare)
    return checked


def _client(model):
    return LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)


def _steps(store: Store, run_id: str) -> int:
    """The environment steps the loop played (the held-out audit after it is not the loop's)."""
    return store.query("SELECT count(*) FROM steps s JOIN episodes e USING (episode_id) WHERE e.run_id = ? "
                       "AND e.kind <> 'audit'", [run_id])[0][0]


@pytest.mark.slow
def test_greedy_replays_a_run_made_before_strategies_existed(tmp_path):
    """The fixture was written by the loop before it was split into strategy, propose and assess
    (tests/fixtures/make_greedy_run.py): replaying it sends the same prompts and gets the same scores."""
    path = tmp_path / "old.duckdb"
    path.write_bytes(gzip.decompress(FIXTURE.read_bytes()))
    store = Store(path)
    (run_id,) = store.query("SELECT run_id FROM runs")[0]
    report = replay(store, run_id)
    assert report.status == "finished" and report.diverged_at is None, report.as_dict()
    assert [r.iteration for r in report.rows] == [0, 1, 2, 3, 4, 5] and all(r.matches for r in report.rows)
    assert sum(r.original_prompt is not None for r in report.rows) == 5
    # the old run's lineage was filled in by migration 6, as the greedy strategy writes it today
    old = store.query("SELECT iteration, parent_iteration, update_status, decision FROM candidates "
                      "WHERE run_id = ? ORDER BY iteration", [run_id])
    new = store.query("SELECT iteration, parent_iteration, update_status, decision FROM candidates "
                      "WHERE run_id = ? ORDER BY iteration", [report.replay_run_id])
    assert old == new, (old, new)
    assert [r[1] for r in old] == [None, 0, 1, 1, 3, 4], "iteration 3 starts from 1 after 2 was rolled back"
    # the unchanged and rejected iterations re-assessed a version already played: their episodes were reused
    cached = store.query("SELECT iteration FROM candidates WHERE run_id = ? AND evaluation = 'cached' ORDER BY 1",
                         [report.replay_run_id])
    assert [r[0] for r in cached] == [3, 4, 5]
    assert _steps(store, report.replay_run_id) < _steps(store, run_id) * 0.6


@pytest.mark.slow
def test_evaluation_cache_saves_steps_not_scores(store, scripted):
    replies = ["not code", json_reply({}), COMPETENT_REPLY, ALWAYS_UP, "still not code"]
    config = dict(game="pong", iterations=5, eval_max_steps=900, rollout_steps=50, workers=2, token_budget=6000,
                  rng_key="cache",  # both runs' random starter draws the same numbers
                  repairs=0,  # one scripted reply per update (repairs: tests/test_repairs.py)
                  audit_episodes=0)  # the loop's steps are compared; a held-out audit is tests/test_audit.py's
    cached = optimize(OptimizeConfig(**config), store, _client(scripted(replies)))
    played = optimize(OptimizeConfig(**config, eval_cache=False), store, _client(scripted(replies)))
    assert [i.score for i in cached.iterations] == [i.score for i in played.iterations]
    assert [i.update_status for i in cached.iterations] == ["initial", "rejected", "unchanged", "accepted",
                                                             "accepted", "rejected"]
    evaluation = store.query("SELECT iteration, evaluation FROM candidates WHERE run_id = ? ORDER BY iteration",
                             [cached.run_id])
    assert [e for _, e in evaluation] == ["played", "cached", "cached", "played", "played", "cached"]
    assert store.query("SELECT count(*) FROM candidates WHERE run_id = ? AND evaluation = 'cached'",
                       [played.run_id])[0][0] == 0
    ratio = _steps(store, cached.run_id) / _steps(store, played.run_id)
    assert ratio < 0.6, ratio
    # iteration 5 fell back to the rolled-back-to best (iteration 3): its row points at iteration 3's episodes
    five, three = (store.query("SELECT train_episode_id, eval_episode_ids FROM iterations WHERE run_id = ? AND "
                               "iteration = ?", [cached.run_id, i])[0] for i in (5, 3))
    assert five == three


@pytest.mark.slow
def test_best_of_n_asks_for_its_proposals_at_once_and_keeps_the_best(store, scripted):
    delay = 2.0
    model = scripted([{"pool": POOL, "seed": 3, "sleep": delay}])
    config = OptimizeConfig(game="pong", strategy="best-of-n", candidates=4, iterations=2, eval_max_steps=900,
                            rollout_steps=50, workers=2, token_budget=6000, temperature=1.0, audit_episodes=0,
                            repairs=0)  # one scripted reply per update (repairs: tests/test_repairs.py)
    result = optimize(config, store, _client(model))
    assert result.status == "finished", result.error
    arrivals = sorted(r["received_at"] for r in model.raw_requests())
    assert len(arrivals) == 8
    for first in (0, 4):  # each iteration's 4 requests were all in flight before the first reply came back
        assert arrivals[first + 3] - arrivals[first] < delay, arrivals
    rows = store.query("SELECT iteration, candidate, parent_iteration, parent_candidate, score, decision, "
                       "llm_call_id IS NOT NULL FROM candidates WHERE run_id = ? AND iteration > 0 "
                       "ORDER BY iteration, candidate", [result.run_id])
    assert len(rows) == 8 and all(r[6] for r in rows), "every candidate has the call that made it"
    for it in (1, 2):
        mine = [r for r in rows if r[0] == it]
        (best_iteration,) = store.query("SELECT best_iteration FROM iterations WHERE run_id = ? AND iteration = ?",
                                        [result.run_id, it - 1])[0]
        (best_candidate,) = store.query("SELECT candidate FROM iterations WHERE run_id = ? AND iteration = ?",
                                        [result.run_id, best_iteration])[0]
        assert {(r[2], r[3]) for r in mine} == {(best_iteration, best_candidate)}, "all improve the best version"
        chosen = store.query("SELECT candidate, score FROM iterations WHERE run_id = ? AND iteration = ?",
                             [result.run_id, it])[0]
        assert chosen[1] == max(r[4] for r in mine), "the iteration's row is its best candidate"
    assert store.query("SELECT count(*) FROM llm_calls WHERE run_id = ?", [result.run_id])[0][0] == 8
    # the lineage view: each candidate with its parent's score
    lineage = store.query("SELECT count(*), count(parent_score) FROM lineage WHERE run_id = ? AND iteration > 0",
                          [result.run_id])[0]
    assert lineage == (8, 8)


@pytest.mark.slow
def test_beam_expands_its_best_versions(store, scripted):
    model = scripted([{"pool": POOL, "seed": 11}])
    config = OptimizeConfig(game="pong", strategy="beam", beam_width=2, candidates=2, iterations=3,
                            eval_max_steps=700, rollout_steps=40, workers=2, token_budget=6000, audit_episodes=0)
    result = optimize(config, store, _client(model))
    assert result.status == "finished", result.error
    frontier = store.query("SELECT policy_version_id, score FROM frontier WHERE run_id = ? ORDER BY rank, "
                           "first_iteration", [result.run_id])
    candidates = store.query("SELECT iteration, parent_version_id, policy_version_id, score FROM candidates "
                             "WHERE run_id = ? ORDER BY iteration, candidate", [result.run_id])
    for it in (2, 3):
        before = {}
        for c in candidates:
            if c[0] < it:
                before.setdefault(c[2], c[3])
        beam = sorted(before.items(), key=lambda kv: -kv[1])[:2]
        parents = sorted({c[1] for c in candidates if c[0] == it})
        assert len([c for c in candidates if c[0] == it]) == 2 * len(beam)
        assert parents == sorted(v for v, _ in beam), (it, parents, beam)
    assert frontier[0][1] == max(c[3] for c in candidates)


@pytest.mark.slow
def test_kill_during_a_concurrent_iteration_then_resume(store, scripted, capsys):
    from pipeline.cli import main

    exe = os.path.join(os.path.dirname(os.sys.executable), "codearcade")
    model = scripted([{"pool": POOL, "seed": 5}])
    process = subprocess.Popen(
        [exe, "optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base, "--strategy",
         "best-of-n", "--candidates", "3", "--iterations", "2", "--eval-max-steps", "3000", "--eval-episodes", "3",
         "--rollout-steps", "40", "--workers", "1", "--repairs", "0", "--audit-episodes", "0", "--store",
         str(store.path)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 180
    # iteration 1's three replies are stored; its candidates are being played: three games each (the seeded pool
    # gives it one policy thrice, played once), so that a loaded machine's poll still lands inside the iteration
    while time.monotonic() < deadline:
        try:
            if store.query("SELECT count(*) FROM llm_calls WHERE iteration = 1")[0][0] == 3:
                break
        except Exception:
            pass
        time.sleep(0.05)
    else:
        raise AssertionError("iteration 1's calls never arrived")
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert store.query("SELECT count(*) FROM iterations WHERE iteration = 1")[0][0] == 0
    calls_before = len(model.requests())
    run_id = store.query("SELECT run_id FROM runs")[0][0]
    capsys.readouterr()  # resumed in this process, as the command line runs it (it had imported litellm once)
    assert main(["optimize", "--resume", run_id, "--store", str(store.path), "--json"]) == 0, capsys.readouterr().err
    assert json.loads(capsys.readouterr().out)["status"] == "finished"
    assert len(model.requests()) == calls_before + 3, "iteration 1's replies came from the store"
    per_iteration = store.query("SELECT iteration, count(*), count(DISTINCT candidate) FROM candidates "
                                "GROUP BY iteration ORDER BY iteration")
    assert per_iteration == [(0, 1, 1), (1, 3, 3), (2, 3, 3)]
    assert store.query("SELECT count(*) FROM llm_calls WHERE iteration = 1")[0][0] == 3
    assert store.query("SELECT count(*), count(DISTINCT episode_id) FROM episodes")[0] == \
        store.query("SELECT count(*), count(*) FROM episodes")[0]


def test_strategy_options_are_checked():
    with pytest.raises(ValueError, match="--strategy must be one of greedy, best-of-n, beam"):
        optimize(OptimizeConfig(game="pong", strategy="annealing"), Store("/nonexistent/x.duckdb"), None)
    with pytest.raises(ValueError, match="greedy makes one proposal"):
        optimize(OptimizeConfig(game="pong", candidates=3), Store("/nonexistent/x.duckdb"), None)


@pytest.mark.slow
def test_strategies_example_and_its_sql(tmp_path, store, scripted):
    """examples/strategies.toml, shortened to a budget of 4 calls with the scripted model standing in; then
    examples/strategies.sql tabulates the strategies at that equal budget."""
    from pipeline.jobs.experiments import load_experiments

    assert len(load_experiments(ROOT / "examples" / "strategies.toml").runs) == 10
    model = scripted([{"pool": POOL, "seed": 2}])
    source = (ROOT / "examples" / "strategies.toml").read_text()
    short = (source.replace("max_llm_calls = 20", "max_llm_calls = 4\neval_max_steps = 300\nrollout_steps = 40\n"
                            "audit_episodes = 0")  # the SQL reads the loop's candidates, not a held-out audit
             .replace('model = "anthropic/claude-sonnet-4-5"', f'model = "{model.model}"\napi_base = "{model.api_base}"')
             .replace("seed = [0, 1, 2]", "seed = [0]"))
    path = tmp_path / "strategies.toml"
    path.write_text(short)
    done = subprocess.run([os.path.join(os.path.dirname(os.sys.executable), "codearcade"), "batch", str(path),
                           "--store", str(store.path), "--workers", "2"], cwd=ROOT, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr + done.stdout
    calls = store.query("SELECT json_extract_string(r.config, '$.strategy'), r.status, u.calls FROM runs r "
                        "JOIN llm_usage u USING (run_id) ORDER BY ALL")
    assert all(status == "budget" and 0 < n <= 4 for _, status, n in calls), calls
    assert dict((s, n) for s, _, n in calls if s != "beam") == {"best-of-n": 4, "greedy": 4}
    from store.views import run_user_query

    # as `codearcade sql` runs it, with mean_ci and ci_text: mean [low, high] over a strategy's runs (alone for one)
    rows = run_user_query(store, (ROOT / "examples" / "strategies.sql").read_text()).rows
    assert sorted(r[0] for r in rows) == ["beam", "best-of-n", "greedy"]
    by_strategy = {r[0]: r for r in rows}
    assert by_strategy["beam"][1] == 2 and by_strategy["greedy"][1] == 1
    assert by_strategy["greedy"][4] == f"{by_strategy['greedy'][5]:.1f} (n=1: too few for an interval)", \
        "one run: its best, no interval"
    assert re.fullmatch(r"\S+ (\[\S+, \S+\] 95% t, n=2|\(n=2: all equal, no interval\))", by_strategy["beam"][4]), \
        "two runs: the mean and its interval"
    means = [[float(text.split()[0]) for text in r[2:5]] for r in rows]
    assert all(a <= b <= c for a, b, c in means), "the best so far never falls as calls are spent"
    assert [m[2] for m in means] == sorted((m[2] for m in means), reverse=True)


@pytest.mark.slow
def test_both_protocols_are_scored_and_the_chosen_one_is_optimized(store, scripted):
    model = scripted([COMPETENT_REPLY])
    config = OptimizeConfig(game="pong", iterations=1, eval_max_steps=800, rollout_steps=40, workers=2,
                            token_budget=6000, robust_episodes=2, optimize_protocol="standard", audit_episodes=0)
    result = optimize(config, store, _client(model))
    assert result.status == "finished", result.error
    rows = store.query("SELECT iteration, score, deterministic_score, standard_score, eval_episode_ids, "
                       "robust_episode_ids FROM candidates ORDER BY iteration")
    assert len(rows) == 2
    for iteration, score, deterministic, standard, evals, robust in rows:
        assert score == standard and len(robust) == 2 and len(evals) == 1
        returns = dict(store.query("SELECT episode_id, return FROM episodes"))
        assert standard == sum(returns[e] for e in robust) / 2 and deterministic == returns[evals[0]]
    protocol = store.query("SELECT DISTINCT kind, sticky, noop_max, verified FROM episodes WHERE kind = 'robust'")
    assert protocol == [("robust", 0.25, 30, True)]
    assert [r[0] for r in store.query("SELECT score FROM iterations ORDER BY iteration")] == [r[1] for r in rows]
    prompt = model.requests()[0][1]["content"]
    assert "under the standard protocol (sticky actions 0.25" in prompt and "the score being optimized" in prompt
    with pytest.raises(ValueError, match="needs --robust-episodes"):
        optimize(OptimizeConfig(game="pong", optimize_protocol="standard"), store, None)


@pytest.mark.slow
def test_map_elites_draws_parents_from_its_archive_and_replays(store, scripted):
    model = scripted([{"pool": POOL, "seed": 17}])
    config = OptimizeConfig(game="pong", strategy="map-elites", candidates=3, iterations=3, eval_max_steps=600,
                            rollout_steps=40, workers=2, token_budget=6000, temperature=1.0, audit_episodes=0)
    result = optimize(config, store, _client(model))
    assert result.status == "finished", result.error
    rows = store.query("SELECT iteration, candidate, parent_iteration, parent_candidate, decision FROM candidates "
                       "WHERE run_id = ? ORDER BY iteration, candidate", [result.run_id])
    assert [r[0] for r in rows] == [0, 1, 1, 1, 2, 2, 2, 3, 3, 3]
    refs = {(r[0], r[1]) for r in rows}
    for it, _, parent_it, parent_c, _ in rows[1:]:
        assert parent_it < it and (parent_it, parent_c) in refs, "every parent is an earlier assessed candidate"
    assert {r[4] for r in rows} <= {"best", "kept", "discarded", "rejected"}
    # the draws are seeded: replaying the run sends the same prompts to the same candidates
    report = replay(store, result.run_id)
    assert report.diverged_at is None and all(r.matches for r in report.rows), report.as_dict()
    replayed = store.query("SELECT iteration, candidate, parent_iteration, parent_candidate FROM candidates "
                           "WHERE run_id = ? ORDER BY iteration, candidate", [report.replay_run_id])
    assert replayed == [r[:4] for r in rows]


@pytest.mark.slow
def test_cascade_and_cache_cut_the_steps_not_the_best_scores(store, scripted):
    """A candidate that falls behind its parent in the first steps of the evaluation game is screened out before
    its full assessment; with the evaluation cache this plays far fewer steps for the same best-so-far curve."""
    replies = [COMPETENT_REPLY, ALWAYS_UP, "no code", COMPETENT_REPLY, ALWAYS_UP]
    config = dict(game="pong", iterations=5, eval_max_steps=1500, rollout_steps=60, workers=2, token_budget=6000,
                  rng_key="cascade",  # both runs' random starter draws the same numbers
                  audit_episodes=0)  # the loop's steps are compared (_steps leaves an audit out)
    plain = optimize(OptimizeConfig(**config, eval_cache=False), store, _client(scripted(replies)))
    cheap = optimize(OptimizeConfig(**config, screen_steps=300), store, _client(scripted(replies)))
    assert [i.best_score for i in cheap.iterations] == [i.best_score for i in plain.iterations]
    rows = store.query("SELECT iteration, update_status, evaluation, screen_score, screen_bar FROM candidates "
                       "WHERE run_id = ? ORDER BY iteration", [cheap.run_id])
    assert rows[1][2] == "played" and rows[1][3] >= rows[1][4], "the competent version kept up: fully assessed"
    assert rows[2][1:3] == ("rejected", "screened") and rows[2][3] < rows[2][4], "always-up fell behind: screened out"
    assert rows[5][1:] == rows[2][1:], "the same always-up code again: screened out by the same game"
    screens = store.query("SELECT count(*), max(length) FROM episodes WHERE run_id = ? AND kind = 'screen'",
                          [cheap.run_id])[0]
    assert screens == (2, 300), "competent and always-up screened once each; the repeat reused its game"
    feedback = store.query("SELECT text FROM feedback WHERE run_id = ? AND iteration = 2", [cheap.run_id])[0][0]
    assert "screened out" in feedback and "first 300 steps" in feedback
    ratio = _steps(store, cheap.run_id) / _steps(store, plain.run_id)
    print(f"environment steps with cascade + cache / without: {ratio:.2f}")
    assert ratio < 0.7, ratio


def test_one_life_optimization_ends_every_episode_at_the_first_lost_life(store, scripted):
    """The authors' protocol (``--one-life``) for the optimizer's episodes too: Breakout's training rollout
    and evaluation stop at the first lost ball. Its random stream pinned, and a call limit with room for a loaded
    machine (an episode ended otherwise in a full run beside two CPU hogs; the default 1 s is wall-clock time)."""
    model = scripted([json_reply({})])
    result = optimize(OptimizeConfig(game="breakout", iterations=1, eval_max_steps=3000, rollout_steps=3000,
                                     workers=2, token_budget=6000, one_life=True, rng_key="one-life",
                                     call_time_limit_s=30.0), store, _client(model))
    assert result.status == "finished", result.error
    episodes = store.query("SELECT kind, lives_lost, end_reason, length FROM episodes WHERE run_id = ?",
                           [result.run_id])
    # kind, lives lost, end, length. The loop's own episodes (the paper's protocol, pinned) lose their first ball.
    # The audit's are on sealed seeds under sticky actions, where the starter can leave the ball unserved for the
    # whole cap (CI saw one such game): then no life is lost and the cap ends it. No episode plays on past a loss.
    loop_episodes = [e for e in episodes if e[0] != "audit"]
    broken = [e for e in loop_episodes if not (e[1] == 1 and e[2] == "terminated" and e[3] < 3000)]
    assert loop_episodes and not broken, broken
    audit = [e for e in episodes if e[0] == "audit"]
    played_on = [e for e in audit if not ((e[1] == 1 and e[2] == "terminated" and e[3] < 3000)
                                          or (e[1] == 0 and e[2] == "truncated" and e[3] == 3000))]
    assert audit and not played_on, played_on
    assert any(e[1] == 1 for e in audit), audit
    assert store.query("SELECT json_extract(config, '$.one_life') FROM runs WHERE run_id = ?",
                       [result.run_id])[0][0] == "true"


def _row(iteration: int, candidate: int, version: str, score: float | None, forfeit: str | None = None,
         complexity: int = 2, length: int = 4000, decision: str = "kept") -> dict:
    return dict(iteration=iteration, candidate=candidate, decision=decision, policy_version_id=version,
                proposed_version_id=version, score=score, forfeit=forfeit, complexity=complexity,
                eval_length=length, parent_iteration=None if iteration == 0 else 0,
                parent_candidate=None if iteration == 0 else 0)


def test_a_version_that_forfeited_is_never_a_parent_of_beam_or_map_elites_while_one_played_out():
    """A forfeit is never ranked (``store/scores.py``), and map-elites' ``decide`` keeps none in its archive; yet
    its plan drew parents from every assessed version, forfeits included, each the elite of a cell of its own (a
    game it ended early is a short game): two crashing versions beside the starter and a better one took 51% of
    800 parent draws, the best honest version 24%. The beam likewise filled a slot with a forfeit. Now both plan
    from the versions that played their games out, and from forfeits only when none did (a starter that
    forfeits is all there is to improve)."""
    from collections import Counter

    from pipeline.optimizer.strategies import Beam, History, MapElites

    rows = [_row(0, 0, "starter", -20.0, decision="best"),
            _row(1, 0, "crash", None, "KeyError at step 1 (policy_error)", complexity=3, length=1,
                 decision="discarded"),
            _row(1, 1, "good", -10.0, complexity=9, decision="best"),
            _row(1, 2, "slow", None, "timeout at step 900 (timeout)", complexity=14, length=900,
                 decision="discarded")]
    history = History([dict(iteration=0, candidate=0, best_iteration=0, best_score=-20.0),
                       dict(iteration=1, candidate=1, best_iteration=1, best_score=-10.0)], rows)
    parents = Counter()
    for seed in range(5):
        strategy = MapElites(candidates=4, seed=seed, eval_max_steps=4000)
        for iteration in range(2, 42):
            parents.update(history.candidate(r.parent)["policy_version_id"] for r in strategy.plan(history, iteration))
    assert set(parents) == {"starter", "good"}, parents
    assert [history.candidate(r)["policy_version_id"] for r in Beam(width=3).beam(history)] == ["good", "starter"]
    # nothing played out: the forfeits are what there is to improve
    only = History([dict(iteration=0, candidate=0, best_iteration=0, best_score=None)],
                   [_row(0, 0, "starter", None, "KeyError at step 3 (policy_error)", decision="best")])
    assert [r.parent for r in MapElites(candidates=2).plan(only, 1)] == [only.chosen(0)] * 2
    assert Beam(width=3).beam(only) == [only.chosen(0)]
