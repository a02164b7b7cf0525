"""Score verification fed while the episode plays: the same replay as one made at the end, and a report that
does not match the recorded actions is not trusted; and the replay of a game stored in an environment of before."""

from __future__ import annotations

import random
from pathlib import Path

from pipeline.play.spec import EpisodeSpec
from pipeline.play.verify import Replay, replay_actions

SCAFFOLD = Path(__file__).resolve().parents[1] / "games" / "scaffolds" / "breakout.py"


def _spec(game="breakout", seed=3):
    return EpisodeSpec(episode_id="e", run_id="r", game=game, policy_text="", policy_version_id="v", seed=seed,
                       sticky=0.25, noop_max=30)


def test_fed_in_chunks_equals_replayed_at_the_end():
    rng = random.Random(0)
    actions = [rng.randrange(4) for _ in range(900)]
    whole = replay_actions(_spec(), actions)
    streamed = Replay(_spec())
    for start in range(0, 750, 250):
        streamed.feed(actions[start:start + 250])
    final = replay_actions(_spec(), actions, streamed)
    assert final is streamed and final.length == whole.length
    assert (final.rewards, final.lives, final.terminated, final.lives_lost) == \
        (whole.rewards, whole.lives, whole.terminated, whole.lives_lost)
    assert sum(whole.rewards) > 0, "the random actions scored: the comparison is not trivially of zeros"


def test_a_report_that_differs_from_the_recorded_actions_is_replayed_again():
    rng = random.Random(1)
    actions = [rng.randrange(4) for _ in range(600)]
    whole = replay_actions(_spec(), actions)
    lied = Replay(_spec())
    lied.feed([3] * 250)  # not what the episode recorded
    final = replay_actions(_spec(), actions, lied)
    assert final is not lied and final.actions == whole.actions and final.rewards == whole.rewards


def test_a_game_stored_before_the_second_serve_still_replays_as_stored(tmp_path, monkeypatch, capsys):
    """A Breakout game stored before ``games.wrappers.ServeAgain`` (2026-12-05) whose serve sticky actions swallowed
    went on without a ball; today's environment serves it again at step 30, so its recorded actions play another
    game. ``doctor --replay`` and the viewer's frames replay it in the environment it was played in, and only
    there: a reward changed in it is still caught."""
    from games.wrappers import ServeAgain
    from pipeline.cli import main
    from pipeline.play.verify import replay_run
    from store import Store
    from viewers.rerun_replay import read_episode, replay_frames

    path = tmp_path / "s.duckdb"
    with monkeypatch.context() as before:
        before.setattr(ServeAgain, "AFTER", 10**9)  # the environment of before: no second serve
        # seed 39 under the standard protocol: the reset's FIRE is swallowed (found by the sweep of 60 seeds)
        assert main(["eval", str(SCAFFOLD), "--sticky", "0.25", "--noop-max", "30", "--one-life", "--seed", "39",
                     "--episodes", "1", "--max-steps", "200", "--workers", "0", "--store", str(path)]) == 0
    store = Store(path)
    (run_id, episode_id, length, score, reason, balls), = store.query(
        "SELECT run_id, episode_id, length, return, end_reason, (SELECT count(ball_x) FROM steps s "
        "WHERE s.episode_id = e.episode_id) FROM episodes e")
    assert (length, score, reason, balls) == (200, 0.0, "truncated", 0), "the stalled game of before"

    with store.read() as con:
        actions = [a for a, in con.execute("SELECT action FROM steps WHERE episode_id = ? ORDER BY step",
                                           [episode_id]).fetchall()]
    today = replay_actions(EpisodeSpec(episode_id="e", run_id="r", game="breakout", policy_text="",
                                       policy_version_id="v", seed=39, sticky=0.25, noop_max=30, one_life=True),
                           actions)
    assert (today.length, today.terminated[-1]) != (200, False), "today's environment plays another game"

    assert main(["doctor", "--replay", run_id, "--store", str(path)]) == 0
    assert "1 as stored" in capsys.readouterr().out
    with store.read() as con:
        stored = read_episode(con, episode_id)
    _, _, check = replay_frames(stored.episode, stored.steps, 50, stored.observation)
    assert check.faithful and check.steps_compared == 200, check.describe()

    with store.write() as con:
        con.execute("UPDATE steps SET reward = 4, score = 4 WHERE episode_id = ? AND step = 120", [episode_id])
    (_, why), = replay_run(store, run_id)
    assert why is not None, "a changed reward replays in neither environment"
