"""Breakout's observation as the authors had it (observation version 2), and runs stored before it.

OCAtari reports each run of adjacent bricks in a row as one ``Block`` (w = 8 * n): the authors' observation
appends each Block unchanged, and so does codearcade's, from the environment through the store to the prompt.
Runs stored before observation versions were recorded split the runs into 8-pixel bricks, and still replay so.
The authors' own saved Breakout run (their repository's history; no licence, so it is read from a fetched copy
and never stored here) checks the convention against their logged scores.
"""

from __future__ import annotations

import gzip
import json
import os
import pickletools
import subprocess
from pathlib import Path

import pytest

from games import get_game
from pipeline.play.evaluate import EvalConfig, evaluate
from pipeline.optimizer.replay import replay
from store import Store
from store.readers import episode_steps
from tests.conftest import POLICIES
from viewers.rerun_replay import read_episode, replay_frames

FIXTURE = Path(__file__).parent / "fixtures" / "breakout_v1_run.duckdb.gz"
ROWS = ("RB", "OB", "YB", "GB", "AB", "BB")

FIRST_RED_BRICK = '''import tracing as trace

GAME = "breakout"


@trace.model
class Policy(trace.Module):
    def __call__(self, obs):
        self.first_red_brick_width(obs)
        return 0

    @trace.bundle(trainable=True)
    def first_red_brick_width(self, obs):
        """The width of the first entry of the red row (a full row at the start)."""
        return obs["RB"][0]["w"]
'''


def _first_red_brick(store: Store, write_policy, observation: int) -> dict:
    path = write_policy(FIRST_RED_BRICK, "first_red_brick.py")
    result = evaluate(path, EvalConfig(max_steps=3, trace=True, observation=observation), store)
    episode_id = result.outcomes[0].episode["episode_id"]
    with store.read() as con:
        (width,) = con.execute("SELECT output FROM nodes WHERE episode_id = ? AND step = 0", [episode_id]).fetchone()
        steps = episode_steps(con, episode_id, list_widths=get_game("breakout").observing(observation).list_widths,
                              derive=get_game("breakout").observing(observation).derive)
    config = json.loads(store.query("SELECT config FROM runs WHERE run_id = ?", [result.run_id])[0][0])
    return {"config": config, "obs": steps[0]["obs"], "width": json.loads(width)}


def test_a_policy_reading_the_first_brick_of_a_full_row_sees_the_whole_row(store, write_policy):
    """The policy sees one entry of w 144 for the full red row (the authors' Block), and so does the step read
    back from the store; the run records the convention."""
    seen = _first_red_brick(store, write_policy, 2)
    assert seen["width"] == 144
    assert seen["config"]["observation"] == 2
    assert seen["obs"]["RB"] == [{"x": 8, "y": 57, "w": 144, "h": 6, "dx": 0, "dy": 0}]
    assert list(seen["obs"]) == ["Player", "Ball", *ROWS, "lives"] and seen["obs"]["lives"] == 5


def test_observation_version_1_still_gives_8_pixel_bricks(store, write_policy):
    seen = _first_red_brick(store, write_policy, 1)
    assert seen["width"] == 8 and seen["config"]["observation"] == 1
    assert [(b["x"], b["w"]) for b in seen["obs"]["RB"]] == [(8 + 8 * i, 8) for i in range(18)]
    assert "lives" not in seen["obs"]


YELLOW_ROW_BYTES = [3 + 6 * k for k in range(6)]
"""Where Breakout keeps the yellow row's bricks: RAM bytes 0-35 are six bitmaps of six bytes, one byte of each row
per group (byte 3 + 6k: yellow; measured by clearing each byte: it takes a run of bricks out of one row)."""


def test_a_cleared_row_is_absent_as_in_the_authors_observation_and_empty_under_version_1():
    """The game's own brick memory with the yellow row cleared: the authors' observation (rebuilt by their rules
    from the same OCAtari objects) has no ``YB`` key, and neither has ours; version 1 shows ``YB: []``."""
    from games.envs import make_env
    from tests.authors_conventions import as_decided, authors_observation, differences

    seen = {}
    for observation in (2, 1):
        env = make_env("breakout", observation=observation)
        try:
            env.reset(seed=0)
            for address in YELLOW_ROW_BYTES:
                env.unwrapped.ale.setRAM(address, 0)
            obs, reward, *_ = env.step(0)
            if observation == 2:
                theirs = authors_observation("breakout", env._objects, env.unwrapped.ale.lives(), reward)
                assert "YB" not in theirs and differences("breakout", obs, as_decided("breakout", theirs)) == []
        finally:
            env.close()
        seen[observation] = obs
    assert [k for k in seen[2] if k in ROWS] == ["RB", "OB", "GB", "AB", "BB"]
    assert seen[2].get("YB", []) == [] and "YB" not in seen[2], "a cleared row is absent, not an empty list"
    assert seen[1]["YB"] == [] and all(len(seen[1][row]) == 18 for row in ROWS if row != "YB")


@pytest.mark.slow
@pytest.mark.parametrize("observation", [2, 1])
def test_the_papers_best_breakout_policy_scores_353_with_runs_of_bricks_as_with_bricks(store, observation):
    """Its gaps are measured between a row's neighbouring entries: the same gaps in both conventions."""
    result = evaluate(POLICIES / "breakout_paper_best.py", EvalConfig(max_steps=4000, observation=observation), store)
    episode = result.summary()["episodes"][0]
    assert (episode["return"], episode["length"]) == (353.0, 4000), episode


@pytest.mark.slow
def test_a_breakout_run_stored_before_observation_versions_replays_with_8_pixel_bricks(tmp_path, monkeypatch):
    """The fixture was written by the code before versions were recorded (tests/fixtures/
    make_breakout_v1_run.py): its config has no version, its prompts show 8-pixel bricks, and it reads back,
    replays prompt for prompt and score for score, and rebuilds its frames with them."""
    path = tmp_path / "old.duckdb"
    path.write_bytes(gzip.decompress(FIXTURE.read_bytes()))
    store = Store(path)
    (run_id, config), = store.query("SELECT run_id, config FROM runs")
    assert "observation" not in json.loads(config)
    prompts = [p for (p,) in store.query("SELECT b.text FROM llm_calls c JOIN blobs b ON b.hash = c.prompt_hash "
                                         "WHERE c.run_id = ? ORDER BY c.iteration", [run_id])]
    assert prompts and all("RB[18] y=57 w=8 h=6 x=8,16,24" in p for p in prompts)

    report = replay(store, run_id)
    assert report.status == "finished" and report.diverged_at is None, report.as_dict()
    assert len(report.rows) == 3 and all(r.matches for r in report.rows)
    replayed = json.loads(store.query("SELECT config FROM runs WHERE run_id = ?", [report.replay_run_id])[0][0])
    assert replayed["observation"] == 1

    old = get_game("breakout").observing(1)
    with store.read() as con:
        (episode_id,) = con.execute("SELECT train_episode_id FROM iterations WHERE run_id = ? AND iteration = 1",
                                    [report.replay_run_id]).fetchone()
        steps = episode_steps(con, episode_id, list_widths=old.list_widths, derive=old.derive)
        as_today = episode_steps(con, episode_id, 0, 1)
        stored = read_episode(con, episode_id)
    assert all(b["w"] == 8 for row in ROWS for b in steps[0]["obs"][row]) and len(steps[0]["obs"]["RB"]) == 18
    assert as_today[0]["obs"]["RB"] == [{"x": 8, "y": 57, "w": 144, "h": 6, "dx": 0, "dy": 0}], \
        "the stored rows are runs either way: the recorded version decides what the policy was shown"
    assert stored.observation == 1
    _, _, check = replay_frames(stored.episode, stored.steps, 20, stored.observation)
    assert check.faithful and check.steps_compared == len(steps), check.describe()

    from pipeline.optimizer import config  # had the run not recorded its version, it would not replay
    monkeypatch.setitem(config.BEFORE_RECORDED, "observation", 2)
    assert replay(store, run_id).diverged_at == 1


# --- the authors' saved Breakout run ------------------------------------------------------------------------

AUTHORS_REPO = Path(os.environ.get("CODEARCADE_AUTHORS_REPO", "/nonexistent"))
"""A clone (or bare git directory) of github.com/ameliakuang/LLM-Game-Playing-Agents, named by
``CODEARCADE_AUTHORS_REPO``; the tests that read it skip without it."""
AUTHORS_RUN_COMMIT = "abb46a11e342c4e852fbeead4b33071cdbba9600"
"""The commit that added their Breakout run of 2025-03-12 (its checkpoints were deleted later)."""
AUTHORS_RUN = "BreakoutNoFrameskip-v4_20250312_190211_skip4_sticky0.0_horizon300_optimSteps100_mem5"
TRAINABLE = ("predict_ball_trajectory", "generate_paddle_target", "select_paddle_action")


def _git(*args: str) -> bytes:
    return subprocess.run(["git", f"--git-dir={_git_dir()}", *args], capture_output=True, check=True).stdout


def _git_dir() -> Path:
    return AUTHORS_REPO / ".git" if (AUTHORS_REPO / ".git").exists() else AUTHORS_REPO


def _checkpoint_sources(pickle_bytes: bytes) -> dict[str, str]:
    """The trainable methods' sources in a Trace checkpoint, read from the pickle's opcodes: a checkpoint is
    untrusted and is never unpickled (that would run whatever it names)."""
    sources = {}
    for _, arg, _ in pickletools.genops(pickle_bytes):
        if isinstance(arg, str) and arg.startswith("def ") and "(" in arg:
            sources[arg[4:arg.index("(")].strip()] = arg
    return sources


def _policy_file(sources: dict[str, str]) -> str:
    """The methods (``def`` at column 0, bodies at 8 spaces, as Trace saves them) in the paper's Breakout
    class, with codearcade's ``tracing`` in place of Trace."""
    text = ('import tracing as trace\n\nGAME = "breakout"\n\n\n@trace.model\nclass Policy(trace.Module):\n'
            "    def __call__(self, obs):\n"
            "        pre_ball_x = self.predict_ball_trajectory(obs)\n"
            "        target_paddle_pos = self.generate_paddle_target(pre_ball_x, obs)\n"
            "        return self.select_paddle_action(target_paddle_pos, obs)\n")
    for name in TRAINABLE:
        first, _, rest = sources[name].partition("\n")
        text += f"\n    @trace.bundle(trainable=True)\n    {first}\n{rest}\n"
    return text


@pytest.mark.skipif(not _git_dir().exists(), reason="the authors' repository is not fetched here "
                                                    "(CODEARCADE_AUTHORS_REPO)")
def test_the_authors_saved_breakout_policies_score_what_their_run_logged(tmp_path):
    """Their run of 2025-03-12 saved the policy of each iteration it evaluated (1 game, 4,000 steps,
    deterministic) beside the logged score: every distinct policy scores here what it scored there."""
    logged = {}
    csv = _git("show", f"{AUTHORS_RUN_COMMIT}:logs/perf_{AUTHORS_RUN}.csv").decode().splitlines()
    for line in csv[1:]:
        step, mean, _ = line.split(",")
        logged[int(step)] = float(mean)
    policy_at = {}  # checkpoint -> its policy's text
    for step in sorted(logged):
        sources = _checkpoint_sources(_git("show", f"{AUTHORS_RUN_COMMIT}:trace_ckpt/{AUTHORS_RUN}/{step}.pkl"))
        policy_at[step] = _policy_file(sources)
    first_at = {text: step for step, text in sorted(policy_at.items(), reverse=True)}
    assert len(first_at) == 7 and len(logged) == 30
    assert [logged[step] for step in sorted(first_at.values())] == [0, 329, 34, 238, 45, 34, 27]

    store = Store(tmp_path / "authors.duckdb")
    scored = {}
    for text, step in first_at.items():
        path = tmp_path / f"checkpoint_{step}.py"
        path.write_text(text)
        result = evaluate(path, EvalConfig(max_steps=4000, workers=1), store)
        scored[text] = result.summary()["episodes"][0]["return"]
    assert {step: scored[text] for step, text in policy_at.items()} == logged, \
        "every checkpoint (the 7 distinct policies and their 23 repeats) scores what the run logged for it"
