"""``codearcade compare``: two policy versions played on the same seeds, and two optimization runs.

Real components: episodes played by the worker processes into a real DuckDB file, optimization runs against
the scripted model over real HTTP, the side-by-side recording written by Rerun and read back with its SDK in
a separate process (tests/rrd_dump.py; this process forks episode workers and never loads Rerun).
"""

from __future__ import annotations

import json
import re

import pytest

from tests.conftest import COMPETENT_REPLY, EXAMPLES, POLICIES, ROOT, run_main
from tests.test_rerun import column, dump

COMPETENT = POLICIES / "pong_competent.py"
STEPS = 300


@pytest.fixture
def wider_dead_zone(tmp_path):
    """The competent Pong policy with one constant changed (DEAD_ZONE 3 -> 4)."""
    text = COMPETENT.read_text()
    assert text.count("DEAD_ZONE = 3\n") == 1
    path = tmp_path / "pong_dead_zone_4.py"
    path.write_text(text.replace("DEAD_ZONE = 3\n", "DEAD_ZONE = 4\n"))
    return path


def stored_actions(store, run_id: str) -> list:
    rows = store.query("SELECT s.action FROM steps s JOIN episodes e USING (episode_id) WHERE e.run_id = ? "
                       "AND e.kind = 'eval' ORDER BY s.step", [run_id])
    return [r[0] for r in rows]


@pytest.mark.slow
def test_two_versions_report_the_first_divergent_step(store, tmp_path, wider_dead_zone):
    rrd = tmp_path / "side_by_side.rrd"
    code, out, err = run_main("compare", COMPETENT, wider_dead_zone, "--max-steps", STEPS, "--rerun", rrd,
                              "--store", store.path, "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["mode"] == "versions" and report["game"] == "pong"
    runs = [v["eval_run"] for v in report["versions"]]
    # independently: the first step where the two stored action sequences differ
    a, b = stored_actions(store, runs[0]), stored_actions(store, runs[1])
    assert len(a) == len(b) == STEPS
    expected = next(i for i, (x, y) in enumerate(zip(a, b)) if x != y)
    (episode,) = report["episodes"]
    assert episode["first_divergent_step"] == expected
    assert episode["actions"] == {"A": a[expected], "B": b[expected]}
    # the steps around it, each side with its observation and what its bundled methods returned
    around = {e["step"]: e for e in episode["around"]}
    assert sorted(around) == list(range(max(0, expected - 3), expected + 4))
    for step, entry in around.items():
        for label, actions in (("A", a), ("B", b)):
            side = entry[label]
            assert side["action"] == actions[step]
            # named as ALE names it, with what it does on screen where that differs: Pong's paddle moves vertically
            assert side["action_name"] == {0: "NOOP", 1: "FIRE", 2: "RIGHT (up)", 3: "LEFT (down)"}[actions[step]]
            assert side["nodes"]["select_action"] == actions[step], "the node output is the action played"
            assert "predict_ball_trajectory" in side["nodes"] and "Player" in side["obs"]
    assert around[expected - 1]["A"]["obs"] == around[expected - 1]["B"]["obs"], "the same game until they part"
    assert "-DEAD_ZONE = 3" in report["diff"] and "+DEAD_ZONE = 4" in report["diff"]
    assert report["diff"].count("\n-") == 1, "one line differs"

    # the side-by-side recording: both episodes on one step timeline, the divergence at its step
    content = dump(rrd)[str(rrd)]
    for side, run_id in zip("AB", runs):
        actions = column(content, f"/{side}/series/action:Scalars:scalars")
        assert [actions[s][0] for s in range(STEPS)] == [float(x) for x in stored_actions(store, run_id)]
        assert sorted(column(content, f"/{side}/game/frame:EncodedImage:blob")) == list(range(0, STEPS, 4))
        assert content["properties"][f"{side}_episode:run_id"] == run_id
    divergence = column(content, "/compare/divergence:TextLog:text")
    assert list(divergence) == [expected] and f"first divergent step {expected}" in divergence[expected][0]
    assert "+DEAD_ZONE = 4" in content["static"]["/compare/diff:TextDocument:text"][0]

    # the same versions, read back from the store as RUN:VERSION (a prefix, and 'best'), part at the same step
    version_b = report["versions"][1]["policy_version_id"]
    code, out, err = run_main("compare", f"{runs[0][:20]}:best", f"{runs[1]}:{version_b[:6]}", "--max-steps",
                              STEPS, "--store", store.path, "--out", tmp_path / "report")
    assert code == 0, err
    assert f"first divergent step: {expected} " in out
    readme = (tmp_path / "report" / "README.md").read_text()
    assert f"first divergent step: {expected} " in readme and "+DEAD_ZONE = 4" in readme


def test_identical_versions_never_diverge(store):
    code, out, err = run_main("compare", COMPETENT, COMPETENT, "--max-steps", 50, "--store", store.path)
    assert code == 0, err
    # off a terminal, each side's episodes say when they start and end (stderr), never a silent wait
    for side in "AB":
        assert f"compare {side}: 1 episode to play" in err and f"compare {side}: 1 of 1 episodes played" in err, err
    assert "the two versions chose the same action at every step" in out and "(the same code)" in out
    # its two eval runs are compare's own: marked so, left out of `runs` and of last
    assert store.query("SELECT kind, made_by FROM runs") == [("eval", "compare")] * 2
    code, out, err = run_main("runs", "--store", store.path)
    assert code == 0 and out.startswith("no runs in")
    code, out, err = run_main("runs", "--all", "--json", "--store", store.path)
    assert [r["made_by"] for r in json.loads(out)] == ["compare", "compare"]
    code, out, err = run_main("report", "last", "--store", store.path)
    assert code == 2 and "there are no runs yet" in err


@pytest.mark.slow
def test_two_runs_curves_budget_table_and_diff(store, tmp_path, scripted):
    ids = []
    for replies in ([COMPETENT_REPLY, "Sorry, I cannot help with that."], ["Sorry.", "Still no."]):
        model = scripted(replies)
        code, out, err = run_main("optimize", "--game", "pong", "--model", model.model, "--api-base",
                                  model.api_base, "--iterations", 2, "--eval-max-steps", 800, "--rollout-steps", 40,
                                  "--workers", 2, "--repairs", 0, "--rng-key", "cmp", "--store", store.path,
                                  "--json")
        assert code == 0, err
        ids.append(json.loads(out)["run_id"])
    code, out, err = run_main("compare", ids[0][:22], ids[1], "--out", tmp_path / "cmp", "--store",
                              store.path, "--json")
    assert code == 0, err
    report = json.loads(out)
    assert [r["run_id"] for r in report["runs"]] == ids

    def best_within_calls(run_id: str, calls: int) -> float:
        """Straight from the tables: the best score among iterations reached with at most ``calls`` LLM calls."""
        return store.query(
            "SELECT max(score) FROM (SELECT i.iteration, i.score, (SELECT count(*) FROM llm_calls c WHERE "
            "c.run_id = i.run_id AND c.iteration <= i.iteration) AS calls FROM iterations i WHERE i.run_id = ?) "
            "WHERE calls <= ?", [run_id, calls])[0][0]

    by_calls = {r["budget"]: r for r in report["budgets"] if r["unit"] == "LLM calls"}
    assert sorted(k for k in by_calls if k != "all") == [0, 1, 2]
    for calls in (0, 1, 2):
        assert by_calls[calls]["A"] == best_within_calls(ids[0], calls)
        assert by_calls[calls]["B"] == best_within_calls(ids[1], calls)
    assert by_calls[1]["A"] > by_calls[1]["B"], "A's first reply was the competent policy, B's was useless"
    assert {r["unit"] for r in report["budgets"]} == {"LLM calls", "1k tokens", "wall seconds"}
    tokens = [r for r in report["budgets"] if r["unit"] == "1k tokens" and r["budget"] != "all"]
    spent = [store.query("SELECT sum(input_tokens + output_tokens) FROM llm_calls WHERE run_id = ?", [i])[0][0]
             for i in ids]
    assert tokens[-1]["budget"] == pytest.approx(min(spent) / 1000, abs=1e-3), "matched up to what both spent"
    # the learning curves are the stored iterations; the diff is starter (B's best) against the competent code
    for label, run_id in zip("AB", ids):
        scores = [r[0] for r in store.query("SELECT score FROM iterations WHERE run_id = ? ORDER BY iteration",
                                            [run_id])]
        assert [p["score"] for p in report["curves"][label]] == scores
    assert report["runs"][0]["best_iteration"] == 1 and report["runs"][1]["best_iteration"] == 0
    assert re.search(r"^-.*offset = \(y - 30\) % 320", report["diff"], re.M), "A's best has the competent code"
    # each best with its interval (store/scores.py's, of the episodes that scored it: the candidate's own), and
    # whether the bests differ beyond the noise: on their held-out audit games (each run was audited as it
    # finished), the tuning figures beside (each best was picked on those episodes: tests/test_compare_selection.py)
    from store.statistics import difference
    from viewers.safe_text import markdown_text

    episodes = dict(store.query("SELECT episode_id, return FROM episodes"))
    returns, held = [], []
    for run in report["runs"]:
        (low, high, ids_), = store.query(
            "SELECT score_low, score_high, eval_episode_ids FROM candidates WHERE run_id = ? AND iteration = ? AND "
            "policy_version_id = ?", [run["run_id"], run["best_iteration"], run["best_version_id"]])
        assert (run["best_low"], run["best_high"], run["best_episodes"]) == (low, high, len(ids_))
        returns.append([episodes[i] for i in ids_])
        (audited,), = store.query("SELECT episode_ids FROM audits WHERE run_id = ? AND role = 'best' AND "
                                  "protocol = 'standard' AND policy_version_id = ?",
                                  [run["run_id"], run["best_version_id"]])
        held.append([episodes[i] for i in audited])
    assert report["difference"]["basis"] == "held_out"
    assert report["difference"]["verdict"] == difference(*held).verdict()
    assert report["difference"]["tuning"]["delta"] == difference(*returns).delta
    verdict = (f"best versions, held out (the standard protocol on their sealed audit games, 3 and 3): "
               f"{difference(*held).verdict()}")
    readme = (tmp_path / "cmp" / "README.md").read_text()
    assert markdown_text(verdict) in readme
    assert markdown_text("on the tuning episodes that picked them (1 and 1): A - B = ") in readme
    # without the audits the tuning difference is not tested, and under the paper's protocol its episodes replay
    # one game: the verdict says both, as compare of two versions does (a reviewer read "beyond the noise" as a
    # result)
    from viewers.compare_report import _best_difference

    unaudited = {**report, "difference": {**report["difference"], "basis": "tuning",
                                          "verdict": "A - B = +1.0: not tested: each best was picked"}}
    assert "compare A:best B:best --audit" in _best_difference(unaudited)
    standard = {**unaudited, "runs": [{**r, "best_protocol": "standard"} for r in report["runs"]]}
    assert "picked" in _best_difference(standard) and "replays the same game" not in _best_difference(standard)
    png = (tmp_path / "cmp" / "curves.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 20_000
    assert "![learning curves" in (tmp_path / "cmp" / "README.md").read_text()
    # runs whose scores measure different things (a step cap of 800 against 50) are compared with a warning
    assert report["cautions"] == [] and "warning" not in err
    with store.write() as con:
        con.execute("UPDATE runs SET config = json_merge_patch(config, '{\"eval_max_steps\": 50}') WHERE run_id = ?",
                    [ids[1]])
    code, out, err = run_main("compare", ids[0], ids[1], "--out", tmp_path / "cmp2", "--store", store.path,
                              "--json")
    assert code == 0 and json.loads(out)["cautions"] == [
        "the runs differ in the evaluation's step cap (eval_max_steps: A 800, B 50): their scores measure different "
        "things"]
    assert "codearcade: warning: the runs differ in the evaluation's step cap" in err
    assert "**Caution:** the runs differ in the evaluation" in (tmp_path / "cmp2" / "README.md").read_text()
    # `last` and `last~1` count the runs with iterations, as every other verb counts its kind: a newer eval run
    # is passed over, and said (it was taken for `last`: "an eval run without iterations")
    assert run_main("eval", EXAMPLES / "pong.py", "--episodes", 1, "--max-steps", 30, "--store",
                    store.path)[0] == 0
    code, out, err = run_main("compare", "last~1", "last", "--out", tmp_path / "cmp3", "--store", store.path,
                              "--json")
    assert code == 0, err
    assert [r["run_id"] for r in json.loads(out)["runs"]] == ids
    assert "compare: last is optimize run" in err and "passing over the newer eval run" in err


def test_versions_on_the_same_seeds_are_compared_pair_by_pair(store, tmp_path):
    """Under the paper's protocol both sides play the same seeds with one random stream, yet their difference was
    Welch's, as if the games were independent: a copy of the random scaffold against itself, 0 on every seed,
    read +0.0 [-13.7, +13.7]. It is now the paired t of the per-seed differences: no interval for the copy (the
    same difference on every seed), and for two policies scipy's ``ttest_rel`` of the stored returns."""
    from scipy import stats

    from store.statistics import PAIRED_METHOD, SAME_DIFFERENCE

    scaffold = ROOT / "games" / "scaffolds" / "pong.py"
    copy = tmp_path / "copy.py"
    copy.write_text(scaffold.read_text())
    found = {}
    for name, other in (("copy", copy), ("competent", COMPETENT)):
        # one random stream named (a new one each time would leave the scaffold's returns to chance: all equal on
        # the three seeds in a CI run, and then there is no noise for any interval)
        code, out, err = run_main("compare", scaffold, other, "--episodes", 3, "--max-steps", 400,
                                  "--rng-key", "paired-by-seed", "--store", store.path, "--json")
        assert code == 0, err
        found[name] = json.loads(out)
    copy_difference = found["copy"]["difference"]
    scaffold_returns = [e["return"] for e in found["copy"]["scores"]["A"]["episodes"]] \
        if "episodes" in found["copy"]["scores"]["A"] else None
    assert copy_difference["method"] == PAIRED_METHOD and copy_difference["reason"] == SAME_DIFFERENCE, \
        (copy_difference, scaffold_returns)
    assert copy_difference["delta"] == 0 and copy_difference["low"] is None and "cannot tell" in \
        copy_difference["verdict"]
    returns = [[r[0] for r in store.query("SELECT return FROM episodes WHERE run_id = ? AND kind = 'eval' "
                                          "ORDER BY episode_index", [v["eval_run"]])]
               for v in found["competent"]["versions"]]
    expected = stats.ttest_rel(*returns).confidence_interval()
    paired = found["competent"]["difference"]
    assert paired["method"] == PAIRED_METHOD and paired["n"] == [3, 3]
    assert (paired["low"], paired["high"]) == pytest.approx((expected.low, expected.high))


def test_what_cannot_be_compared_is_said_in_one_line(store, tmp_path):
    code, out, err = run_main("eval", EXAMPLES / "pong.py", "--max-steps", 5, "--store", store.path, "--json")
    run_id = json.loads(out)["run_id"]
    cases = [
        (("compare", run_id, COMPETENT), "is a policy version but"),
        (("compare", COMPETENT, tmp_path / "missing.py"), "does not exist"),
        (("compare", f"{run_id}:ffff", COMPETENT), "has no policy version 'ffff'"),
        (("compare", run_id, run_id), "is an eval run without iterations"),
        (("compare", COMPETENT, EXAMPLES / "breakout.py"), "plays pong but"),
        (("compare", "01NOSUCHRUN", run_id), "no run 01NOSUCHRUN"),
        (("compare", COMPETENT, COMPETENT, "--rerun", "side.mp4"), "give a FILE.rrd"),
    ]
    for argv, message in cases:
        code, out, err = run_main(*argv, "--store", store.path)
        assert code == 2 and message in err, (argv, err)
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


# ------------------------------------------------------------------------------------ beyond the noise (--audit)
# Figures (docs/compare.md): the competent policy on audit seeds 1000000..11 against 1000012..23, 1000 steps
# (compare's sealed draws pinned there):
# A - B = +0.0 [-1.3, +1.3] (Welch t); the same policy's first seeds happen to lose more (6 a side: -1.7
# [-3.6, +0.3]; at 9 a side the interval leaves 0 out, as a 95% one does about one time in twenty), so 12 a side
# are played. The scaffold against it on 6 seeds each: -19.0 [-21.0, -17.0].
AUDIT_STEPS = 1000


@pytest.fixture
def audit_seeds_from_base(pinned_audit_seeds):
    """The figures above were played on the audit seeds from ``AUDIT_SEED_BASE`` on: pin compare's draws there."""
    from games.base import AUDIT_SEED_BASE

    pinned_audit_seeds(AUDIT_SEED_BASE)


def audit_compare(store, a, b, episodes: int) -> dict:
    code, out, err = run_main("compare", a, b, "--audit", "--episodes", episodes, "--max-steps", AUDIT_STEPS,
                              "--workers", 2, "--rng-key", "audit-compare", "--store", store.path, "--json")
    assert code == 0, err
    return json.loads(out)


def stored_returns(store, run_id: str) -> list[float]:
    return [r[0] for r in store.query("SELECT return FROM episodes WHERE run_id = ? AND kind = 'eval' "
                                      "ORDER BY episode_index", [run_id])]


@pytest.mark.slow
def test_a_policy_against_itself_on_other_audit_seeds_differs_by_no_more_than_the_noise(store, capsys,
                                                                                       audit_seeds_from_base):
    from games.base import AUDIT_SEED_BASE, STANDARD_NOOP_MAX, STANDARD_STICKY
    from store.scores import score_episodes
    from store.statistics import difference

    report = audit_compare(store, COMPETENT, COMPETENT, 12)
    assert report["protocol"] == "audit" and report["episodes"] == [], "different games: no divergent step"
    runs = [v["eval_run"] for v in report["versions"]]
    # each side on its own audit seeds, under the standard protocol, as the store recorded them
    for k, run_id in enumerate(runs):
        seeds = [r[0] for r in store.query("SELECT seed FROM episodes WHERE run_id = ? ORDER BY episode_index",
                                           [run_id])]
        assert seeds == [AUDIT_SEED_BASE + 12 * k + i for i in range(12)]
        config = json.loads(store.query("SELECT config FROM runs WHERE run_id = ?", [run_id])[0][0])
        assert (config["sticky"], config["noop_max"]) == (STANDARD_STICKY, STANDARD_NOOP_MAX)
    returns = [stored_returns(store, r) for r in runs]
    assert returns[0] != returns[1], "the standard protocol's seeds are different games"
    expected = difference(*returns)
    assert report["difference"]["significant"] is False and expected.significant is False
    assert (report["difference"]["low"], report["difference"]["high"]) == (expected.low, expected.high)
    assert report["difference"]["low"] < 0 < report["difference"]["high"]
    for label, side in zip("AB", returns):
        score = score_episodes([{"return": r, "end_reason": "truncated", "length": AUDIT_STEPS} for r in side])
        assert report["scores"][label]["returns"] == side
        assert (report["scores"][label]["mean"], report["scores"][label]["low"]) == (score.mean, score.low)


@pytest.mark.slow
def test_the_starter_against_the_competent_policy_differs_beyond_the_noise(store, capsys, tmp_path,
                                                                            audit_seeds_from_base):
    from pipeline.cli import main as cli

    report = audit_compare(store, EXAMPLES / "pong.py", COMPETENT, 6)
    difference = report["difference"]
    assert difference["significant"] is True and difference["high"] < 0, difference
    assert report["scores"]["A"]["high"] < report["scores"]["B"]["low"], "the intervals do not even overlap"
    # the text and the README say it in words, with both sides' scores
    code = cli(["compare", str(EXAMPLES / "pong.py"), str(COMPETENT), "--audit", "--episodes", "2", "--max-steps", "100",
                "--store", str(store.path), "--out", str(tmp_path / "cmp")])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert re.search(r"^  A: mean return \S+ (?:\[\S+, \S+\] 95% t, n=2|\(n=2: all equal, no interval\)) "
                     r"\(seeds 1000000\.\.1000001; returns ", out, re.M), "the interval's level, method and n"
    assert re.search(r"^  B: .*\(seeds 1000002\.\.1000003; ", out, re.M)
    assert re.search(r"^  A - B = ", out, re.M) and "first divergent step" not in out
    readme = (tmp_path / "cmp" / "README.md").read_text()
    assert "## Scores" in readme and "- A - B = " in readme


@pytest.mark.slow
def test_compare_audit_draws_sealed_seeds_afresh_for_each_side_and_each_comparison(store):
    """No policy can know --audit's games in advance: each comparison draws both sides' seeds afresh over the audit's
    whole range (not the public AUDIT_SEED_BASE + i), the two sides' disjoint, and the text names the seeds played."""
    from games.base import AUDIT_SEED_BASE, AUDIT_SEED_END

    played = []
    for _ in range(2):
        code, out, err = run_main("compare", COMPETENT, COMPETENT, "--audit", "--episodes", 2, "--max-steps", 20,
                                  "--workers", 2, "--rng-key", "sealed", "--store", store.path, "--json")
        assert code == 0, err
        report = json.loads(out)
        sides = [report["scores"][label]["seeds"] for label in "AB"]
        for side, version in zip(sides, report["versions"]):
            stored = [r[0] for r in store.query("SELECT seed FROM episodes WHERE run_id = ? ORDER BY episode_index",
                                                [version["eval_run"]])]
            assert stored == side and len(side) == 2
        seeds = sides[0] + sides[1]
        assert len(set(seeds)) == 4 and all(AUDIT_SEED_BASE <= s < AUDIT_SEED_END for s in seeds), seeds
        assert not set(seeds) & set(range(AUDIT_SEED_BASE, AUDIT_SEED_BASE + 1000)), "not the old public seeds"
        played.append(seeds)
        from viewers.compare_report import text_lines
        text = "\n".join(text_lines(report))
        assert f"(seeds {sides[0][0]}, {sides[0][1]}; returns " in text, text
    assert not set(played[0]) & set(played[1]), "each comparison draws its own games"


def test_same_seed_comparison_says_the_paper_protocol_measures_no_noise(store):
    code, out, err = run_main("compare", COMPETENT, COMPETENT, "--episodes", 2, "--max-steps", 50,
                              "--store", store.path)
    assert code == 0, err
    # one game twice on each side: every return the same, so no interval (not [+0, +0]) and no call either way
    assert "A - B = +0.0 (n=2 and 2: all equal, no interval): cannot tell" in out
    assert "under the paper's protocol every seed is the same game" in out
    code, out, err = run_main("compare", COMPETENT, COMPETENT, "--audit", "--rerun", "x.rrd",
                              "--store", store.path)
    assert code == 2 and "with --audit each side plays its own seeds" in err


def test_two_budgets_of_a_run_comparison_are_two_rows_however_close():
    """Budget rows are rounded to three decimals (``budget_table``); printed to two, 0.007 and 0.013 thousand
    tokens both read 0.01. Over budgets of every size, each distinct one reads distinctly and as its value."""
    import random

    from viewers.compare_report import _amount

    rng = random.Random(3)
    budgets = {round(rng.random() * 10.0 ** rng.randint(-3, 5), 3) for _ in range(2000)} | {0.007, 0.013, 3.08, 2.0}
    texts = {_amount(b): b for b in budgets}
    assert len(texts) == len(budgets)
    assert all(float(text) == budget and not text.endswith((".", "0.0")) for text, budget in texts.items())


def test_the_runs_table_never_cuts_a_best_score_s_interval():
    """The runs table clipped its cells at 32 characters: ``-1.0 (n=3: all equal, no interv…``, ``1385.0 [1310.4,
    1459.6] 95% t, …`` lost the n the interval names. Over scores of every size and every kind of interval, the
    printed table holds each run's best exactly as ``interval_text`` writes it."""
    import random

    from viewers.compare_report import _best, text_lines

    rng = random.Random(5)
    for _ in range(200):
        runs = []
        for label in "AB":
            point = round(rng.choice([-1, 1]) * rng.random() * 10.0 ** rng.randint(-3, 6), rng.randint(0, 4))
            spread = abs(point) * rng.random() if rng.random() < 0.7 else None
            n = rng.choice([1, 2, 3, 30, 1000])
            runs.append({"label": label, "run_id": "01" + "X" * 24, "model": "openai/" + "m" * rng.randint(1, 60),
                         "status": "finished", "iterations": 3, "best_score": point,
                         "best_low": None if spread is None else point - spread,
                         "best_high": None if spread is None else point + spread, "best_episodes": n,
                         "best_iteration": 2, "llm_calls": 3, "total_tokens": 9000, "elapsed_s": 12.0})
        budgets = [{"unit": "LLM calls", "budget": 3, "A": runs[0]["best_score"], "B": runs[1]["best_score"]}]
        data = {"mode": "runs", "runs": runs, "difference": {"verdict": "no verdict"}, "budgets": budgets,
                "diff": None}
        table = text_lines(data)[0]
        for run in runs:
            assert _best(run) in table, (_best(run), table)
