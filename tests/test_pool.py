"""The asynchronous proposal pool (``--pool``): calls in flight across iterations, candidates played as their replies
come in, iterations committed in order, and runs that resume and replay to the same versions and scores — against a
scripted model with a long-tailed latency behind a real HTTP endpoint, called through litellm."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from datetime import timedelta

import pytest

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig, validate_config
from pipeline.optimizer.loop import optimize
from pipeline.optimizer.replay import replay
from tests.conftest import ROOT, run_main
from tests.test_strategies import POOL

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
SCRIPT = [{"pool": POOL, "seed": 3, "latency": [0.8, 0.7, 1]}]
"""Candidates of mixed quality, each after a log-normal time (median 0.8 s, a long tail)."""


def _config(**kwargs):
    defaults = dict(game="pong", strategy="best-of-n", candidates=4, iterations=3, eval_max_steps=600,
                    rollout_steps=50, workers=2, token_budget=6000, temperature=1.0, audit_episodes=0, pool=True,
                    rng_key="pool")
    return OptimizeConfig(**{**defaults, **kwargs})


def _client(model):
    return LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)


def _calls(store, run_id):
    return store.query("SELECT iteration, candidate, repair_turn, history_iterations, created_at, latency_s "
                       "FROM llm_calls WHERE run_id = ? ORDER BY created_at", [run_id])


def _bases(store, run_id):
    """Each call's (iteration, candidate, turn, basis iterations, basis candidates, prompt hash, reply hash)."""
    return store.query("SELECT iteration, candidate, repair_turn, history_iterations, basis_candidates, prompt_hash, "
                       "reply_hash FROM llm_calls WHERE run_id = ? AND error_type IS NULL ORDER BY created_at",
                       [run_id])


def _outcome(store, run_id):
    """What a run made: per iteration, its chosen version and score, and every candidate's version and score."""
    iterations = store.query("SELECT iteration, policy_version_id, score, best_score FROM iterations WHERE run_id = ? "
                             "ORDER BY iteration", [run_id])
    candidates = store.query("SELECT iteration, candidate, policy_version_id, score, update_status FROM candidates "
                             "WHERE run_id = ? ORDER BY iteration, candidate", [run_id])
    return iterations, candidates


def _check_bases(store, run_id, resumed=False):
    """No call started from a basis that leaves out a candidate already assessed: every candidate the pool had
    assessed before a call's basis was taken (``candidates.assessed_at`` < ``llm_calls.basis_at``) is in it, committed
    (an iteration below ``history_iterations``) or pending (``basis_candidates``); and a basis holds nothing assessed
    after it was taken (but in a resumed run, whose uncommitted candidates were assessed again after the calls
    recorded before the kill). Returns the first calls' bases."""
    assessed = {(i, c): at for i, c, at in store.query(
        "SELECT iteration, candidate, assessed_at FROM candidates WHERE run_id = ? AND iteration > 0", [run_id])}
    assert assessed and all(at is not None for at in assessed.values()), "the pool records when it learnt each"
    calls = store.query("SELECT iteration, candidate, history_iterations, basis_candidates, basis_at FROM llm_calls "
                        "WHERE run_id = ? AND coalesce(repair_turn, 0) = 0 ORDER BY basis_at", [run_id])
    for iteration, candidate, committed, fresh, at in calls:
        assert at is not None and fresh is not None, (iteration, candidate)
        pending = {(r["iteration"], r["candidate"]) for r in fresh}
        seen = {key for key in assessed if key[0] < committed} | pending
        missed = sorted(key for key, done in assessed.items() if done < at and key not in seen)
        assert not missed, f"the call of candidate {iteration}.{candidate} left out {missed}, assessed before it"
        assert all((resumed or assessed[key] <= at) and key[0] >= committed for key in pending), \
            (iteration, candidate, pending)
    return calls


@pytest.mark.slow
def test_calls_stay_in_flight_across_iterations_and_iterations_commit_in_order(store, scripted):
    model = scripted(SCRIPT)
    result = optimize(_config(), store, _client(model))
    assert result.status == "finished" and [i.iteration for i in result.iterations] == [0, 1, 2, 3]
    run_id = result.run_id
    counts = store.query("SELECT iteration, count(*) FROM candidates WHERE run_id = ? GROUP BY 1 ORDER BY 1", [run_id])
    assert counts == [(0, 1), (1, 4), (2, 4), (3, 4)], "every iteration committed whole, in order"
    calls = _calls(store, run_id)
    firsts = [c for c in calls if c[2] == 0]
    assert sorted((c[0], c[1]) for c in firsts) == [(i, j) for i in (1, 2, 3) for j in range(4)]
    # no barrier: calls of a later iteration started from the iterations committed then, before the one before it
    assert all(basis <= iteration for iteration, _, _, basis, _, _ in firsts)
    assert any(basis < iteration for iteration, _, _, basis, _, _ in firsts), firsts
    spans = [(end - timedelta(seconds=latency), end, iteration) for iteration, _, _, _, end, latency in calls]
    overlapping = [{it for start, end, it in spans if start <= moment < end} for moment, _, _ in spans]
    assert max(sum(1 for start, end, _ in spans if start <= m < end) for m, _, _ in spans) <= 4, "at most K at once"
    assert any(len(iterations) > 1 for iterations in overlapping), "calls of two iterations were in flight together"
    finished = [r[0] for r in store.query("SELECT finished_at FROM iterations WHERE run_id = ? ORDER BY iteration",
                                          [run_id])]
    assert finished == sorted(finished)
    assert "in flight" in result.iterations[1].pool and "playing" in result.iterations[1].pool
    # the last iteration's line says what was in flight once its games were played: nothing (it said "4 candidates
    # playing", the state before the event that completed it)
    assert result.iterations[-1].pool == ("pool: 0 calls in flight, 0 candidates playing (0 episodes), 0 waiting "
                                          "to play"), result.iterations[-1].pool
    bases = _check_bases(store, run_id)
    assert any(fresh for _, _, _, fresh, _ in bases), "some prompts were built from candidates not yet committed"

    report = replay(store, run_id)
    assert report.status == "finished" and all(row.matches for row in report.rows), report.as_dict()["iterations"]
    assert _outcome(store, report.replay_run_id) == _outcome(store, run_id), "the same versions and scores"
    requests = len(model.requests())
    assert requests == len(calls), "a replay never calls the model"


def test_greedy_keeps_its_order():
    with pytest.raises(ValueError, match="--pool is for best-of-n, beam and map-elites"):
        validate_config(OptimizeConfig(game="pong", pool=True))


@pytest.mark.slow
def test_a_call_budget_holds_while_calls_are_in_flight(store, scripted):
    model = scripted(SCRIPT)
    result = optimize(_config(max_llm_calls=6, repairs=0), store, _client(model))
    assert result.status == "budget" and "call budget" in result.error
    assert len(_calls(store, result.run_id)) == 6 == len(model.requests()), "never more calls than the budget"
    counts = store.query("SELECT iteration, count(*) FROM candidates WHERE run_id = ? GROUP BY 1 ORDER BY 1",
                         [result.run_id])
    assert counts == [(0, 1), (1, 4)], "the incomplete iteration is not committed"


@pytest.mark.slow
def test_the_last_calls_of_a_budget_go_to_the_earliest_candidates_whatever_thread_is_first(store, scripted,
                                                                                          monkeypatch):
    """A budget of exactly two iterations' calls commits both, however long each candidate's thread takes to build
    its prompt: a candidate of iteration 3 that starts while one of iteration 2 is still building (it started when a
    quick call freed a slot) must not take the budget's last call from it, or iteration 2 is never committed and the
    budget's calls are spent on candidates that are thrown away (CI's run of bench/proposal_pool.py: 4 of 8). Each
    sweep point slows one thread of iteration 2 well past a call's latency, after its prompt is built."""
    import pipeline.optimizer.propose as propose_module

    choosing = propose_module.choose_members  # between the prompt's build (a store read) and the budget's check
    for slow in ("propose-2.3", "propose-2.1"):
        def slow_choice(*args, _slow=slow, **kwargs):
            if threading.current_thread().name == _slow:
                time.sleep(2.0)  # iteration 3's first candidate starts and asks meanwhile
            return choosing(*args, **kwargs)

        monkeypatch.setattr(propose_module, "choose_members", slow_choice)
        model = scripted([{"pool": POOL, "seed": 3, "latency": [0.1, 0.0, 1]}])
        result = optimize(_config(max_llm_calls=8, repairs=0, eval_max_steps=200, rollout_steps=20), store,
                          _client(model))
        assert result.status == "budget" and "call budget" in result.error
        counts = store.query("SELECT iteration, count(*) FROM candidates WHERE run_id = ? GROUP BY 1 ORDER BY 1",
                             [result.run_id])
        assert counts == [(0, 1), (1, 4), (2, 4)], (slow, counts, result.error)
        calls = store.query("SELECT DISTINCT iteration FROM llm_calls WHERE run_id = ?", [result.run_id])
        assert sorted(calls) == [(1,), (2,)], "no call went to an iteration past the budget"


@pytest.mark.slow
def test_a_token_budget_is_not_spent_by_the_worst_cases_of_calls_in_flight(store, scripted):
    """Calls in flight reserve their worst case (prompt + a reply of --max-tokens), and a real reply is far
    shorter: a call that only those reservations keep out waits for them to be recorded. The pool spends as much of
    a token budget as the barrier loop (which asks for an iteration's calls at once), and never more than it."""
    made = {}
    for pool in (False, True):
        model = scripted(SCRIPT)
        result = optimize(_config(pool=pool, candidates=3, iterations=4, repairs=0, max_total_tokens=40_000),
                          store, _client(model))
        used = store.query("SELECT sum(input_tokens + output_tokens), count(*) FROM llm_calls WHERE run_id = ?",
                           [result.run_id])[0]
        assert used[0] <= 40_000, "the budget holds"
        made[pool] = (result.status, result.error, used)
    assert made[True][2][1] >= made[False][2][1] >= 6, made
    assert made[True][0] == "finished", "12 calls of ~2,000 tokens fit in 40,000, though 4 worst cases do not"


@pytest.mark.parametrize("pool", [False, True])
def test_the_time_budget_stops_the_run_before_its_next_call(store, scripted, pool):
    """``--max-wall`` 0.001 min (60 ms) is spent by the starter's iteration: the barrier loop does not start an iteration
    (one as long as the last would pass it), the pool starts no call; the run ends ``budget``, saying why."""
    model = scripted(SCRIPT)
    result = optimize(_config(pool=pool, max_wall_minutes=0.001), store, _client(model))
    assert result.status == "budget" and "time budget" in result.error and "--max-wall 0.001 min" in result.error
    assert model.requests() == [] and _calls(store, result.run_id) == [], "no call was made"
    assert store.query("SELECT iteration FROM iterations WHERE run_id = ?", [result.run_id]) == [(0,)]


KILL_POINTS = {
    "early": lambda count, model: count("SELECT count(*) >= 3 AND (SELECT count(*) FROM iterations) <= 2 "
                                        "FROM llm_calls"),
    "mid-way": lambda count, model: len(model.raw_requests()) >= 10,
}
"""Where the run is killed: 3 calls recorded and iteration 1 perhaps not committed; or once the model has been asked
10 times (of at least 16: iteration 2's candidates or later asked, and iterations 1-3 committed or not, as the
latencies fell). The second reads the model's own request log, not the store: a read of the store waits for the
optimizer's writes (up to 1.6 s on a loaded machine), and a slow call of iteration 1 can hold its commit until 1, 2
and 3 commit within a tenth of a second — a window that a store poll misses."""


@pytest.mark.slow
@pytest.mark.parametrize("kill_at", sorted(KILL_POINTS))
def test_a_pool_run_killed_mid_way_resumes_and_replays_to_the_same_versions_and_scores(store, scripted, kill_at):
    model = scripted(SCRIPT)
    command = [EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
               "--strategy", "best-of-n", "--candidates", "4", "--iterations", "4", "--pool", "--eval-max-steps",
               "600", "--rollout-steps", "50", "--temperature", "1", "--audit-episodes", "0", "--rng-key", "pool",
               "--store", str(store.path), "--json"]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def count(sql):
        try:
            return store.query(sql)[0][0] if store.exists() else 0
        except Exception:  # noqa: BLE001 - tables not made yet
            return 0

    deadline = time.monotonic() + 300
    while not KILL_POINTS[kill_at](count, model):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.05)
    process.kill()
    process.wait()
    run_id = store.query("SELECT run_id FROM runs")[0][0]
    before = {(c[0], c[1], c[2]): c[3:] for c in _bases(store, run_id)}
    assert count("SELECT count(*) FROM iterations") < 5, "killed before the end"
    committed = [i for (i,) in store.query("SELECT iteration FROM iterations WHERE run_id = ?", [run_id])]
    # replayed as it was left: the iterations it committed replay alike (their candidates' calls are all
    # recorded), and the replay says where the record ends, which is no divergence (exit 0); the replay and the
    # resume run in this process, as the command line runs them (the killed run was a process of its own)
    early = run_main("replay", run_id, "--store", str(store.path), "--json")
    assert early.returncode == 0, early.stdout + early.stderr
    early = json.loads(early.stdout)
    rows = {row["iteration"]: row for row in early["iterations"]}
    assert all(rows[i]["matches"] for i in committed), early["iterations"]
    recorded = {(i, c) for i, c, turn in before if turn == 0}
    started = range(max(committed) + 1, max(max(committed) + 1, *(i for i, _ in recorded)) + 1)
    unrecorded = sum((i, c) not in recorded for i in started for c in range(4))
    # (the pool may have recorded every call of the iterations it had started: then the replay went on past them)
    assert early["status"] == ("incomplete" if unrecorded else "finished") and early["diverged_at"] is None, early
    assert early["record_ends"] == (f"the run stopped after iteration {max(committed)} (interrupted); {unrecorded} "
                                    f"call{'s' * (unrecorded != 1)} {'were' if unrecorded != 1 else 'was'} never "
                                    "recorded"), early
    assert store.query("SELECT status FROM runs WHERE run_id = ?", [early["replay_run_id"]]) == [
        ("interrupted" if unrecorded else "finished",)]
    done = run_main("optimize", "--resume", run_id, "--store", str(store.path), "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["status"] == "finished"
    counts = store.query("SELECT iteration, count(*) FROM candidates WHERE run_id = ? GROUP BY 1 ORDER BY 1", [run_id])
    assert counts == [(0, 1)] + [(i, 4) for i in range(1, 5)]
    after = _calls(store, run_id)
    # a candidate whose call was recorded before the kill was started again from the same basis (iterations and
    # pending candidates) and sent the same prompt: its reply was reused, never asked for twice
    assert len(after) == len({(c[0], c[1], c[2]) for c in after}), "one call per candidate and turn"
    again = {(c[0], c[1], c[2]): c[3:] for c in _bases(store, run_id)}
    assert all(again[key] == basis for key, basis in before.items()), (before, again)
    _check_bases(store, run_id, resumed=True)

    report = replay(store, run_id)
    assert report.status == "finished" and all(row.matches for row in report.rows), report.as_dict()["iterations"]
    assert _outcome(store, report.replay_run_id) == _outcome(store, run_id)


@pytest.mark.slow
def test_an_ensemble_in_the_pool_shares_its_calls_by_weight_and_replays_alike(store, scripted, monkeypatch):
    """Models are chosen as the pool starts candidates, in order, the calls in flight counting as chosen: 1:1
    weights give each model half the calls although most start before the iterations they follow are committed."""
    first, second = scripted(SCRIPT), scripted(SCRIPT)
    monkeypatch.setenv("OPENAI_API_KEY", "none")
    monkeypatch.setenv("LITELLM_LOCAL_MODEL_COST_MAP", "True")
    done = run_main(  # in this process, as the command line runs it
        "optimize", "--game", "pong", "--strategy", "best-of-n", "--candidates", "4", "--iterations", "3",
        "--pool", "--model", f"openai/gpt-4o,api_base={first.api_base}",
        "--model", f"openai/gpt-4o-mini,api_base={second.api_base}", "--model-choice", "fixed",
        "--eval-max-steps", "600", "--rollout-steps", "50", "--temperature", "1", "--audit-episodes", "0",
        "--rng-key", "pool", "--repairs", "0", "--store", str(store.path), "--json")
    assert done.returncode == 0, done.stderr
    run_id = json.loads(done.stdout)["run_id"]
    query = "SELECT iteration, candidate, request_model FROM llm_calls WHERE run_id = ? ORDER BY iteration, candidate"
    chosen = store.query(query, [run_id])
    models = [m for _, _, m in chosen]
    assert models.count("openai/gpt-4o") == models.count("openai/gpt-4o-mini") == 6, chosen
    assert len(first.requests()) == len(second.requests()) == 6
    report = replay(store, run_id)
    assert report.status == "finished" and all(row.matches for row in report.rows)
    assert store.query(query, [report.replay_run_id]) == chosen, "the replay chose the same model for every call"


@pytest.mark.slow  # a whole run against a wall-clock budget
@pytest.mark.parametrize("turn", ["first call", "repair turn"])
@pytest.mark.parametrize("pool", [False, True])
def test_a_call_in_flight_when_the_time_budget_runs_out_is_given_up_on(store, scripted, pool, turn):
    """``--max-wall`` stopped the loop only before a call: a model that answered after 300 s held the run 300 s
    past its time budget, an attempt at a time (up to 4 with retries), and repair turns were made past it. The
    call in flight, first or repair, is now given up on when the run's time runs out; it is recorded
    (``OutOfTime``) and the run ends ``budget``, saying why. The budget is set from the starter's own iteration,
    so that iteration 1 starts (the barrier loop's rule: one as long as the last would fit) however long this
    machine took to play it."""
    from pipeline.optimizer.loop import plan_resume
    from tests.test_repairs import RAISES

    late = {"sleep": 300, "content": "never read"}
    model = scripted([late] if turn == "first call" else [RAISES, late])  # a rejected reply, then its repair
    first = optimize(_config(pool=pool, iterations=0, candidates=2 if turn == "first call" else 1), store,
                     _client(model))
    assert first.status == "finished", first.error
    (wall,), = store.query("SELECT sum(wall_s) FROM iterations WHERE run_id = ?", [first.run_id])
    limit_s = 2 * wall + 6.0  # 6 s left for iteration 1 after a starter's iteration as long as iteration 0
    plan = plan_resume(store, first.run_id, {"iterations": 1, "max_wall_minutes": limit_s / 60})
    began = time.monotonic()
    result = optimize(plan.config, store, _client(model), resume=first.run_id)
    took = time.monotonic() - began
    assert result.status == "budget" and "ran out while the model was asked" in result.error, result.error
    assert model.raw_requests(), "iteration 1 asked the model"
    cut = store.query("SELECT error_type, repair_turn FROM llm_calls WHERE run_id = ? AND error_type IS NOT NULL",
                      [first.run_id])
    assert cut and {error for error, _ in cut} == {"OutOfTime"}, cut
    assert {repair for _, repair in cut} == ({0} if turn == "first call" else {1}), cut
    # the deadline is limit_s - wall after the resume began; the model's answer would have come after 300 s
    assert took < limit_s - wall + 60, (took, limit_s, wall)


HANGS_AT_STEP_400 = json.dumps({"reasoning": "scripted", "suggestion": {"select_action": (
    "def select_action(self, predicted_ball_y, obs):\n"
    "    self.calls = self.calls + 1 if hasattr(self, 'calls') else 1\n"
    "    while self.calls > 400:\n"
    "        pass\n"
    "    return 0\n")}})
"""A candidate that passes its checks (a few hundred recorded observations) and then hangs in its game."""


@pytest.mark.slow  # a whole run against a wall-clock budget
@pytest.mark.parametrize("pool", [False, True])
def test_games_still_playing_when_the_time_budget_runs_out_are_stopped(store, scripted, pool):
    """With no call limit (``--call-time-limit 0``), a candidate that hangs in a game held the run until the
    episode's own limit, 15 minutes, under a 1-minute ``--max-wall``. The games still playing when the time runs
    out are stopped, none of them scored or committed, and the run ends ``budget``, saying so."""
    from pipeline.optimizer.loop import plan_resume

    model = scripted([HANGS_AT_STEP_400])
    first = optimize(_config(pool=pool, iterations=0, candidates=1, call_time_limit_s=0.0), store, _client(model))
    assert first.status == "finished", first.error
    (wall,), = store.query("SELECT sum(wall_s) FROM iterations WHERE run_id = ?", [first.run_id])
    limit_s = 2 * wall + 8.0
    plan = plan_resume(store, first.run_id, {"iterations": 1, "max_wall_minutes": limit_s / 60})
    began = time.monotonic()
    result = optimize(plan.config, store, _client(model), resume=first.run_id)
    took = time.monotonic() - began
    assert result.status == "budget" and "games played" in result.error, (result.status, result.error)
    assert store.query("SELECT max(iteration) FROM iterations WHERE run_id = ?", [first.run_id]) == [(0,)]
    assert took < limit_s - wall + 60, (took, limit_s, wall)  # the episode's own limit is 900 s


def test_a_version_assessed_in_an_iteration_not_committed_yet_is_not_played_again(store, scripted):
    """The evaluation cache read only committed candidates: in the pool, a version a candidate of an iteration not
    committed yet had played (here every reply is the same code; often a rejected or unchanged candidate falling
    back to a parent still pending) was played again, its train rollout and evaluation games. Now each version's
    games are played once in the run, whichever candidates stand on them."""
    from tests.conftest import COMPETENT_REPLY

    slow = {"sleep": 3, "content": COMPETENT_REPLY}  # the first reply's games are played before the others arrive
    model = scripted([COMPETENT_REPLY, slow, slow, slow, COMPETENT_REPLY])
    result = optimize(_config(iterations=2, eval_max_steps=200, rollout_steps=30), store, _client(model))
    assert result.status == "finished", result.error
    rows = store.query("SELECT policy_version_id, list(DISTINCT train_episode_id), count(*), "
                       "list(DISTINCT evaluation) FROM candidates WHERE run_id = ? AND iteration > 0 GROUP BY 1",
                       [result.run_id])
    assert len(rows) == 1 and rows[0][2] == 8, rows  # one version: the reply's code, proposed or fallen back to
    version, trains, _, evaluations = rows[0]
    assert len(trains) == 1 and "cached" in evaluations, rows
    assert store.query("SELECT count(*) FROM episodes WHERE run_id = ? AND policy_version_id = ? AND kind = 'train'",
                       [result.run_id, version]) == [(1,)], "its training rollout was played once"
