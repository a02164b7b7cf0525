"""Shared fixtures: a fresh store per test, the example policies, and a writer of throwaway policy files."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from store import Store

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
POLICIES = Path(__file__).resolve().parent / "policies"


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return Store(tmp_path / "test.duckdb", lock_timeout_s=20)


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
