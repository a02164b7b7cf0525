"""kill -9 at random points of an optimize run, again and again, each followed by --resume.

By default four kills, the three after the first at times drawn from three strata of the first nine seconds of a
resume (start-up and litellm's import, the first call, evaluation), so a short loop still spreads its kills over
the whole span; ``pytest --soak tests/faults/test_kill_loop.py`` makes it the full twenty (about 2-3 minutes).

At the end the store passes `codearcade doctor`, every iteration exists exactly once, and the run's results
(versions and scores per iteration) equal those of an uninterrupted run with the same scripted model.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import time

import pytest

from store import Store
from tests.conftest import COMPETENT_REPLY, ROOT

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
KILLS = 4
SOAK_KILLS = 20
SEED = 20261124


def _command(model, store, *extra):
    return [EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
            "--iterations", "3", "--eval-max-steps", "400", "--rollout-steps", "120", "--token-budget", "6000",
            "--store", str(store.path), "--rng-key", "kills", *extra]  # both runs' random starter draws alike


def _results(store):
    return store.query("SELECT iteration, policy_version_id, update_status, score FROM iterations ORDER BY iteration")


@pytest.mark.slow
def test_kills_lose_nothing(tmp_path, scripted, soak):
    # one reply for every call: what an iteration gets cannot depend on how often calls were cut off
    model = scripted([COMPETENT_REPLY])
    reference = Store(tmp_path / "reference.duckdb")
    done = subprocess.run(_command(model, reference), cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    expected = _results(reference)

    store = Store(tmp_path / "killed.duckdb")
    rng = random.Random(SEED)
    first = subprocess.Popen(_command(model, store), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not store.exists():
        time.sleep(0.05)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if store.query("SELECT count(*) FROM runs")[0][0]:
                break
        except Exception:
            pass
        time.sleep(0.05)
    first.kill()
    first.wait()
    run_id = store.query("SELECT run_id FROM runs")[0][0]

    wanted = SOAK_KILLS if soak else KILLS
    # litellm's import alone takes seconds: kill anywhere between start-up and a few iterations' work, one kill
    # in each stratum of that span (in a random order)
    edges = [0.2 + (9.0 - 0.2) * i / (wanted - 1) for i in range(wanted)]
    delays = [rng.uniform(low, high) for low, high in zip(edges, edges[1:])]
    rng.shuffle(delays)
    kills, finished_early = 1, False
    while kills < wanted:
        process = subprocess.Popen([EXE, "optimize", "--resume", run_id, "--store", str(store.path)], cwd=ROOT,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        time.sleep(delays[kills - 1])
        if process.poll() is not None:  # it finished before the kill: nothing left to interrupt
            finished_early = True
            break
        process.kill()
        process.wait()
        kills += 1
    done = subprocess.run([EXE, "optimize", "--resume", run_id, "--store", str(store.path), "--json"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["status"] == "finished"
    assert kills >= wanted or finished_early

    doctor = subprocess.run([EXE, "doctor", "--store", str(store.path), "--json"], cwd=ROOT, capture_output=True,
                            text=True, timeout=120)
    report = json.loads(doctor.stdout)
    assert doctor.returncode == 0 and report["ok"], report["findings"]
    assert _results(store) == expected, "the killed run ended exactly like the uninterrupted one"
    assert store.query("SELECT count(*) FROM iterations") == [(4,)]
    # no LLM call was paid twice for one iteration: a stored reply is reused on resume
    assert store.query("SELECT iteration, count(*) FROM llm_calls WHERE error_type IS NULL GROUP BY iteration "
                       "HAVING count(*) > 1") == []
    print(f"kills survived: {kills}; rows lost: 0")
