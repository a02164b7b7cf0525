"""Scores that mean what they say (store/scores.py): a forfeit is never a run's best, intervals, differences.

The end-to-end tests run the real loop against a scripted model over real HTTP: its candidates are the competent
Pong policy made to fail at its 301st call (raise, spin past the call limit, or exhaust memory), so each had
scored more when it stopped than the starter does playing on — the case in which averaging partial returns
made a crash the run's best.
"""

from __future__ import annotations

import json

import pytest

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from store.scores import score_episodes
from store.statistics import ALL_EQUAL, IQM_MIN_PER_STRATUM, difference, interval_text, iqm, iqm_interval, mean_interval
from tests.conftest import COMPETENT_PREDICT, COMPETENT_SELECT, json_reply, run_main

FAIL_AT_301 = {
    "raise": "raise RuntimeError('boom at call 301')",
    "spin": "while True:\n                pass",
    "memory": "self.hoard = bytearray(6 * 2**30)\n            self.hoard[::4096] = b'x' * len(self.hoard[::4096])",
}


def failing_reply(how: str) -> str:
    """The competent policy, whose select_action fails at its 301st call (step 300) in the way ``how`` says."""
    select = COMPETENT_SELECT.replace(
        '    """Steer the paddle (where it will be next step) to the predicted y."""\n',
        '    """Steer the paddle (where it will be next step) to the predicted y."""\n'
        "    self.calls = getattr(self, 'calls', 0) + 1\n"
        "    if self.calls > 300:\n"
        f"        if True:\n            {FAIL_AT_301[how]}\n")
    return json_reply({"predict_ball_trajectory": COMPETENT_PREDICT, "select_action": select})


def _optimize(store, model, **settings):
    config = OptimizeConfig(**{**dict(game="pong", iterations=1, eval_max_steps=400, rollout_steps=50, workers=2,
                                      token_budget=8000, call_time_limit_s=0.5, rng_key="scores"), **settings})
    result = optimize(config, store, LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05))
    assert result.status == "finished", result.error
    return result


def test_the_rule():
    played = [{"return": -20.0, "end_reason": "terminated", "length": 800},
              {"return": -19.0, "end_reason": "truncated", "length": 4000}]
    forfeit = {"return": -7.0, "end_reason": "policy_error", "length": 300,
               "error": "RuntimeError: boom at line 4: `raise RuntimeError('boom')`"}
    clean = score_episodes(played)
    # two episodes a point apart: Student t with 1 degree of freedom, -19.5 ± 12.706 · 0.5
    assert clean.ranked == clean.mean == -19.5
    assert clean.low == pytest.approx(-19.5 - 6.353102) and clean.high == pytest.approx(-19.5 + 6.353102)
    assert clean.forfeit is None
    mixed = score_episodes(played + [forfeit])
    assert mixed.ranked is None, "a forfeited assessment has no score to rank"
    assert mixed.mean == -19.5 and mixed.partial == pytest.approx(-46 / 3), "forfeits are named, never averaged in"
    assert mixed.summary() == ("no score: 1 of 3 episodes forfeited (RuntimeError at step 300); the 2 played out "
                               "averaged -19.5, not a score"), "no score, and the played-out mean is labelled so"
    assert mixed.forfeit == "1 of 3 episodes forfeited: RuntimeError at step 300 (policy_error)"
    timeout = score_episodes([{"return": 3.0, "end_reason": "timeout", "length": 12, "error": "the call took 2 s"}])
    assert timeout.mean is None and timeout.summary() == "no score: 1 of 1 episode forfeited (timeout at step 12)"
    assert score_episodes([{"return": 5.0, "end_reason": "tampered", "length": 9}]).ranked is None
    # no interval where there is nothing to compute one from: said, never printed as [x, x]
    alone = score_episodes(played[:1])
    assert (alone.low, alone.high) == (None, None)
    assert alone.summary() == "mean return -20.0 (n=1: too few for an interval)"
    same = score_episodes([played[0]] * 3)
    assert (same.low, same.high) == (None, None) and same.mean == -20.0
    assert same.summary() == "mean return -20.0 (n=3: all equal, no interval)"
    assert same.interval.reason == ALL_EQUAL and same.interval.method == "t" and same.interval.n == 3


def test_every_interval_is_printed_with_its_level_method_and_n():
    assert interval_text(-20.6667, -21.0, -20.3333, 3, "t") == "-20.7 [-21.0, -20.3] 95% t, n=3"
    assert interval_text(0.4567, 0.1234, 0.789, 8, "stratified bootstrap") == (
        "0.457 [0.123, 0.789] 95% stratified bootstrap, n=8"), "normalized scores keep three decimals"
    assert interval_text(2.0, -1.0, 5.0, (3, 4), "Welch t", signed=True) == "+2.0 [-1.0, +5.0] 95% Welch t, n=3 and 4"
    assert interval_text(-21.0, None, None, 1, "t") == "-21.0 (n=1: too few for an interval)"
    assert interval_text(-21.0, None, None, 5, "t") == "-21.0 (n=5: all equal, no interval)"
    assert interval_text(3.0, 1.0, 5.0, 10, "t", level=0.9) == "3.0 [1.0, 5.0] 90% t, n=10"
    found = mean_interval([-21, -20, -21])
    assert found.text() == f"-20.7 [{found.low:.1f}, {found.high:.1f}] 95% t, n=3"
    assert found.low < -21 < -20 < found.high


def test_differences_and_aggregates():
    same = difference([3, 5, -2, 4, 1, 0], [2, 4, 1, -1, 5, 3])
    assert same.significant is False and same.low < 0 < same.high
    assert same.verdict() == ("A - B = -0.5 [-3.6, +2.6] 95% Welch t, n=6 and 6: no difference beyond the noise "
                              "(the interval includes 0)")
    apart = difference([14, 11, 17, 12, 9], [-21, -20, -21, -19, -21])
    assert apart.significant is True and apart.low > 20
    assert "beyond the noise (the interval excludes 0)" in apart.verdict()
    assert difference([1], [2, 3]).significant is None, "one episode cannot say how noisy it is"
    assert "too few episodes to tell" in difference([1], [2, 3]).verdict()
    # every return the same on both sides (the paper's protocol: one game, played again): no noise to measure, so
    # no call either way; one constant side is fine, the other's spread is the noise
    for flat in (difference([4, 4], [4, 4]), difference([4, 4], [3, 3])):
        assert flat.significant is None and flat.reason == ALL_EQUAL and "cannot tell" in flat.verdict()
    assert difference([4, 4, 4], [1, 1.5, 2]).significant is True
    # the interquartile mean of all values; its interval (each stratum resampled on its own) only from
    # IQM_MIN_PER_STRATUM values a stratum, where the bootstrap keeps its level (tests/test_calibration.py)
    assert iqm([[1, 2, 3, 4], [5, 6, 7, 100]]) == (pytest.approx(4.5), None, None)
    wide = [[float(i % 9) for i in range(IQM_MIN_PER_STRATUM)],
            [float(i % 4 + 50) for i in range(IQM_MIN_PER_STRATUM)]]
    point, low, high = iqm(wide)
    assert low < point < high
    assert iqm([[7], [7]]) == (7.0, None, None) and iqm_interval([[7], [7]]).reason == ALL_EQUAL


@pytest.mark.slow
def test_a_candidate_that_raises_at_step_300_is_never_the_best(store, scripted, tmp_path):
    model = scripted([failing_reply("raise")])
    result = _optimize(store, model)
    it0, it1 = result.iterations
    assert it1.update_status == "accepted" and it1.score is None
    assert it1.forfeit == "1 of 1 episode forfeited: RuntimeError at step 300 (policy_error)"
    assert it1.forfeit_score > it0.score, "it had lost fewer points when it stopped than the starter playing on"
    assert it1.best_iteration == 0 and it1.best_score == it0.score and it1.rolled_back
    [(score, best, best_iteration, forfeit, partial)] = store.query(
        "SELECT score, best_score, best_iteration, forfeit, forfeit_score FROM learning_curve WHERE iteration = 1")
    assert score is None and best == it0.score and best_iteration == 0 and "RuntimeError" in forfeit
    assert partial == it1.forfeit_score
    [(stage, text)] = store.query("SELECT stage, text FROM feedback WHERE iteration = 1")
    assert stage == "low" and "did not play the game to its end" in text and "RuntimeError at step 300" in text
    starter = store.query("SELECT policy_version_id FROM iterations WHERE iteration = 0")[0][0]
    ranks = dict(store.query("SELECT policy_version_id, rank FROM frontier"))
    assert ranks[starter] == 1 and len(ranks) == 2, "the version that played its game out ranks first"
    # every reader names the starter, which played its games out
    code, out, _ = run_main("runs", "--json", "--store", str(store.path))
    [row] = json.loads(out)
    assert code == 0 and row["best_score"] == it0.score and row["best_iteration"] == 0 and row["forfeits"] == 1
    code, out, _ = run_main("blame", "last", "--json", "--store", str(store.path))
    assert code == 0 and json.loads(out)["policy_version_id"] == starter
    code, out, _ = run_main("report", "last", "--out", str(tmp_path / "report"), "--store", str(store.path))
    readme = (tmp_path / "report" / "README.md").read_text()
    assert code == 0 and f"{it0.score:g}" in readme and "forfeit" in readme.lower()


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["best-of-n"])
def test_no_way_of_failing_at_step_300_wins_a_population(store, scripted, strategy):
    model = scripted([failing_reply("raise"), failing_reply("spin"), failing_reply("memory")])
    result = _optimize(store, model, strategy=strategy, candidates=3)
    it0, it1 = result.iterations
    assert it1.best_iteration == 0 and it1.best_score == it0.score
    rows = store.query("SELECT score, forfeit, forfeit_score, decision FROM candidates WHERE iteration = 1 "
                       "ORDER BY candidate")
    assert len(rows) == 3 and all(score is None and decision != "best" for score, _, _, decision in rows)
    endings = sorted(r[1].rsplit("(", 1)[1].rstrip(")") for r in rows)
    assert endings == sorted(["policy_error", "timeout", "policy_error" if "MemoryError" in str(rows) else "crashed"])
    assert any("MemoryError" in r[1] or "crashed" in r[1] for r in rows), rows
    assert all(r[2] > it0.score for r in rows if "step 300" in r[1]), "each had scored more when it stopped"


PEEK_POLICY = '''
import random
import numpy as np
import tracing as trace

GAME = "pong"

@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        self.peek()
        return 0

    @trace.bundle(trainable=True)
    def peek(self):
        if getattr(self, "seen", False):
            return None
        self.seen = True
        return [random.getrandbits(62), int(np.random.get_state()[1][0]), float(np.random.random())]
'''


def test_a_policy_cannot_read_the_game_seed_from_its_own_generators(store, write_policy):
    """Its generators are seeded from the run's key and the game's seed (runinfo.policy_rng_seed), not with the
    seed: what they give says nothing of the seed, differs between seeds, and between runs of the same seeds."""
    import random

    import numpy as np

    policy = write_policy(PEEK_POLICY)

    def draws(seed: int) -> dict[int, list]:
        code, _, _ = run_main("eval", policy, "--episodes", "2", "--seed", seed, "--max-steps", "3", "--trace",
                              "--store", store.path)
        assert code == 0
        rows = store.query("SELECT e.seed, n.output FROM nodes n JOIN episodes e USING (episode_id) "
                           "WHERE e.run_id = (SELECT run_id FROM runs ORDER BY created_at DESC LIMIT 1) "
                           "AND n.step = 0")
        return {s: json.loads(out) for s, out in rows}

    first, again = draws(0), draws(0)
    assert sorted(first) == [0, 1]
    for seed, (bits, state, value) in first.items():
        legacy = np.random.RandomState(seed)  # what a policy seeded with the game's seed would draw
        assert bits != random.Random(seed).getrandbits(62) and state != seed and value != legacy.random_sample()
    assert first[0] != first[1], "each game's stream is its own"
    assert first[0] != again[0] and first[1] != again[1], "the stream is keyed by the run: no table carries over"


@pytest.mark.parametrize("value, shown", [(200 / 3, "66.67"), (-62 / 3, "-20.67"), (3.0, "3"), (-21, "-21"),
                                          (0.125, "0.12"), (1 / 3, "0.33"), (-0.004, "0"), (1234.5, "1234.5")])
def test_a_score_prints_with_at_most_two_decimals(value, shown):
    """One number format for scores wherever a line shows them (runs, optimize's iteration lines, batch, the
    report's figure, the Rerun run view): never 66.6667 beside -20.67."""
    from store.scores import score_text

    assert score_text(value) == shown
