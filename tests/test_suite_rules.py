"""The suite's own rules hold (tests/conftest.py): a test that passes but takes longer than the ceiling fails with
its time, ``--soak`` lifts the ceiling and runs the soak loops in full, and the quick lane is a marker."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from tests.conftest import ROOT

SUITE = textwrap.dedent("""
    import time

    def test_quick():
        pass

    def test_slow_one(soak):
        time.sleep(1.5)
        print("soak" if soak else "short")
""")


def _run(tmp_path, *args: str) -> subprocess.CompletedProcess:
    """pytest over a two-test suite that takes the project's rules from tests/conftest.py, with a ceiling of 1 s."""
    (tmp_path / "conftest.py").write_text("from tests.conftest import pytest_addoption, pytest_runtest_makereport, "
                                          "soak  # noqa: F401\n")
    (tmp_path / "test_timed.py").write_text(SUITE)
    env = {**os.environ, "CODEARCADE_TEST_CEILING_S": "1", "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-s", "-q", *args],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.slow
def test_a_test_past_the_ceiling_fails_with_its_time(tmp_path):
    done = _run(tmp_path)
    assert done.returncode == 1, done.stdout
    assert "1 failed, 1 passed" in done.stdout, done.stdout
    assert "test_timed.py::test_slow_one passed, but took 2 s, over the ceiling of 1 s" in done.stdout, done.stdout
    assert "short" in done.stdout


@pytest.mark.slow
def test_soak_lifts_the_ceiling_and_runs_the_loops_in_full(tmp_path):
    done = _run(tmp_path, "--soak")
    assert done.returncode == 0 and "2 passed" in done.stdout, done.stdout
    assert "soak" in done.stdout.replace("--soak", "")


def test_the_quick_lane_is_a_marker_of_this_suite():
    """``pytest -m 'not slow'`` (docs/install.md) leaves out the end-to-end tests and keeps the rest."""
    done = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-n", "0", "--collect-only",
                           "-q", "-m", "not slow"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    quick = [line for line in done.stdout.splitlines() if "::" in line]
    assert "tests/test_suite_rules.py::test_the_quick_lane_is_a_marker_of_this_suite" in quick
    assert not any("test_kill_loop" in line or "test_readme_tour.py::test_the_readme_tour" in line for line in quick)
    assert len(quick) > 500


def test_the_default_ceiling_stretches_with_the_load_per_core_and_an_explicit_one_does_not(monkeypatch):
    """On a machine busy with other work the default ceiling grows by the load per core (no test fails because the
    machine is slow); on one at or below a load of one per core it is the ceiling; a ceiling set in the
    environment is kept as set."""
    from tests import conftest

    monkeypatch.setattr(conftest, "CEILING_SCALES_WITH_LOAD", True)
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 2)
    for load, stretch in ((0.3, 1.0), (2.0, 1.0), (3.0, 1.5), (7.0, 3.5)):
        monkeypatch.setattr(conftest.os, "getloadavg", lambda load=load: (0.0, load, 0.0))
        assert conftest.ceiling_s() == conftest.CEILING_S * stretch
    monkeypatch.setattr(conftest, "CEILING_SCALES_WITH_LOAD", False)
    assert conftest.ceiling_s() == conftest.CEILING_S
