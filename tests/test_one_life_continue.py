"""The authors' one-life protocol exactly (``--one-life-continue``, ``one_life = "continue"``; issue 25 item 3).

Their follow-up (ameliakuang/LLM-Game-Playing-Agents: ``trace_envs/<game>.py``, baselines' ``EpisodicLifeEnv``,
and ``evaluate_policy`` in ``training_utils.py``) plays N evaluation episodes with one environment and one
policy object: an episode ends, terminated, on the step whose lives fell while still above 0, and the next
goes on with the same game after one NOOP whose reward is dropped (Breakout: then a FIRE, dropped too); after a
real game over the environment is reset. Here: one game host and one policy process play a game's episodes in
order; each is stored as an episode that ``continues`` the one before, reproducible from the game's seed and
the actions (``doctor --replay``). The environments below that check it are built from gymnasium's ALE and our
object extraction only, with the authors' steps written out by hand.
"""

from __future__ import annotations

import json
import subprocess
import sys

import gymnasium as gym
import pytest

from games import get_game
from games.envs import ObjectObservation
from pipeline.cli import main
from pipeline.play.spec import EpisodeSpec
from pipeline.play.verify import replay_outcome, replay_run
from store.readers import episode_steps, replay_material
from store.showing import lead_in_actions
from tests.conftest import EXAMPLES, POLICIES, ROOT

NOOP, FIRE = 0, 1


def evaluate(capsys, store, policy, *extra) -> dict:
    code = main(["eval", str(policy), "--store", str(store.path), "--json", *map(str, extra)])
    out, err = capsys.readouterr()
    assert code in (0, 1), err
    return json.loads(out)


def stored(store, game: str, episode_id: str) -> list[dict]:
    spec = get_game(game)
    with store.read() as con:
        return episode_steps(con, episode_id, list_widths=spec.list_widths, derive=spec.derive)


def rows(store, run_id: str) -> list[tuple]:
    return store.query('SELECT episode_index, seed, continues, start_step, length, "return", end_reason, lives_lost, '
                       "verified FROM episodes WHERE run_id = ? ORDER BY episode_index", [run_id])


def bare_env(game: str):
    """The game's objects over plain ALE in the paper's setting: none of codearcade's protocol wrappers (no
    FIRE after reset, nothing at a lost life), for the authors' steps to be taken by hand."""
    spec = get_game(game)
    ale = gym.make(spec.env_id, obs_type="ram", frameskip=4, repeat_action_probability=0.0, full_action_space=False,
                   disable_env_checker=True)
    return ObjectObservation(ale, spec)


@pytest.mark.slow
def test_a_continued_asterix_game_goes_on_where_each_life_was_lost(store, capsys, tmp_path):
    """Four episodes of the (random, seeded) starter: lives 1-3 of one game, then, after the game over, the first
    life of the next game (their evaluation resets on a real game over), all from seed 0."""
    summary = evaluate(capsys, store, EXAMPLES / "asterix.py", "--one-life-continue", "--episodes", 4,
                       "--max-steps", 4000, "--rng-key", "asterix")
    run_id, episodes = summary["run_id"], summary["episodes"]
    table = rows(store, run_id)
    assert [r[1] for r in table] == [0, 0, 0, 0], "every episode has the game's seed"
    ids = [e["episode_id"] for e in episodes]
    assert [r[2] for r in table] == [None] + ids[:-1], "each continues the one before"
    lengths = [r[4] for r in table]
    assert [r[3] for r in table] == [0, lengths[0], lengths[0] + lengths[1], sum(lengths[:3])]
    assert all(r[6] == "terminated" and r[7] == 1 and r[8] is True for r in table)

    steps = [stored(store, "asterix", i) for i in ids]
    assert [s[0]["lives"] for s in steps] == [3, 2, 1, 3], "lives 3, 2, 1 of the first game, then a new game"

    # episode 2's first observation is what the game gives after episode 1's actions and one NOOP
    env = bare_env("asterix")
    obs, _ = env.reset(seed=0)
    assert obs == steps[0][0]["obs"]
    for step in steps[0]:
        obs, reward, *_ = env.step(step["action"])
        assert reward == step["reward"]
    obs, _, terminated, truncated, info = env.step(NOOP)
    assert not (terminated or truncated) and info["lives"] == 2
    assert obs == steps[1][0]["obs"], "the next episode starts after one NOOP, where the life was lost"
    for step in steps[1]:
        assert obs == step["obs"]
        obs, reward, *_ = env.step(step["action"])
        assert reward == step["reward"]
    assert steps[1][-1]["score"] == episodes[1]["return"] == sum(s["reward"] for s in steps[1]), \
        "the NOOP's reward is not the episode's"

    # doctor --replay replays them in order, each from where the one before ended; from reset(seed) the second
    # would not replay (a different game state), so the replay did continue
    assert replay_run(store, run_id) == [(i, None) for i in ids]
    with store.read() as con:
        row, recorded = next((r, s) for r, s in replay_material(con, run_id) if r["episode_id"] == ids[1])
    alone = EpisodeSpec(episode_id=ids[1], run_id=run_id, game="asterix", policy_text="", policy_version_id="",
                        seed=0, max_steps=4000, one_life="continue")
    assert replay_outcome(alone, row, recorded) is not None
    code = main(["doctor", "--replay", run_id, "--store", str(store.path)])
    out, _ = capsys.readouterr()
    assert code == 0 and "replayed 4 episode(s): 4 as stored" in out, out

    # the frames of `codearcade view` come from the same replay: the third episode after the first two's actions
    # (the command runs apart: loading the Rerun SDK into this process would stay for the tests after this one)
    with store.read() as con:
        assert [len(actions) for actions in lead_in_actions(con, ids[2])] == lengths[:2]
    shown = subprocess.run([sys.executable, "-m", "pipeline.cli", "view", run_id, "--episode", "2", "--save",
                            str(tmp_path / "third.rrd"), "--store", str(store.path)], cwd=ROOT, capture_output=True,
                           text=True, timeout=300)
    assert shown.returncode == 0, shown.stderr
    assert f"replayed frames match the stored objects on all {lengths[2]} steps" in shown.stdout, shown.stdout

    # a stored reward changed in the third episode is caught by the replay there, and only there
    with store.write() as con:
        con.execute("UPDATE steps SET reward = reward + 50 WHERE episode_id = ? AND step = 3", [ids[2]])
    found = dict(replay_run(store, run_id))
    assert [i for i in ids if found[i]] == [ids[2]] and "step 3: recorded reward" in found[ids[2]]

    # the doctor finds a game whose episodes do not add up
    with store.write() as con:
        con.execute("UPDATE episodes SET start_step = start_step + 1 WHERE episode_id = ?", [ids[3]])
    code = main(["doctor", "--store", str(store.path)])
    out, _ = capsys.readouterr()
    assert code == 1 and f"episodes that continue a game that is not there: 1 — {ids[3]}" in out, out


def test_breakout_continues_with_a_noop_then_a_fire_and_drops_both_rewards(store, capsys):
    """Breakout: their reset presses FIRE after the real reset and after the NOOP of a continued game; their step
    that loses a ball presses nothing more (codearcade's whole games and ``--one-life`` FIRE inside that step)."""
    summary = evaluate(capsys, store, EXAMPLES / "breakout.py", "--one-life-continue", "--episodes", 3,
                       "--max-steps", 4000, "--workers", 0)
    ids = [e["episode_id"] for e in summary["episodes"]]
    steps = [stored(store, "breakout", i) for i in ids]
    assert [s[0]["lives"] for s in steps] == [5, 4, 3]

    env = bare_env("breakout")
    env.reset(seed=0)
    obs, *_ = env.step(FIRE)
    assert obs == steps[0][0]["obs"], "FIRE after the reset"
    for k in (0, 1):
        for step in steps[k]:
            assert obs == step["obs"]
            obs, reward, terminated, *_ = env.step(step["action"])
            assert reward == step["reward"] and terminated is False
        noop, *_ = env.step(NOOP)
        assert noop != steps[k + 1][0]["obs"], "the NOOP alone is not where the next episode starts"
        obs, *_ = env.step(FIRE)
        assert obs == steps[k + 1][0]["obs"], "NOOP, then FIRE"
        assert summary["episodes"][k]["return"] == sum(s["reward"] for s in steps[k]) == steps[k][-1]["score"]
    assert replay_run(store, summary["run_id"]) == [(i, None) for i in ids]


COUNTING_POLICY = """
    import random

    import tracing as trace

    GAME = "asterix"
    FAIL_AT = {fail_at}


    @trace.model
    class Policy(trace.Module):

        def __call__(self, obs):
            self.count(obs)
            return random.choice([1, 2, 3, 4, 5, 6, 7, 8])

        @trace.bundle(trainable=True)
        def count(self, obs):
            \"\"\"How many observations this policy object has been shown.\"\"\"
            self.seen = getattr(self, "seen", 0) + 1
            if self.seen == FAIL_AT:
                raise RuntimeError("enough")
            return self.seen
"""


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 0])
def test_one_policy_object_plays_the_whole_game(store, capsys, write_policy, workers):
    """Their ``evaluate_policy`` calls one policy object for every episode: its state (and its RNG) goes on
    from one life to the next, in the policy process (``--workers 1``) as in this process (``--workers 0``).
    A policy failure ends the game: the lives after it are not played."""
    policy = write_policy(COUNTING_POLICY.format(fail_at=0))
    summary = evaluate(capsys, store, policy, "--one-life-continue", "--episodes", 3, "--trace", "--workers", workers,
                       "--rng-key", "counting")  # the failing twin below draws the same numbers
    ids = [e["episode_id"] for e in summary["episodes"]]
    lengths = [e["length"] for e in summary["episodes"]]
    first_counts = [int(store.query("SELECT output FROM nodes WHERE episode_id = ? AND step = 0 AND function = "
                                    "'count'", [i])[0][0]) for i in ids]
    assert first_counts == [1, lengths[0] + 1, lengths[0] + lengths[1] + 1]
    seen_first = evaluate(capsys, store, policy, "--one-life", "--episodes", 3, "--trace", "--workers", workers)
    assert [int(store.query("SELECT output FROM nodes WHERE episode_id = ? AND step = 0 AND function = 'count'",
                            [e["episode_id"]])[0][0]) for e in seen_first["episodes"]] == [1, 1, 1], \
        "--one-life: a fresh policy for each seeded game"

    failing = write_policy(COUNTING_POLICY.format(fail_at=lengths[0] + 5), "failing.py")
    broken = evaluate(capsys, store, failing, "--one-life-continue", "--episodes", 3, "--workers", workers,
                      "--rng-key", "counting")
    (first, second, third) = broken["episodes"]
    assert (first["length"], first["end_reason"]) == (lengths[0], "terminated"), "the same game until it fails"
    assert (second["length"], second["end_reason"]) == (4, "policy_error") and "enough" in second["error"]
    assert (third["length"], third["end_reason"], third["return"]) == (0, "policy_error", 0.0)
    assert third["error"].startswith("not played: episode 1 of this game ended with policy_error")
    assert store.query("SELECT count(*) FROM steps WHERE episode_id = ?", [second["episode_id"]])[0][0] == 5


@pytest.mark.slow
def test_the_competent_asterix_policy_scores_their_figure_under_their_protocol(store, capsys):
    """3 x 20,000 (their Asterix evaluation) of tests/policies/asterix_competent.py: lives 1-3 of one game score
    3,400, 32,300 and 6,800, mean 14,166.7 (their 14,167: docs/games.md, section Games), where ``--one-life`` (the
    first life of three seeded games) gives 3,400."""
    summary = evaluate(capsys, store, POLICIES / "asterix_competent.py", "--one-life-continue", "--episodes", 3,
                       "--max-steps", 20000, "--workers", 1)
    returns = [e["return"] for e in summary["episodes"]]
    assert returns == [3400.0, 32300.0, 6800.0] and round(sum(returns) / 3) == 14167
    assert [e["end_reason"] for e in summary["episodes"]] == ["terminated"] * 3
    assert store.query("SELECT json_extract_string(config, '$.one_life') FROM runs WHERE run_id = ?",
                       [summary["run_id"]]) == [("continue",)]


def test_the_two_one_life_flags_exclude_each_other(capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["eval", str(EXAMPLES / "asterix.py"), "--one-life", "--one-life-continue"])
    _, err = capsys.readouterr()
    assert stopped.value.code == 2 and "--one-life-continue: not allowed with argument --one-life" in err


def test_a_host_that_plays_on_after_the_policy_failed_is_not_believed(write_policy):
    """The parent checks a game's answer as a game: as many episodes as asked, none played after the policy
    failed; ``start_step`` is its own sum of the lengths."""
    from pipeline.boundary import wire
    from pipeline.boundary.wire import BadMessage
    from pipeline.play.episodes import _decode_game, episode_to_json
    from pipeline.play.rollout import run_game

    text = (EXAMPLES / "asterix.py").read_text()
    specs = [EpisodeSpec(episode_id=f"r.0.eval.{i}", run_id="r", game="asterix", policy_text=text,
                         policy_version_id="v", index=i, max_steps=4000, one_life="continue",
                         continues=f"r.0.eval.{i - 1}" if i else None) for i in range(3)]
    outcomes = run_game(specs)

    def answer(outcomes, start_steps=None):
        rows = [episode_to_json(o.episode) for o in outcomes]
        for row, step in zip(rows, start_steps or []):
            row["start_step"] = step
        tables = [wire.arrow_frame(o.steps)[wire.HEADER.size:] for o in outcomes]
        return {"kind": "result", "episodes": rows, "nodes": [False] * len(rows)}, tables

    decoded = _decode_game(specs, *answer(outcomes, start_steps=[7, 7, 7]))
    lengths = [o.episode["length"] for o in outcomes]
    assert [o.episode["start_step"] for o in decoded] == [0, lengths[0], lengths[0] + lengths[1]]
    with pytest.raises(BadMessage, match="another number of episodes"):
        _decode_game(specs, *answer(outcomes[:2]))
    outcomes[0].episode["end_reason"] = "policy_error"
    with pytest.raises(BadMessage, match="played after its game ended"):
        _decode_game(specs, *answer(outcomes))


@pytest.mark.slow
def test_the_optimizer_evaluates_the_lives_of_one_game(store, scripted):
    """``optimize --one-life-continue``: the training rollout is the first life of the game, the evaluation episodes
    its lives in order; the run records the protocol, and ``doctor --replay`` replays it all."""
    from pipeline.llm.client import LiteLLMClient
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.loop import optimize
    from tests.conftest import json_reply

    model = scripted([json_reply({})])
    config = OptimizeConfig(game="asterix", iterations=1, eval_episodes=3, eval_max_steps=4000, rollout_steps=4000,
                            workers=2, token_budget=6000, one_life="continue", rng_key="lives")
    result = optimize(config, store, LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05))
    assert result.status == "finished", result.error
    episodes = store.query("SELECT iteration, kind, episode_index, seed, continues, start_step, length, lives_lost, "
                           "end_reason FROM episodes WHERE run_id = ? AND kind <> 'audit' "
                           "ORDER BY iteration, kind <> 'train', episode_index", [result.run_id])
    assert {e[0] for e in episodes} == {0}, "iteration 1's unchanged version reused iteration 0's episodes"
    train, *evals = episodes
    assert train[1:6] == ("train", 0, 0, None, 0) and train[7:] == (1, "terminated")
    assert [e[1:4] for e in evals] == [("eval", i, 0) for i in range(3)]
    assert [e[4] is None for e in evals] == [True, False, False]
    assert [e[5] for e in evals] == [0, evals[0][6], evals[0][6] + evals[1][6]]
    assert train[6] == evals[0][6], "the training rollout is the game's first life, as its first episode"
    assert store.query("SELECT json_extract_string(config, '$.one_life') FROM runs WHERE run_id = ?",
                       [result.run_id]) == [("continue",)]
    # audited under its own protocol too: per protocol, the lives of one sealed game, each going on from the last
    audit = store.query("SELECT episode_id, episode_index, seed, continues, start_step, length FROM episodes "
                        "WHERE run_id = ? AND kind = 'audit' AND episode_id LIKE '%audit-run%' ORDER BY episode_index",
                        [result.run_id])
    assert [a[1] for a in audit] == [0, 1, 2] and len({a[2] for a in audit}) == 1 and audit[0][2] >= 1_000_000
    assert [a[3] for a in audit] == [None, audit[0][0], audit[1][0]]
    assert [a[4] for a in audit] == [0, audit[0][5], audit[0][5] + audit[1][5]]
    assert all(why is None for _, why in replay_run(store, result.run_id))
    # `audit --seeds` with the seeds its audits rows list (the one game's seed once a life) plays it again as it
    # was: it was refused ("each seed once"), and one seed given once replaced the audit by one life (n=1)
    stored = store.query("SELECT role, protocol, seeds, score, score_low, score_high FROM audits ORDER BY ALL")
    # each game less its audit's token (a re-audit's games have ids of their own)
    audited = ("SELECT regexp_replace(episode_id, '[.][^.]*$', '') AS game, seed, \"return\", length FROM episodes "
               "WHERE kind = 'audit' ORDER BY 1")
    games = store.query(audited)
    seeds = ",".join(map(str, stored[0][2]))
    assert len(stored[0][2]) == 3
    assert main(["audit", result.run_id, "--seeds", seeds, "--store", str(store.path)]) == 0
    assert store.query("SELECT role, protocol, seeds, score, score_low, score_high FROM audits ORDER BY ALL") == stored
    assert store.query(audited) == games
    other = f"{stored[0][2][0]},{stored[0][2][0] + 1}"  # two games: not this run's audit
    assert main(["audit", result.run_id, "--seeds", other, "--store", str(store.path)]) == 2
    assert store.query("SELECT role, protocol, seeds, score, score_low, score_high FROM audits ORDER BY ALL") == stored


def test_experiment_files_take_the_protocol_and_the_benchmarks_use_it_where_the_authors_did(tmp_path):
    from games import GAMES
    from pipeline.jobs.experiments import ExperimentError, load_experiments
    from tests.conftest import ROOT

    runs = {r.config.game: r.config for r in load_experiments(ROOT / "examples" / "benchmarks.toml").runs}
    assert {game: config.one_life for game, config in runs.items()} == {
        name: "continue" if game.task.one_life_episodes else False for name, game in GAMES.items()}
    path = tmp_path / "bad.toml"
    path.write_text('name = "x"\n[[run]]\ngame = "asterix"\none_life = "sometimes"\n')
    with pytest.raises(ExperimentError) as err:
        load_experiments(path)
    assert "one_life must be false, true" in str(err.value) and "\n" not in str(err.value)


def test_the_gymnasium_environment_continues_the_game_on_reset():
    """``gymnasium.make("codearcade/Asterix-v0", one_life="continue")``: ``reset()`` goes on with the game (a
    standing player loses a life at a time), ``reset(seed=...)`` and a game over start a new one."""
    import games.envs  # noqa: F401 - registers the ids

    env = gym.make("codearcade/Asterix-v0", one_life="continue")
    played = []
    for k in range(4):
        obs, info = env.reset(seed=0) if k == 0 else env.reset()
        assert obs in env.observation_space
        first_lives, steps = info["lives"], 0
        while True:
            obs, _, terminated, truncated, info = env.step(NOOP)
            steps += 1
            if terminated or truncated:
                break
        played.append((first_lives, info["lives"], steps, terminated))
    assert [p[:2] for p in played] == [(3, 2), (2, 1), (1, 0), (3, 2)]
    assert all(p[3] for p in played) and played[3][2] == played[0][2], "after the game over, the same new game"
    obs, info = env.reset(seed=0)
    assert info["lives"] == 3, "a seed starts a new game wherever the last one was"


def test_eval_does_not_call_the_lives_of_one_game_that_game_again(store, capsys):
    """Under the paper's protocol eval notes that repeated episodes are one game again, and its interval only the
    policy's own draws; under --one-life-continue the episodes are the lives of one game, and no such note is
    printed (a reviewer saw it after three lives returning 3,400, 32,300 and 6,800)."""
    from pipeline.cli.eval import PAPER_PROTOCOL_NOTE

    code = main(["eval", str(EXAMPLES / "breakout.py"), "--one-life-continue", "--episodes", "2", "--max-steps",
                 "60", "--store", str(store.path)])
    out = capsys.readouterr().out
    assert code == 0 and "2 episode" in out, out
    assert PAPER_PROTOCOL_NOTE not in out
