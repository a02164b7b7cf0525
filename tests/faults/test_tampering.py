"""Scores a policy cannot touch: the game host computes them where no policy code runs (pipeline/play/rollout.py).

Before the game host, the policy ran in the process that held the emulator, and this policy reached it through a
module that re-exports ``sys`` and wrapped ``step`` to add one point per step (a 600-step Pong episode reported
about +584; the parent caught it by replaying every episode). Now the policy process holds no environment to
wrap: the same code, as a policy file and as an LLM reply, scores exactly what an honest policy that plays the
same actions scores, step for step. ``codearcade doctor --replay RUN`` re-checks a stored run by replay, and finds
a score edited in the store afterwards.
"""

from __future__ import annotations

import json
import textwrap

import pytest

from pipeline.cli import main
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.play.rollout import EpisodeOutcome, run_episode
from pipeline.play.spec import EpisodeSpec
from pipeline.play.verify import checked_outcome, replay_outcome
from tests.conftest import json_reply, pong_policy, random_policy

TAMPER_BODY = """
mods = typing.sys.modules
targets = []
for name in ("games.envs", "ale_py", "gymnasium"):
    try:
        targets.append(mods.get(name) or mods["importlib"].import_module(name))
    except Exception:
        pass
for module in targets:
    for env in list(getattr(module, "_shared", {}).values()):
        if not getattr(env, "tampered", False):
            orig = env.step
            def step(action, orig=orig):
                o, r, te, tr, i = orig(action)
                return o, r + 1.0, te, tr, i
            env.step = step
            env.tampered = True
try:
    for found in mods["importlib"].import_module("gc").get_objects():
        if callable(getattr(found, "step", None)) and not getattr(found, "tampered", False):
            orig = found.step
            found.step = lambda action, orig=orig: orig(action)
            found.tampered = True
except Exception:
    pass
return 0
"""
TAMPERING_POLICY = pong_policy(TAMPER_BODY, prelude="import typing\n")
HONEST_POLICY = pong_policy("return 0")

TAMPER_SELECT = "def select_action(self, predicted_ball_y, obs):\n    import typing\n" + textwrap.indent(
    TAMPER_BODY.strip("\n"), "    ") + "\n"


def _spec(text: str, **kwargs) -> EpisodeSpec:
    defaults = dict(episode_id="r.0.eval.0", run_id="r", game="pong", policy_text=text, policy_version_id="v",
                    max_steps=600)
    return EpisodeSpec(**{**defaults, **kwargs})


@pytest.mark.slow
def test_a_tampering_policy_file_scores_what_its_actions_score(store, write_policy, capsys):
    honest = write_policy(HONEST_POLICY, "honest.py")
    assert main(["eval", str(honest), "--max-steps", "600", "--store", str(store.path), "--json"]) == 0
    true_return = json.loads(capsys.readouterr().out)["episodes"][0]["return"]

    path = write_policy(TAMPERING_POLICY, "tamper.py")
    code = main(["eval", str(path), "--max-steps", "600", "--store", str(store.path), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    episode = json.loads(out)["episodes"][0]
    assert episode["end_reason"] == "truncated" and episode["return"] == true_return < 0
    rewards = store.query("SELECT e.policy_version_id, list(s.reward ORDER BY s.step) FROM steps s "
                          "JOIN episodes e USING (episode_id) GROUP BY ALL")
    assert len(rewards) == 2 and rewards[0][1] == rewards[1][1], "the same rewards, step for step"
    assert store.query("SELECT bool_and(verified) FROM episodes") == [(True,)]
    run = store.query("SELECT run_id FROM runs ORDER BY created_at DESC LIMIT 1")[0][0]
    assert main(["doctor", "--replay", run, "--store", str(store.path)]) == 0, capsys.readouterr()


@pytest.mark.slow
def test_a_tampering_candidate_scores_no_more_than_its_actions(store, scripted):
    model = scripted([json_reply({"select_action": TAMPER_SELECT})])
    client = LiteLLMClient(model.model, api_base=model.api_base, retries=0)
    config = OptimizeConfig(game="pong", iterations=1, eval_max_steps=600, rollout_steps=60, token_budget=8000,
                            workers=2, rng_key="tamper")
    result = optimize(config, store, client)
    assert result.status == "finished", result.error
    rows = store.query("SELECT iteration, score FROM iterations ORDER BY iteration")
    assert len(rows) == 2 and all(score < 0 for _, score in rows), "no inflated score is recorded"
    honest = run_episode(_spec(HONEST_POLICY))
    tampering = store.query("SELECT e.\"return\" FROM episodes e JOIN iterations i ON e.episode_id = "
                            "i.eval_episode_ids[1] WHERE i.iteration = 1")
    assert tampering == [(honest.episode["return"],)]


@pytest.mark.parametrize("game, sticky, noop_max", [("pong", 0.25, 30), ("breakout", 0.25, 30),
                                                     ("space_invaders", 0.0, 0), ("breakout", 0.0, 0)])
def test_a_stored_episode_replays_under_both_protocols(game, sticky, noop_max):
    text = random_policy(game, "random.randrange(4)")
    spec = _spec(text, game=game, sticky=sticky, noop_max=noop_max, seed=3, max_steps=800)
    outcome = run_episode(spec)
    assert replay_outcome(spec, outcome.episode, outcome.steps) is None
    edited = outcome.steps.set_column(
        outcome.steps.schema.get_field_index("reward"), "reward",
        [[r + (1.0 if i == 10 else 0.0) for i, r in enumerate(outcome.steps.column("reward").to_pylist())]])
    assert "step 10: recorded reward" in replay_outcome(spec, outcome.episode, edited)


def test_doctor_replay_finds_a_score_edited_in_the_store(store, capsys):
    from tests.conftest import EXAMPLES

    assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "300", "--store", str(store.path)]) == 0
    run = store.query("SELECT run_id FROM runs")[0][0]
    assert main(["doctor", "--replay", run, "--store", str(store.path)]) == 0
    capsys.readouterr()
    with store.write() as con:
        con.execute("UPDATE steps SET reward = reward + 1 WHERE step = 100")
        con.execute("UPDATE episodes SET \"return\" = \"return\" + 1")
    assert main(["doctor", "--replay", run, "--store", str(store.path)]) == 1
    out = capsys.readouterr().out
    assert "step 100: recorded reward" in out


def test_a_forged_episode_row_cannot_redirect_or_inflate():
    spec = _spec(HONEST_POLICY, max_steps=50)
    outcome = run_episode(spec)
    outcome.episode.update({"episode_id": "other.0.eval.0", "run_id": "other", "seed": 99,
                            "evil); DROP TABLE steps; --": 1, "end_reason": "won"})
    row = checked_outcome(spec, outcome).episode
    assert (row["episode_id"], row["run_id"], row["seed"]) == (spec.episode_id, spec.run_id, spec.seed)
    assert not any("DROP" in k for k in row)
    assert row["end_reason"] == "tampered"


def test_a_malformed_step_table_is_kept_out():
    spec = _spec(HONEST_POLICY, max_steps=50)
    outcome = run_episode(spec)
    outcome.steps = "not a table"
    checked = checked_outcome(spec, outcome)
    assert checked.episode["end_reason"] == "crashed" and checked.steps.num_rows == 0
    assert "malformed" in checked.episode["error"]


def test_anything_sent_becomes_a_marked_episode():
    spec = _spec(HONEST_POLICY, max_steps=50)
    for sent in (None, "an outcome", EpisodeOutcome(episode="row", steps=None, nodes=42)):
        checked = checked_outcome(spec, sent)
        assert checked.episode["episode_id"] == spec.episode_id and checked.episode["end_reason"] == "crashed"
        assert checked.steps.num_rows == 0
