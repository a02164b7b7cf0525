"""Score verification fed while the episode plays: the same replay as one made at the end, and a report that
does not match the recorded actions is not trusted."""

from __future__ import annotations

import random

from pipeline.play.spec import EpisodeSpec
from pipeline.play.verify import Replay, replay_actions


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
