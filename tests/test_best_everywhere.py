"""A run's best, the same version in every reader outside the loop: ``runs``, ``report``, ``blame`` and ``RUN:best``
agree with the loop's choice (``iterations.best_version_id``, by ``store.scores``' rule), and an audit is shown
as the best's only when it played that version.

The stores are tests/fixtures/greedy_run.duckdb.gz (an optimization of Pong whose best is iteration 1's version,
``596254575f4ccf7d``, score 0; iteration 0's starter scored -10, iteration 2's ``ec8ecf68611bac85`` -19), with
``audits`` rows written as ``codearcade audit`` and a served run's finalize write them
(``store.writer.replace_audits``).
"""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import pytest

from store import Store
from store.comparisons import resolve_version
from store.writer import replace_audits
from tests.conftest import run_main

FIXTURE = Path(__file__).parent / "fixtures" / "greedy_run.duckdb.gz"
STARTER, BEST, WORSE = "0688b04958724e0e", "596254575f4ccf7d", "ec8ecf68611bac85"


@pytest.fixture
def greedy(tmp_path) -> tuple[Store, str]:
    path = tmp_path / "greedy.duckdb"
    with gzip.open(FIXTURE) as packed, open(path, "wb") as out:
        shutil.copyfileobj(packed, out)
    store = Store(path)
    return store, store.query("SELECT run_id FROM runs")[0][0]


def _audit(role: str, protocol: str, version: str, iteration: int, score: float | None, tuning: float | None,
           overfit: bool | None = None) -> dict:
    return dict(role=role, protocol=protocol, policy_version_id=version, iteration=iteration, seeds=[1_000_003],
                episode_ids=[], score=score, score_low=None, score_high=None,
                forfeit=None if score is not None else "1 of 1 episode forfeited: timeout at step 9 (timeout)",
                tuning_score=tuning, overfit=overfit)


def test_an_audit_of_an_earlier_best_is_never_shown_as_the_best_s(greedy, tmp_path):
    """A run audited when its best was the starter, then resumed to a new best (iteration 1) with no audit at its
    end: the audit's -15 was the starter's, and runs and report printed it as the held-out score of the best."""
    store, run = greedy
    with store.write() as con:
        replace_audits(con, run, [_audit("best", "standard", STARTER, 0, -15.0, -10.0, False),
                                  _audit("starter", "standard", STARTER, 0, -15.0, None)])
    code, out, _ = run_main("runs", "--store", store.path)
    assert code == 0 and "stale (iteration 0)" in out and "-15" not in out, out
    (row,) = store.query("SELECT best_score, best_iteration, audit_score, audit_low, audit_run_score, overfit, "
                         "starter_audit_score, audit_stale, audit_iteration FROM run_summary")
    assert row == (0.0, 1, None, None, None, None, None, True, 0), row
    code, out, _ = run_main("runs", "--json", "--store", store.path)
    (listed,) = json.loads(out)
    assert listed["audit_score"] is None and listed["audit_stale"] is True and listed["overfit"] is None

    code, _, _ = run_main("report", run, "--out", tmp_path / "report", "--store", store.path)
    readme = (tmp_path / "report" / "README.md").read_text()
    headline = readme.splitlines()[2]
    assert code == 0 and "best score **0** (iteration 1)" in headline, headline
    assert "-15" not in headline and "overfit" not in headline.lower(), headline
    assert "held-out audit: not of the run's best: it played the best of iteration 0" in headline
    assert "**not of the run's best: it played the best of iteration 0" in readme.split("## Held-out audit")[1]

    # audited again: of the best of now, shown as the best's
    with store.write() as con:
        replace_audits(con, run, [_audit("best", "standard", BEST, 1, -3.0, 0.0, True),
                                  _audit("starter", "standard", STARTER, 0, -15.0, None)])
    assert store.query("SELECT audit_score, overfit, starter_audit_score, audit_stale, audit_iteration "
                       "FROM run_summary") == [(-3.0, True, -15.0, False, 1)]
    code, out, _ = run_main("runs", "--store", store.path)
    assert "-3 OVERFIT" in out and "stale" not in out, out


def test_a_served_runs_best_is_its_best_by_validation_in_blame_and_run_best(greedy):
    """A served run's finalize picked iteration 2's version by validation (its training score, -19, is not the
    best's): blame's default named it without calling it the best, and RUN:best (compare) resolved to another."""
    store, run = greedy
    with store.write() as con:
        con.execute("UPDATE runs SET kind = 'serve' WHERE run_id = ?", [run])
        replace_audits(con, run, [_audit("submission 1", "validation", BEST, 1, -5.0, 0.0),
                                  _audit("submission 2", "validation", WORSE, 2, 3.0, -19.0),
                                  _audit("best", "standard", WORSE, 2, 2.0, -19.0, False),
                                  _audit("starter", "standard", STARTER, 0, -10.0, None)])
    code, out, _ = run_main("blame", run, "--store", store.path)
    assert code == 0 and out.splitlines()[0].endswith(f"policy version {WORSE} (iteration 2, the best)"), out
    with store.read() as con:
        assert resolve_version(con, run, "best") == WORSE, "RUN:best: the version the run picked"
    code, out, _ = run_main("blame", run, "--iteration", 1, "--store", store.path)
    assert "the best" not in out.splitlines()[0]
    assert store.query("SELECT audit_score, audit_stale FROM run_summary") == [(2.0, False)], \
        "a served run's audit is of its best by validation, never stale"

    # not finalized yet: the best by training score, as before
    with store.write() as con:
        replace_audits(con, run, [])
    with store.read() as con:
        assert resolve_version(con, run, "best") == BEST


def _finalized(store: Store, run: str, *validation: float | None) -> None:
    """The fixture's run as a served run finalized as ``pipeline/serve/finalize.py`` writes it: submissions 1 (the
    training best, ``BEST``, training score 0) and 2 (``WORSE``, -19) on the validation pool with these scores, and
    the best by validation with the starter on the held-out pool (none when every submission forfeited)."""
    versions = ((1, BEST, 0.0), (2, WORSE, -19.0))
    rows = [_audit(f"submission {i}", "validation", v, i, score, tuning)
            for (i, v, tuning), score in zip(versions, validation)]
    ranked = [(score, -i, v, tuning) for (i, v, tuning), score in zip(versions, validation) if score is not None]
    if ranked:
        _, neg, version, tuning = max(ranked)
        rows += [_audit("best", "standard", version, -neg, 2.0, tuning, False),
                 _audit("starter", "standard", STARTER, 0, -10.0, None)]
    with store.write() as con:
        con.execute("UPDATE runs SET kind = 'serve' WHERE run_id = ?", [run])
        replace_audits(con, run, rows)


def test_a_finalized_served_run_names_its_best_by_validation_in_every_verb(greedy, tmp_path):
    """A served run finalized with submission 2 as its best by validation (score 3; its training score, -19, is not
    the training best's 0, submission 1's). blame and RUN:best named submission 2, but run_summary's best columns
    were the best by training score: `runs` printed "best 0" beside the audit of submission 2, `report` said "best
    score 0 (iteration 1)" and showed submission 1's methods, `compare` diffed and scored submission 1 (its held-out
    audit 'of an earlier best', so no verdict), and the OTLP export's root span named submission 1. Now every verb
    names submission 2, with its validation score said as such (view run_best, the one home of a run's best)."""
    store, run = greedy
    _finalized(store, run, -5.0, 3.0)
    picked = (WORSE, 2, 3.0, "validation", -19.0)
    code, out, _ = run_main("runs", "--store", store.path)
    assert code == 0 and "3 validation" in out.splitlines()[2], out
    code, out, _ = run_main("runs", "--json", "--store", store.path)
    (listed,) = json.loads(out)
    assert (listed["best_iteration"], listed["best_score"], listed.get("best_version_id"), listed.get("best_by")) \
        == (2, 3.0, WORSE, "validation") and listed["audit_iteration"] == 2, listed
    for view in ("run_summary", "run_best"):
        assert store.query("SELECT best_version_id, best_iteration, best_score, best_by, best_training_score "
                           f"FROM {view}") == [picked], view

    code, _, _ = run_main("report", run, "--out", tmp_path / "report", "--store", store.path)
    readme = (tmp_path / "report" / "README.md").read_text()
    assert code == 0 and "best by validation **3** (iteration 2; training -19)" in readme.splitlines()[2], readme
    assert f"## Methods of the best version (`{WORSE}`)" in readme, readme

    code, out, _ = run_main("blame", run, "--store", store.path)
    assert code == 0 and out.splitlines()[0].endswith(f"policy version {WORSE} (iteration 2, the best)"), out
    with store.read() as con:
        assert resolve_version(con, run, "best") == WORSE

    code, out, _ = run_main("compare", run, run, "--json", "--out", tmp_path / "compare", "--store", store.path)
    compared = json.loads(out)
    assert code == 0 and [(r["best_version_id"], r["best_iteration"], r["best_score"], r["best_by"])
                          for r in compared["runs"]] == [picked[:4]] * 2, compared["runs"]
    assert all(r["held_out_missing"] is None for r in compared["runs"]) and \
        compared["difference"]["basis"] == "held_out", "the audit is of the best compared: a verdict on it"
    code, out, _ = run_main("compare", run, run, "--out", tmp_path / "compare", "--store", store.path)
    assert code == 0 and all("3.0 (n=0: too few for an interval) by validation" in line
                             for line in out.splitlines()[2:4]), out

    from store.run_trace import run_trace_rows
    from viewers.otlp_export import build_spans

    with store.read() as con:
        root = next(s for s in build_spans(run_trace_rows(con, run)) if s.parent is None)
    assert (root.attributes["codearcade.best_version_id"], root.attributes["codearcade.best_iteration"],
            root.attributes["codearcade.best_score"], root.attributes["codearcade.best_by"]) == picked[:4]

    saved = tmp_path / "run.rrd"
    assert run_main("view", run, "--save", saved, "--store", store.path).returncode == 0
    lines = _rrd_log_lines(saved)
    assert lines[-1] == f"finalized: best by validation 3 (iteration 2), version {WORSE}", lines
    assert lines[2].startswith("iteration 2: update accepted, score -19, best training score 0 (iteration 1)"), lines


def test_a_served_run_not_finalized_names_its_training_best_as_such_and_one_without_a_pick_none(greedy, tmp_path):
    """Before its finalize a served run's best is its best by training score, and says so; a finalize whose every
    submission forfeited a validation game picked none: no verb names the training best then."""
    store, run = greedy
    _finalized(store, run, -5.0, 3.0)
    with store.write() as con:
        replace_audits(con, run, [])
    code, out, _ = run_main("runs", "--store", store.path)
    assert code == 0 and "0 training" in out.splitlines()[2], out
    assert store.query("SELECT best_version_id, best_iteration, best_score, best_by FROM run_summary") == \
        [(BEST, 1, 0.0, "training")]
    run_main("report", run, "--out", tmp_path / "report", "--store", store.path)
    headline = (tmp_path / "report" / "README.md").read_text().splitlines()[2]
    assert "best score by training score (not finalized) **0** (iteration 1)" in headline, headline

    _finalized(store, run, None, None)
    code, out, _ = run_main("runs", "--store", store.path)
    assert "no score validation" in out.splitlines()[2], out
    assert store.query("SELECT best_version_id, best_score, best_by FROM run_summary") == [(None, None, "validation")]
    with store.read() as con, pytest.raises(ValueError, match="every submission forfeited a validation game"):
        resolve_version(con, run, "best")
    run_main("report", run, "--out", tmp_path / "again", "--store", store.path)
    readme = (tmp_path / "again" / "README.md").read_text()
    assert "**no best**: every submission forfeited a validation game" in readme and "Methods of the best" not in \
        readme, readme


def _rrd_log_lines(saved: Path) -> list[str]:
    """The run recording's log lines, in order (read by tests/rrd_dump.py in a process of its own)."""
    import subprocess
    import sys

    root_dir = Path(__file__).resolve().parents[1]
    dumped = subprocess.run([sys.executable, str(root_dir / "tests" / "rrd_dump.py"), str(saved)],
                            capture_output=True, text=True, timeout=120, cwd=root_dir)
    assert dumped.returncode == 0, dumped.stderr
    by_iteration = json.loads(dumped.stdout)[str(saved)]["timelines"]["iteration"]["/log:TextLog:text"]
    return [line for _, lines in sorted(by_iteration.items(), key=lambda kv: int(kv[0])) for line in lines]


def _forfeit(store: Store, iterations: tuple[int, ...]) -> None:
    """Make these iterations' versions forfeit their evaluation game as the loop stores one: a policy error at
    step 300 after scoring 50 (above every score of the run), the candidate's score NULL, its partial return kept
    as forfeit_score; with the starter among them, no best until a version plays its games out."""
    with store.write() as con:
        for i in iterations:
            con.execute("UPDATE episodes SET end_reason = 'policy_error', return = 50, length = 300, "
                        "error = 'RuntimeError: quit' WHERE episode_id LIKE ? AND kind = 'eval'", [f"%.{i}.eval.0"])
            con.execute("UPDATE candidates SET score = NULL, deterministic_score = NULL, forfeit_score = 50, "
                        "forfeit = '1 of 1 episode forfeited: RuntimeError at step 300 (policy_error)' "
                        "WHERE iteration = ?", [i])
            con.execute("UPDATE iterations SET score = NULL WHERE iteration = ?", [i])
        if 0 in iterations:
            con.execute("UPDATE iterations SET best_score = NULL")


def test_the_otlp_export_and_the_run_recording_name_a_forfeit_never_score_it(greedy, tmp_path):
    """Iteration 2's version forfeits its game after scoring 50: its span and its line in the run recording had no
    score and nothing saying why (the recording printed 'score -'); a run all of whose versions forfeited had no
    best score on its root span and nothing saying why."""
    import subprocess
    import sys

    from store.run_trace import run_trace_rows
    from viewers.otlp_export import build_spans

    store, run = greedy
    _forfeit(store, (2,))
    with store.read() as con:
        spans = build_spans(run_trace_rows(con, run))
    two = next(s for s in spans if s.name == "iteration 2")
    assert two.attributes["codearcade.forfeit"] == ("1 of 1 episode forfeited: RuntimeError at step 300 "
                                                    "(policy_error)")
    assert "codearcade.score" not in two.attributes and 50 not in two.attributes.values()
    assert all("codearcade.forfeit" not in s.attributes for s in spans if s.name == "iteration 1")
    root = next(s for s in spans if s.parent is None)
    assert root.attributes["codearcade.best_score"] == 0.0 and "codearcade.run.no_score" not in root.attributes

    root_dir = Path(__file__).resolve().parents[1]
    saved = tmp_path / "run.rrd"
    viewed = subprocess.run([sys.executable, "-m", "pipeline.cli", "view", run, "--save", str(saved), "--store",
                             str(store.path)], capture_output=True, text=True, timeout=300, cwd=root_dir)
    assert viewed.returncode == 0, viewed.stderr
    dumped = subprocess.run([sys.executable, str(root_dir / "tests" / "rrd_dump.py"), str(saved)],
                            capture_output=True, text=True, timeout=120, cwd=root_dir)
    assert dumped.returncode == 0, dumped.stderr
    lines = json.loads(dumped.stdout)[str(saved)]["timelines"]["iteration"]["/log:TextLog:text"]
    assert lines["2"] == ["iteration 2: update accepted, score none (1 of 1 episode forfeited: RuntimeError at step "
                          "300 (policy_error)), best 0 (iteration 1), version ec8ecf68611bac85, rolled back"]

    _forfeit(store, (0, 1, 2, 3, 4, 5))
    with store.read() as con:
        root = next(s for s in build_spans(run_trace_rows(con, run)) if s.parent is None)
    assert "codearcade.best_score" not in root.attributes and root.attributes["codearcade.run.forfeits"] == 6
    assert root.attributes["codearcade.run.no_score"] == "no score: every version it assessed forfeited a game"


@pytest.mark.parametrize("picked_by, said", [
    (("tuning", "tuning"), "on the tuning episodes that picked them (3 and 5)"),
    (("validation", "validation"), "on the validation games that picked them (3 and 5)"),
    (("validation", "tuning"), "on the tuning episodes and validation games that picked them (3 and 5)"),
])
def test_compare_names_the_games_that_picked_each_best(picked_by, said):
    """compare's held-out verdict gives the figures on the games that picked each best beside it: a finalized served
    run's best was picked on its validation games, not on tuning episodes (the line said so of every run)."""
    from viewers.compare_report import _best_difference

    data = {"difference": {"basis": "held_out", "verdict": "within the noise", "tuning": {
        "interval": "+1 [-2, +4]", "note": "not a test: each best was picked on them"}},
        "runs": [{"best_by": by, "best_episodes": n, "held_out": {"seeds": [1, 2]}} for by, n in zip(picked_by, (3, 5))]}
    assert said in _best_difference(data)
