"""The suite's own rules hold (tests/conftest.py): a test that passes but takes longer than the ceiling fails with
its time, ``--soak`` lifts the ceiling and runs the soak loops in full, and the quick lane is a marker."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

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


def test_a_test_past_the_ceiling_fails_with_its_time(tmp_path):
    done = _run(tmp_path)
    assert done.returncode == 1, done.stdout
    assert "1 failed, 1 passed" in done.stdout, done.stdout
    assert "test_timed.py::test_slow_one passed, but took 2 s, over the ceiling of 1 s" in done.stdout, done.stdout
    assert "short" in done.stdout


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
