"""``codearcade compare RUN_A RUN_B`` never prints a selection-biased "beyond the noise".

Each run's best is its highest-scoring version, picked on the very episodes that scored it, so a test of the two
bests on those episodes calls identical policies different far more often than its 5%. The simulation here draws
returns shaped like Atari's (``tests/test_calibration.py``'s exact tables), lets run A pick the best of 20
identical versions on ``n`` episodes each as the loop does (a version takes the best only by scoring above it)
against run B's starter, gives each best ``n`` held-out games from the same distribution, and asks the verdict
function compare uses (``pipeline.optimizer.runs.best_difference``, pure: numbers in, verdict out) for the text
it prints. "beyond the noise" may appear at most 5% of the time, plus Monte-Carlo slack; the simulation must
also show the bias on the tuning episodes (the verdict compare printed before, ``difference_data`` of those
episodes), so a return to it would fail here. One end-to-end test makes two real runs in a real store.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.test_calibration import SHAPES, draw

SIMULATIONS = 1000
"""Simulated pairs of runs per case: the standard error of a 5% rate is 0.69%."""
SLACK = 3 * math.sqrt(0.05 * 0.95 / SIMULATIONS)
"""Monte-Carlo slack on the 5% a 95% test may err: three standard errors (2.1 points)."""
UNAUDITED = 200
"""Of those, the pairs also asked without one or both held-out scores (no verdict at all: a few suffice)."""
VERSIONS = 20
"""Versions run A tries (its starter and 19 candidates), all the same policy."""
BEYOND = "a difference beyond the noise"


def scored(returns) -> object:
    from store.scores import score_episodes

    return score_episodes({"return": float(r), "end_reason": "terminated", "length": 100} for r in returns)


def picked_best(returns: np.ndarray) -> np.ndarray:
    """The episodes of the version the loop keeps from versions tried in order (rows): the first to score highest
    (a later one takes the best only by scoring above it, ``store.scores.beats``)."""
    return returns[int(np.argmax(returns.mean(axis=1)))]


def simulate(shape: str, n: int, shift: float = 0.0, seed: int = 0, runs: int = SIMULATIONS) -> dict[str, float]:
    """How often each verdict says "beyond the noise" over ``runs`` pairs of runs: A's best of :data:`VERSIONS`
    against B's starter, ``n`` episodes a version and ``n`` held-out games a best; ``shift`` moves A's true returns
    (0: the same policy). ``before``: Welch's t of the tuning episodes, what compare printed before (its verdict
    called "beyond the noise" exactly when this interval left out 0), for all the pairs at once."""
    from pipeline.optimizer.runs import best_difference
    from store.statistics import difference_bounds

    tuning_a = draw(SHAPES[shape], (runs, VERSIONS, n), (seed, 1)) + shift
    tuning_b = draw(SHAPES[shape], (runs, n), (seed, 2))
    held_a = draw(SHAPES[shape], (runs, n), (seed, 3)) + shift
    held_b = draw(SHAPES[shape], (runs, n), (seed, 4))
    best_a = np.stack([picked_best(versions) for versions in tuning_a])
    low, high = difference_bounds(best_a, tuning_b)
    rates = {"before": float(np.mean((low > 0) | (high < 0)))}
    counts = {"unaudited": 0, "one_audited": 0, "audited": 0}
    for i in range(runs):
        tuning = (scored(best_a[i]), scored(tuning_b[i]))
        held = (scored(held_a[i]), scored(held_b[i]))
        asked = [("audited", held)] + ([("unaudited", (None, None)), ("one_audited", (held[0], None))]
                                       if i < UNAUDITED else [])
        for name, sides in asked:
            verdict = best_difference("pong", tuning, sides)["verdict"]
            counts[name] += BEYOND in verdict and "no difference beyond the noise" not in verdict
    return {**rates, "audited": counts["audited"] / runs, "unaudited": counts["unaudited"] / min(runs, UNAUDITED),
            "one_audited": counts["one_audited"] / min(runs, UNAUDITED)}


@pytest.mark.slow
@pytest.mark.parametrize("shape,n", [("pong", 3), ("bimodal", 5), ("ties", 10)])
def test_identical_policies_are_called_different_at_most_five_percent_of_the_time(shape, n):
    rates = simulate(shape, n)
    # the simulation has the bias: the tuning episodes that picked A's best call the same policy different
    # (measured: pong n=3 9.8%, bimodal n=5 19.9%, ties n=10 19.8%; held out: 2.8%, 3.7%, 5.1%)
    assert rates["before"] > 0.05 + SLACK, rates
    # without both held-out scores there is no verdict; with them, the verdict is a 5% test's
    assert rates["unaudited"] == 0 and rates["one_audited"] == 0, rates
    assert rates["audited"] <= 0.05 + SLACK, rates


def test_a_real_difference_is_still_found_on_held_out_games():
    """Not a test that says nothing: A better by about two and a half standard deviations of a game is called so
    on its 6 held-out games most of the time."""
    rates = simulate("bimodal", 6, shift=20.0, seed=7, runs=200)
    assert rates["audited"] > 0.8, rates


def test_the_verdict_says_what_it_rests_on_and_keeps_the_tuning_figures():
    from pipeline.optimizer.runs import best_difference

    tuning = (scored([10, 11, 12]), scored([0, 1, 2]))
    held = (scored([5, 4, 6]), scored([5, 6, 4]))
    found = best_difference("pong", tuning, (None, held[1]))
    assert found["basis"] == "tuning" and found["significant"] is None and found["to_audit"] == ["A"]
    assert found["delta"] == 10 and found["low"] is not None, "the figures are still given"
    assert found["verdict"].startswith("A - B = +10.0 [") and "not tested: each best was picked" in found["verdict"]
    assert "`codearcade audit` of run A scores its best" in found["verdict"] and BEYOND not in found["verdict"]
    found = best_difference("pong", tuning, held)
    assert found["basis"] == "held_out" and found["significant"] is False and found["to_audit"] == []
    assert found["verdict"].endswith("no difference beyond the noise (the interval includes 0)")
    assert found["tuning"]["delta"] == 10 and found["tuning"]["interval"].startswith("+10.0 [")
    json.dumps(found)  # plain data, as --json prints it


# ------------------------------------------------------------------------------------------ end to end


@pytest.mark.slow
def test_compare_of_two_real_runs_gives_its_verdict_on_their_held_out_games(tmp_path, capsys):
    """Two optimization runs without LLM updates, from the competent Pong policy and from the scaffold, scored
    under the standard protocol on 3 games: their tuning episodes differ by ~18 points, which compare called "a
    difference beyond the noise" though each best was picked on them. Unaudited, it is not tested, and the audit
    commands are named; audited, the verdict is the held-out games', with the tuning figures beside."""
    from pipeline.cli import main
    from pipeline.llm.client import LiteLLMClient
    from pipeline.optimizer.audit import audit_run
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.loop import optimize
    from store import Store
    from tests.conftest import EXAMPLES, POLICIES

    store = Store(tmp_path / "s.duckdb", lock_timeout_s=20)
    ids = []
    for policy in (POLICIES / "pong_competent.py", EXAMPLES / "pong.py"):
        config = OptimizeConfig(game="pong", policy=str(policy), iterations=0, rollout_steps=50, eval_max_steps=600,
                                robust_episodes=3, optimize_protocol="standard", audit_episodes=0, seed=16, workers=2,
                                rng_key="selection")
        result = optimize(config, store, LiteLLMClient("openai/unused", api_base="http://127.0.0.1:9"))
        assert result.status == "finished", result.error
        ids.append(result.run_id)

    def compare(*extra):
        code = main(["compare", *ids, "--out", str(tmp_path / "cmp"), "--store", str(store.path), *extra])
        out, err = capsys.readouterr()
        assert code == 0, err
        return out

    data = json.loads(compare("--json"))
    found = data["difference"]
    assert found["low"] > 0, f"the tuning episodes part beyond their interval: {found}"
    assert BEYOND not in found["verdict"] and "not tested" in found["verdict"], found["verdict"]
    assert found["basis"] == "tuning" and found["significant"] is None and found["to_audit"] == ["A", "B"]
    assert found["tuning"]["low"] == found["low"], "the figures are the tuning episodes'"
    assert found["audit_commands"] == [f"codearcade audit {i} --store {store.path}" for i in ids]
    assert [r["held_out"] for r in data["runs"]] == [None, None]
    text = compare()
    assert BEYOND not in text and "not tested: each best was picked" in text and "`codearcade audit " in text
    assert BEYOND not in (tmp_path / "cmp" / "README.md").read_text()
    for run_id in ids:
        audit_run(store, run_id, workers=2, seeds=list(range(1_000_000, 1_000_005)))
    data = json.loads(compare("--json"))
    found = data["difference"]
    assert found["basis"] == "held_out" and found["to_audit"] == [] and found["audit_commands"] == []
    assert found["significant"] is True and found["verdict"].endswith(f"{BEYOND} (the interval excludes 0)"), found
    assert found["tuning"]["interval"] and found["tuning"]["note"].startswith("not a test")
    held = [store.query("SELECT score FROM audits WHERE run_id = ? AND role = 'best' AND protocol = 'standard'",
                        [i])[0][0] for i in ids]
    assert [r["held_out"]["mean"] for r in data["runs"]] == pytest.approx(held)
    assert found["delta"] == pytest.approx(held[0] - held[1])
    text = compare()
    assert "best versions, held out (the standard protocol on their sealed audit games, 5 and 5)" in text
    assert "on the tuning episodes that picked them (3 and 3)" in text
    # an audit of an earlier best is not the best's held-out score: no verdict
    with store.write() as con:
        con.execute("UPDATE audits SET policy_version_id = 'elsewhere', iteration = 7 WHERE run_id = ?", [ids[1]])
    data = json.loads(compare("--json"))
    assert data["difference"]["basis"] == "tuning" and data["difference"]["to_audit"] == ["B"]
    assert data["runs"][1]["held_out_missing"] == "its audit played an earlier best (iteration 7)"
