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

from pipeline.cli import main
from store import Store
from store.comparisons import resolve_version
from store.writer import replace_audits

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


def _cli(capsys, *argv) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    out, _ = capsys.readouterr()
    return code, out


def test_an_audit_of_an_earlier_best_is_never_shown_as_the_best_s(greedy, tmp_path, capsys):
    """A run audited when its best was the starter, then resumed to a new best (iteration 1) with no audit at its
    end: the audit's -15 was the starter's, and runs and report printed it as the held-out score of the best."""
    store, run = greedy
    with store.write() as con:
        replace_audits(con, run, [_audit("best", "standard", STARTER, 0, -15.0, -10.0, False),
                                  _audit("starter", "standard", STARTER, 0, -15.0, None)])
    code, out = _cli(capsys, "runs", "--store", store.path)
    assert code == 0 and "stale (iteration 0)" in out and "-15" not in out, out
    (row,) = store.query("SELECT best_score, best_iteration, audit_score, audit_low, audit_run_score, overfit, "
                         "starter_audit_score, audit_stale, audit_iteration FROM run_summary")
    assert row == (0.0, 1, None, None, None, None, None, True, 0), row
    code, out = _cli(capsys, "runs", "--json", "--store", store.path)
    (listed,) = json.loads(out)
    assert listed["audit_score"] is None and listed["audit_stale"] is True and listed["overfit"] is None

    code, _ = _cli(capsys, "report", run, "--out", tmp_path / "report", "--store", store.path)
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
    code, out = _cli(capsys, "runs", "--store", store.path)
    assert "-3 OVERFIT" in out and "stale" not in out, out


def test_a_served_runs_best_is_its_best_by_validation_in_blame_and_run_best(greedy, capsys):
    """A served run's finalize picked iteration 2's version by validation (its training score, -19, is not the
    best's): blame's default named it without calling it the best, and RUN:best (compare) resolved to another."""
    store, run = greedy
    with store.write() as con:
        con.execute("UPDATE runs SET kind = 'serve' WHERE run_id = ?", [run])
        replace_audits(con, run, [_audit("submission 1", "validation", BEST, 1, -5.0, 0.0),
                                  _audit("submission 2", "validation", WORSE, 2, 3.0, -19.0),
                                  _audit("best", "standard", WORSE, 2, 2.0, -19.0, False),
                                  _audit("starter", "standard", STARTER, 0, -10.0, None)])
    code, out = _cli(capsys, "blame", run, "--store", store.path)
    assert code == 0 and out.splitlines()[0].endswith(f"policy version {WORSE} (iteration 2, the best)"), out
    with store.read() as con:
        assert resolve_version(con, run, "best") == WORSE, "RUN:best: the version the run picked"
    code, out = _cli(capsys, "blame", run, "--iteration", 1, "--store", store.path)
    assert "the best" not in out.splitlines()[0]
    assert store.query("SELECT audit_score, audit_stale FROM run_summary") == [(2.0, False)], \
        "a served run's audit is of its best by validation, never stale"

    # not finalized yet: the best by training score, as before
    with store.write() as con:
        replace_audits(con, run, [])
    with store.read() as con:
        assert resolve_version(con, run, "best") == BEST
