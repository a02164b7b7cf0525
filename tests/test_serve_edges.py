"""A served run (``codearcade serve``) at the edges where it meets the other verbs: a verb that cannot do what was
asked of such a run says why in one line, with the command that does it, and exits 2; a stopped server says how
to go on with its run. The runs are made as ``serve`` makes them (``create_run``: nothing is played), and a
submission is a ``candidates`` row, as a committed one is: these verbs read the store, never the games.
"""

from __future__ import annotations

import pytest

from pipeline.serve.config import ServeConfig
from pipeline.serve.protocol import create_run
from store import Store
from store.writer import finish_run, insert_candidate
from tests.conftest import run_main


def _served(store: Store, submitted: bool) -> str:
    """A served run stopped as a server leaves it (``interrupted``), with one committed submission or none."""
    run_id = create_run(store, ServeConfig(game="pong", budget=2))
    with store.write() as con:
        if submitted:
            insert_candidate(con, dict(run_id=run_id, iteration=1, candidate=0, strategy="serve",
                                       policy_version_id="v" * 16, update_status="accepted", evaluation="played",
                                       decision="best"))
        finish_run(con, run_id, "interrupted")
    return run_id


def _counts(store: Store, run_id: str) -> tuple[int, int]:
    return store.query("SELECT (SELECT count(*) FROM audits WHERE run_id = $r), "
                       "(SELECT count(*) FROM episodes WHERE run_id = $r)", {"r": run_id})[0]


@pytest.mark.parametrize("as_json", [False, True])
def test_audit_of_a_served_run_not_finalized_says_how_to_finalize_it_and_fails(tmp_path, as_json):
    # it printed a hint on stderr (with --json, `"audits": []` on stdout) and exited 0, having played and written
    # nothing: a script took that for an audit
    store = Store(tmp_path / "s.duckdb")
    run_id = _served(store, submitted=True)
    before = _counts(store, run_id)
    result = run_main("audit", run_id, *(["--json"] if as_json else []), "--store", store.path)
    assert result.returncode == 2, result
    assert result.stdout == "", result
    (line,) = result.stderr.strip().splitlines()
    assert "not finalized" in line and f"serve --finalize {run_id[:8]}" in line, line
    assert _counts(store, run_id) == before == (0, 0)


def test_a_serve_stopped_before_any_submission_says_last_passes_over_it_and_how_to_go_on(tmp_path, monkeypatch):
    # it said "run X stopped: `serve --resume X` serves it again, `serve --finalize X` ends it": not that `last`
    # now passes over it, and the finalize it named refuses a run without a submission
    import pipeline.stopping

    def ctrl_c(done=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline.stopping, "wait_for_stop", ctrl_c)
    store = Store(tmp_path / "s.duckdb")
    lines = {}
    for submitted in (False, True):
        run_id = _served(store, submitted)
        result = run_main("serve", "--resume", run_id, "--port", "0", "--store", store.path)
        assert result.returncode == 0, result
        lines[submitted] = result.stderr.strip().splitlines()[-1]
        assert f"serve --resume {run_id[:8]}" in lines[submitted], lines
    assert "before any submission" in lines[False] and "`last` passes over it" in lines[False], lines
    assert "--finalize" not in lines[False], lines
    assert "--finalize" in lines[True] and "passes over" not in lines[True], lines


def test_serve_finalize_of_a_run_without_a_submission_names_it_and_how_to_go_on(tmp_path):
    # it said "no submission yet: there is nothing to finalize", naming neither the run (`--finalize last` takes
    # the newest served run, whichever) nor what to do
    store = Store(tmp_path / "s.duckdb")
    run_id = _served(store, submitted=False)
    result = run_main("serve", "--finalize", "last", "--store", store.path)
    assert result.returncode == 2, result
    (line,) = result.stderr.strip().splitlines()
    assert f"run {run_id[:8]}" in line and "nothing to finalize" in line, line
    assert f"serve --resume {run_id[:8]}" in line, line
    assert _counts(store, run_id) == (0, 0)


@pytest.mark.parametrize("as_json", [False, True])
def test_serve_finalize_of_a_finalized_run_says_so_and_plays_nothing(tmp_path, as_json):
    # it reprinted the result as if it had just finalized the run, without a word that it had been before
    store = Store(tmp_path / "s.duckdb")
    run_id = _served(store, submitted=True)
    with store.write() as con:
        finish_run(con, run_id, "finished")
    result = run_main("serve", "--finalize", run_id[:8], "--store", store.path, *(["--json"] if as_json else []))
    assert result.returncode == 0, result
    (line,) = result.stderr.strip().splitlines()
    assert line == f"run {run_id[:8]} was finalized before: its result as recorded", line
    assert _counts(store, run_id) == (0, 0), "nothing was played again"
    if as_json:
        assert '"run_id"' in result.stdout, result.stdout


def test_doctor_replay_of_a_run_without_episodes_says_it_replayed_none(tmp_path):
    # it printed the store's counts and "ok" and no word of the replay asked for, as if every episode replayed
    store = Store(tmp_path / "s.duckdb")
    run_id = _served(store, submitted=False)
    result = run_main("doctor", "--replay", run_id, "--store", store.path)
    assert result.returncode == 0, result
    assert f"replayed no episode: run {run_id[:8]}" in result.stdout, result


def test_whether_a_served_run_holds_a_submission_is_what_last_counts(tmp_path):
    # `audit` read a served run's whole submission rows to learn whether it had one: the store says it now, as
    # `last` counts it (store/runs.py: UNSUBMITTED_SQL)
    from store.runs import passed_over, unsubmitted

    store = Store(tmp_path / "s.duckdb")
    empty_first = _served(store, submitted=False)
    submitted = _served(store, submitted=True)
    empty_last = _served(store, submitted=False)
    with store.read() as con:
        assert [unsubmitted(con, r) for r in (empty_first, submitted, empty_last)] == [True, False, True]
        assert passed_over(con, submitted) == [(empty_last, "serve", True)]
        assert not unsubmitted(con, "no such run")


def test_serve_finalize_stopped_by_ctrl_c_says_how_to_finalize_it(tmp_path, monkeypatch):
    # a Ctrl-C while the validation and held-out pools played ended it with "codearcade: interrupted" alone (exit
    # 130, 0.6 s after the press): the run not finalized, and nothing said how to go on, where audit and optimize
    # each name the command that continues
    from pipeline.serve.protocol import ServeRun

    store = Store(tmp_path / "s.duckdb")
    run_id = _served(store, submitted=True)

    def pressed(self):  # the press, as it lands in the pools' games
        raise KeyboardInterrupt

    monkeypatch.setattr(ServeRun, "finalize", pressed)
    result = run_main("serve", "--finalize", "last", "--store", store.path)
    assert result.returncode == 130, result
    lines = result.stderr.strip().splitlines()
    assert lines[-1] == "codearcade: interrupted", result
    assert f"run {run_id[:8]} is not finalized" in lines[-2], lines
    assert f"serve --finalize {run_id[:8]}" in lines[-2], lines
