"""Shared fixtures: a fresh store per test, the example policies, and a writer of throwaway policy files; and the
suite's own rules of time: a ceiling per test, and ``--soak`` for the long form of the soak loops; and Ctrl-C
live in the commands the tests start, however the suite itself was started.

How to run the suite, its quick lane and the full soak: docs/install.md, "Running the tests".
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import re
import signal
import textwrap
import time
from pathlib import Path
from typing import NamedTuple

import pytest

from store import Store

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "games" / "scaffolds"
POLICIES = Path(__file__).resolve().parent / "policies"

CEILING_S = float(os.environ.get("CODEARCADE_TEST_CEILING_S", "150"))
"""No single test may take longer (its call, on a 2-core machine beside the other worker): a test that grows past
it fails with its time, so it is seen when it lands, not when the suite no longer fits CI's 90 minutes. The slowest
test takes about a third of it on an idle machine. ``--soak`` lifts it."""

QUICK_SHARE = 0.1
"""A test of the quick lane (not marked ``slow``) gets this share of the ceiling, 15 s by default: the quick lane is
for a developer's loop (docs/install.md), and a test that starts commands, games or model servers belongs to the
full suite (``@pytest.mark.slow``). Without this rule the quick lane grew from 75 s to 6.5 min in two days."""

CEILING_STRETCHES = "CODEARCADE_TEST_CEILING_S" not in os.environ
"""The default ceiling is for a machine that runs the suite alone, as fast as the one it was set on: on one busy with
other work (a load average above its cores) it stretches by the load per core, and on a slower one by how much slower
(:func:`machine_slowness`), so that no test fails because the machine is slow; an explicit
``CODEARCADE_TEST_CEILING_S`` is taken as it is."""

REFERENCE_LOOP_S = 0.016
"""The best time of :func:`plain_python_loop` on the 2-core machine :data:`CEILING_S` was set on, a little under the
18-19 ms it took there on a quiet night (2026-12-07), so that a machine as slow as that one stretches no ceiling
by much."""


def plain_python_loop() -> float:
    """Seconds of a fixed loop of plain Python (no I/O, no allocation to speak of): how fast this machine runs."""
    began = time.perf_counter()
    total = 0
    for i in range(300_000):
        total += i * i
    return time.perf_counter() - began


@functools.lru_cache(maxsize=1)
def machine_slowness() -> float:
    """How many times slower than the machine the ceiling was set on this one runs plain Python, at least 1 (a faster
    one keeps the ceiling): the best of nine runs of :func:`plain_python_loop` against :data:`REFERENCE_LOOP_S`,
    measured once a process. A VM whose host is busy runs everything slower without a load average that shows it:
    the same tests ran 1.5 times as long one evening here as that afternoon."""
    return max(1.0, min(plain_python_loop() for _ in range(9)) / REFERENCE_LOOP_S)


def load_now() -> float:
    """The machine's load for the ceiling: the larger of its 1- and 5-minute averages. The 5-minute one lags a load
    that has just risen by minutes (a quick test of 8 s failed at 15 s so, two other jobs having just started); the
    1-minute one forgets within a minute a load that the test has just run under."""
    one, five, _ = os.getloadavg()
    return max(one, five)


def ceiling_s(slow: bool = True) -> float:
    """The ceiling of a test that ends now (:data:`CEILING_S`, or its :data:`QUICK_SHARE` for a test not marked
    ``slow``; stretched by the load per core and by the machine's slowness when it may)."""
    ceiling = CEILING_S if slow else CEILING_S * QUICK_SHARE
    if not CEILING_STRETCHES:
        return ceiling
    return ceiling * max(1.0, load_now() / (os.cpu_count() or 1)) * machine_slowness()


def pytest_configure(config):
    """Give SIGINT its handler back if the suite was started with it ignored: a suite started in the background of
    a script (``cmd &``), under ``nohup ... &`` or by a CI runner that ignores it would pass the ignoring on to every
    command a test starts, and Python then never turns SIGINT into KeyboardInterrupt, so a server a test stops with
    Ctrl-C serves on, holding its ports, until the test's time-out (three tests failed so, beside two CPU hogs).
    A caught signal is reset to its default by ``exec``: the commands start as from a terminal. A test that wants
    the ignoring (``tests/faults/test_ctrl_c_group.py``, ``nohup=True``) sets it in its child itself."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_addoption(parser):
    parser.addoption("--soak", action="store_true",
                     help="codearcade: run the soak loops in full (twenty kills instead of four, ...); no ceiling "
                          "per test")


@pytest.fixture
def soak(request) -> bool:
    """Whether the soak loops run in full (``pytest --soak``) or as a few representative rounds (default)."""
    return bool(request.config.getoption("--soak"))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if call.when != "call" or not report.passed or item.config.getoption("--soak"):
        return
    slow = item.get_closest_marker("slow") is not None
    ceiling = ceiling_s(slow)
    if call.duration > ceiling:
        kind, rule, advice = ("test", "CEILING_S", "") if slow else \
            ("quick test", "CEILING_S x QUICK_SHARE", "; a test that starts commands or games is marked slow")
        report.outcome = "failed"
        report.longrepr = (f"{item.nodeid} passed, but took {call.duration:.0f} s, over the ceiling of {ceiling:g} s a "
                           f"{kind} (tests/conftest.py: {rule}, load {load_now():.1f} on {os.cpu_count()} "
                           f"cores, {machine_slowness():.2f} times as slow as the reference machine): play fewer "
                           f"steps, share what it builds, or split it{advice}")


@pytest.fixture(autouse=True)
def _private_user_store(tmp_path_factory, monkeypatch):
    """A command run without --store in a test never writes the person's own per-user store (store/locate.py)."""
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path_factory.getbasetemp() / "xdg-data"))


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return Store(tmp_path / "test.duckdb", lock_timeout_s=20)


def old_store(path: Path, version: int):
    """A store file as a codearcade at schema ``version`` left it (migrations 1..version applied, recorded); an
    open read-write DuckDB connection to it, for the test to add rows with, then close."""
    import duckdb

    from store.migrations import MIGRATIONS

    con = duckdb.connect(str(path))
    con.execute("CREATE TABLE schema_migrations (version INTEGER PRIMARY KEY, name VARCHAR NOT NULL, "
                "applied_at TIMESTAMP NOT NULL)")
    for number, name, sql in MIGRATIONS[:version]:
        con.execute(sql)
        con.execute("INSERT INTO schema_migrations VALUES (?, ?, now())", [number, name])
    return con


@pytest.fixture
def pinned_audit_seeds(monkeypatch):
    """``pin(first)``: ``compare --audit``'s sealed draws replaced by the seeds from ``first`` on (A's, then B's),
    for a test whose assertions need known games; the draws themselves are tested in tests/test_audit.py."""
    import pipeline.play.versus as versus

    def pin(first: int) -> None:
        monkeypatch.setattr(versus, "draw_audit_seeds", lambda n: [first + i for i in range(n)])
    return pin


@pytest.fixture
def write_policy(tmp_path: Path):
    """Write a policy file from (dedented) text and return its path."""

    def write(text: str, name: str = "policy.py") -> Path:
        path = tmp_path / name
        path.write_text(textwrap.dedent(text))
        return path

    return write


PONG_HEADER = """
import tracing as trace

GAME = "pong"

@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        y = self.predict_ball_trajectory(obs)
        return self.select_action(y, obs)

    @trace.bundle(trainable=True)
    def predict_ball_trajectory(self, obs):
        ball = obs.get("Ball")
        return None if ball is None else float(ball["y"])
"""


def pong_policy(select_action_body: str, prelude: str = "") -> str:
    """A Pong policy whose ``select_action`` body is given (indented 8 spaces inside the method)."""
    body = textwrap.indent(textwrap.dedent(select_action_body).strip("\n"), " " * 8)
    return (
        textwrap.dedent(prelude)
        + PONG_HEADER
        + "\n    @trace.bundle(trainable=True)\n    def select_action(self, predicted_ball_y, obs):\n"
        + body
        + "\n"
    )


class CommandResult(NamedTuple):
    """What a command run by :func:`run_main` ended with (the names of ``subprocess.CompletedProcess``)."""

    returncode: int
    stdout: str
    stderr: str


def run_main(*argv) -> CommandResult:
    """``codearcade ARGV...`` run by its ``main`` in this process: the command line's parser and handlers, without a
    process of its own (one spends ~5 s of CPU importing litellm, which the test's process imports once). Each
    argument is passed as ``str``; the exit status is ``main``'s, or argparse's ``SystemExit`` code for a refused
    argument or ``--help``; ``stdout`` and ``stderr`` are what the command wrote to ``sys.stdout`` and
    ``sys.stderr`` (its child processes' own writes are not among them). A test about the process itself (a
    signal, an exit code the interpreter sets, start-up) starts one instead."""
    from pipeline.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(arg) for arg in argv])
        except SystemExit as exc:  # argparse's refusals and --help
            code = exc.code
    return CommandResult(code, out.getvalue(), err.getvalue())


PROGRESS_LINE = re.compile(r"\S.*: (\d+ episodes? to play|\d+ of \d+ episodes played, [\d,]+ steps)")
"""A line of progress off a terminal (``pipeline.cli.common.EpisodeProgress``)."""


def said(err: str) -> list[str]:
    """The lines a command wrote to stderr besides its progress (what it said to the person)."""
    return [line for line in err.strip().splitlines() if not PROGRESS_LINE.fullmatch(line)]


def random_policy(game: str, action: str) -> str:
    """A policy for ``game`` whose one bundled method returns ``action`` (an expression; ``random`` is imported)."""
    return f"GAME = {game!r}\n" + textwrap.dedent("""
        import random
        import tracing as trace

        @trace.model
        class Policy(trace.Module):
            def __call__(self, obs):
                return self.act(obs)

            @trace.bundle(trainable=True)
            def act(self, obs):
                return ACTION
        """).replace("ACTION", action)


# The competent Pong policy's two methods with its constants written in, as an LLM would suggest them.
COMPETENT_PREDICT = '''def predict_ball_trajectory(self, obs):
    """Where the ball's centre reaches x=140, bouncing off y=30 and y=190; None if unknown."""
    ball = obs.get("Ball")
    if ball is None or ball["dx"] <= 0:
        return None
    steps = (140 - ball["x"]) / ball["dx"]
    y = ball["y"] + ball["h"] / 2 + ball["dy"] * steps
    offset = (y - 30) % 320
    return 30 + (offset if offset <= 160 else 320 - offset)
'''
COMPETENT_SELECT = '''def select_action(self, predicted_ball_y, obs):
    """Steer the paddle (where it will be next step) to the predicted y."""
    player = obs.get("Player")
    if player is None:
        return 0
    target = predicted_ball_y
    if target is None:
        ball = obs.get("Ball")
        target = ball["y"] + ball["h"] / 2 if ball else 110
    paddle = player["y"] + 7.5 + 4 + player["dy"]
    if paddle < target - 3:
        return 3
    if paddle > target + 3:
        return 2
    return 0
'''


def json_reply(suggestion: dict, reasoning: str = "scripted") -> str:
    import json

    return json.dumps({"reasoning": reasoning, "suggestion": suggestion})


COMPETENT_REPLY = json_reply({"predict_ball_trajectory": COMPETENT_PREDICT, "select_action": COMPETENT_SELECT})


@pytest.fixture
def scripted(tmp_path):
    """Start a scripted model with ``scripted([replies...])``; stopped after the test."""
    from tests.scripted_llm import ScriptedModel

    started = []

    def start(script: list) -> ScriptedModel:
        model = ScriptedModel(script, tmp_path / f"model{len(started)}")
        started.append(model.start())
        return started[-1]

    yield start
    for model in started:
        model.stop()
