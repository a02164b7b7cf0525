"""kill -9 at any point of `codearcade optimize`, then --resume; and `codearcade replay`."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time

import pytest

import pipeline.optimizer.prompt
from pipeline.optimizer.replay import replay
from tests.conftest import COMPETENT_REPLY, ROOT

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")


def _optimize(model, store, *extra, audit=1):
    # the held-out audit at the run's end: one game a version and protocol (its default, 3, played 12 games: a third
    # of a run), which _assert_complete checks the resumed run played once; none where no test looks at it
    return [EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
            "--iterations", "3", "--eval-max-steps", "1200", "--store", str(store.path), "--audit-episodes", str(audit),
            "--rng-key", "resume", *extra]  # every run's random starter draws the same: runs can be compared


def _start(model, store, *extra):
    return subprocess.Popen(_optimize(model, store, *extra), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def _wait_for(predicate, timeout=120.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError("timed out waiting")


def _count(store, sql, params=()):
    if not store.exists():
        return 0
    try:
        return store.query(sql, list(params))[0][0]
    except Exception:  # tables not created yet
        return 0


def _run_id(store):
    return store.query("SELECT run_id FROM runs")[0][0]


def _resume(store, run_id, model):
    done = subprocess.run([EXE, "optimize", "--resume", run_id, "--store", str(store.path), "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    return done


def _assert_complete(store, iterations=3):
    rows = store.query("SELECT iteration, count(*) FROM iterations GROUP BY iteration ORDER BY iteration")
    assert rows == [(i, 1) for i in range(iterations + 1)], rows
    assert store.query("SELECT status FROM runs")[0][0] == "finished"
    # every episode of every iteration exactly once, with all its steps (a version assessed before reuses its
    # episodes: the evaluation cache)
    referenced = store.query("SELECT count(DISTINCT e) FROM (SELECT unnest(list_append(eval_episode_ids, "
                             "train_episode_id)) AS e FROM candidates)")[0][0]
    assert store.query("SELECT count(*), count(DISTINCT episode_id) FROM episodes WHERE kind <> 'audit'")[0] == \
        (referenced, referenced)
    assert referenced >= 4
    # and the held-out audit of the finished run, once: its rows and episodes
    audited = store.query("SELECT count(*), sum(len(episode_ids)) FROM audits")[0]
    assert audited[0] in (2, 4) and store.query("SELECT count(*) FROM episodes WHERE kind = 'audit'")[0][0] == \
        store.query("SELECT count(DISTINCT e) FROM (SELECT unnest(episode_ids) AS e FROM audits)")[0][0]
    assert store.query("SELECT count(*) FROM (SELECT episode_id, step FROM steps GROUP BY ALL HAVING count(*) > 1)")[0][0] == 0
    lengths = store.query("SELECT e.length, count(s.step) FROM episodes e JOIN steps s USING (episode_id) GROUP BY e.episode_id, e.length")
    assert all(a == b for a, b in lengths)


@pytest.mark.slow
def test_kill_during_llm_call_then_resume(store, scripted):
    model = scripted([COMPETENT_REPLY, {"sleep": 60, "content": COMPETENT_REPLY}, COMPETENT_REPLY])
    process = _start(model, store)
    _wait_for(lambda: len(model.requests()) == 2)  # iteration 2's call is hanging
    process.kill()
    process.wait()
    run_id = _run_id(store)
    assert _count(store, "SELECT max(iteration) FROM iterations") == 1
    done = _resume(store, run_id, model)
    assert done.returncode == 0, done.stderr
    _assert_complete(store)
    assert json.loads(done.stdout)["status"] == "finished"


KILL_WINDOWS = {
    # where the run is killed: (the script, the extra flags, when to kill, what the replay says)
    # a starter whose evaluation games last (4,000 steps each, two of them): the window from its training rollout's
    # write to iteration 0's commit is seconds long. The scaffold loses in ~800 steps; once litellm was imported
    # before the run was made (the prompt's budget checked first), that window was ~0.3 s, and the store's polls,
    # waiting on the run's writes, missed it every time
    "during iteration 0": ([COMPETENT_REPLY], (str(ROOT / "tests" / "policies" / "pong_competent.py"), "--workers",
                                               "1", "--eval-max-steps", "4000", "--eval-episodes", "2"),
                           lambda store, model: _count(store, "SELECT count(*) FROM episodes") >= 1
                           and _count(store, "SELECT count(*) FROM iterations") == 0,
                           "the run stopped during iteration 0 (interrupted); 1 call was never recorded"),
    "after iteration 1's reply": ([COMPETENT_REPLY], ("--workers", "1", "--eval-max-steps", "4000"),
                                  lambda store, model: _count(store, "SELECT count(*) FROM episodes WHERE iteration = 1 "
                                                                     "AND kind = 'train'") == 1
                                  and _count(store, "SELECT count(*) FROM iterations WHERE iteration = 1") == 0,
                                  "the run stopped after iteration 0 (interrupted); 1 call was never recorded"),
    "during iteration 2's call": ([COMPETENT_REPLY, {"sleep": 60, "content": COMPETENT_REPLY}], (),
                                  lambda store, model: len(model.requests()) == 2,
                                  "the run stopped after iteration 1 (interrupted); 1 call was never recorded"),
}


@pytest.mark.slow
@pytest.mark.parametrize("window", KILL_WINDOWS)
def test_replay_of_a_killed_run_says_where_its_record_ends(store, scripted, window):
    """A run killed and never resumed: its replay reproduces what it committed, then meets the call that was never
    recorded. That is where the record ends, not a divergence: exit 0, and it says so; the replay run is stored as
    interrupted, like its original. Before iteration 0's commit there is nothing to compare (it said "first
    divergence at iteration 0"); after a reply whose iteration was never committed, the next iteration's call is
    the one never made (it said "0 calls were never recorded")."""
    script, extra, ready, says = KILL_WINDOWS[window]
    model = scripted(script)
    process = _start(model, store, *extra)
    _wait_for(lambda: ready(store, model))
    process.kill()
    process.wait()
    run_id = _run_id(store)
    asked = len(model.requests())
    done = subprocess.run([EXE, "replay", run_id, "--store", str(store.path)], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"{says}: replayed up to there, nothing diverged" in done.stdout, done.stdout
    assert ": incomplete" in done.stdout and "divergence" not in done.stdout, done.stdout
    assert len(model.requests()) == asked, "a replay never calls the model"
    assert store.query("SELECT status FROM runs WHERE kind = 'replay'") == [("interrupted",)]


@pytest.mark.slow
def test_kill_during_evaluation_reuses_the_stored_reply(store, scripted):
    model = scripted([COMPETENT_REPLY])
    # One worker and whole games: the evaluation starts after the training rollout is written and plays for
    # seconds, a window the poll below cannot miss (with two workers it was a few hundred milliseconds).
    process = _start(model, store, "--workers", "1", "--eval-max-steps", "4000")
    _wait_for(lambda: _count(store, "SELECT count(*) FROM episodes WHERE iteration = 1 AND kind = 'train'") == 1
              and _count(store, "SELECT count(*) FROM iterations WHERE iteration = 1") == 0)
    process.kill()
    process.wait()
    requests_before = len(model.requests())
    assert requests_before == 1
    done = _resume(store, _run_id(store), model)
    assert done.returncode == 0, done.stderr
    _assert_complete(store)
    assert len(model.requests()) == 3, "iteration 1's reply came from the store; only iterations 2 and 3 called"
    assert _count(store, "SELECT count(*) FROM llm_calls WHERE iteration = 1") == 1


@pytest.mark.slow
def test_random_kills_end_like_an_uninterrupted_run(store, scripted, tmp_path):
    from store import Store

    model = scripted([COMPETENT_REPLY])
    reference = Store(tmp_path / "reference.duckdb")
    done = subprocess.run(_optimize(model, reference, audit=0), cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    expected = reference.query("SELECT iteration, policy_version_id, score FROM iterations ORDER BY iteration")

    rng = random.Random(7)
    process = _start(model, store)
    _wait_for(lambda: _count(store, "SELECT count(*) FROM runs") == 1)
    time.sleep(rng.uniform(0.5, 3.0))
    process.send_signal(signal.SIGKILL)
    process.wait()
    run_id = _run_id(store)
    for _ in range(2):
        resumed = subprocess.Popen([EXE, "optimize", "--resume", run_id, "--store", str(store.path)], cwd=ROOT,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(0.5, 3.0))
        resumed.kill()
        resumed.wait()
    done = _resume(store, run_id, model)
    assert done.returncode == 0, done.stderr
    _assert_complete(store)
    assert store.query("SELECT iteration, policy_version_id, score FROM iterations ORDER BY iteration") == expected


@pytest.mark.slow
def test_replay_matches_then_reports_divergence(store, scripted, monkeypatch):
    model = scripted([COMPETENT_REPLY, "no code here", COMPETENT_REPLY])
    done = subprocess.run(_optimize(model, store, audit=0), cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    run_id = _run_id(store)
    calls_before = len(model.requests())

    report = replay(store, run_id)
    assert report.status == "finished" and report.diverged_at is None
    assert [r.iteration for r in report.rows] == [0, 1, 2, 3] and all(r.matches for r in report.rows)
    assert len(model.requests()) == calls_before, "a replay never calls the model"

    monkeypatch.setattr(pipeline.optimizer.prompt, "SYSTEM", pipeline.optimizer.prompt.SYSTEM + "\nBe brief.")  # the builder changed
    report = replay(store, run_id)
    assert report.status == "diverged" and report.diverged_at == 1
    assert store.query("SELECT count(*) FROM runs WHERE kind = 'replay'")[0][0] == 2
