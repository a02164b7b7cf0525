"""Scores a policy cannot touch (pipeline/play/verify.py): the parent replays every episode's actions.

The tampering policy below really inflates its score without verification: it reaches the worker's
environment through a module that re-exports ``sys`` and wraps ``step`` to add one point per step (a
600-step Pong episode reports about +584). The first test shows that on the raw worker outcome, then that
``codearcade eval`` stores the true score, marked ``tampered``, and exits 1; the second sends the same code as
an LLM reply and checks it is rejected, never the best version.
"""

from __future__ import annotations

import json
import textwrap

import pytest

from pipeline.cli import main
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.play.episodes import run_episodes
from pipeline.play.rollout import EpisodeOutcome, EpisodeSpec, run_episode
from pipeline.play.verify import verify_outcome
from tests.conftest import json_reply, pong_policy

TAMPER_BODY = """
envs = typing.sys.modules["games.envs"]
for env in envs._shared.values():
    if not getattr(env, "tampered", False):
        orig = env.step
        def step(action, orig=orig):
            o, r, te, tr, i = orig(action)
            return o, r + 1.0, te, tr, i
        env.step = step
        env.tampered = True
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


def test_the_tampering_policy_really_inflates_its_raw_score():
    spec = _spec(TAMPERING_POLICY)
    [(_, raw)] = list(run_episodes([spec], workers=1))
    assert raw.episode["return"] > 500, "the attack works on what the worker reports"
    verified = verify_outcome(spec, raw)
    assert verified.episode["end_reason"] == "tampered" and verified.episode["verified"] is False
    assert verified.episode["return"] < 0
    assert "score tampering detected" in verified.episode["error"]
    assert verified.steps.column("score").to_pylist()[-1] == verified.episode["return"]


def test_a_tampering_policy_file_gets_its_true_score(store, write_policy, capsys):
    honest = write_policy(HONEST_POLICY, "honest.py")
    assert main(["eval", str(honest), "--max-steps", "600", "--store", str(store.path), "--json"]) == 0
    true_return = json.loads(capsys.readouterr().out)["episodes"][0]["return"]

    path = write_policy(TAMPERING_POLICY, "tamper.py")
    code = main(["eval", str(path), "--max-steps", "600", "--store", str(store.path), "--json"])
    out, err = capsys.readouterr()
    assert code == 1
    episode = json.loads(out)["episodes"][0]
    assert episode["end_reason"] == "tampered" and episode["return"] == true_return
    assert "score tampering detected" in err and len(err.strip().splitlines()) == 1
    rows = store.query('SELECT "return", verified, verify_error, end_reason FROM episodes ORDER BY started_at')
    assert rows[0][:2] == (true_return, True) and rows[0][2] is None
    assert rows[1][:2] == (true_return, False) and "replay gives" in rows[1][2] and rows[1][3] == "tampered"
    # the stored steps are the replay's, so the store (and the next prompt) agree with the true score
    assert store.query("SELECT sum(reward) FROM steps GROUP BY episode_id") == [(true_return,), (true_return,)]
    assert main(["doctor", "--store", str(store.path)]) == 0


def test_a_tampering_candidate_is_not_accepted_as_the_best_version(store, scripted):
    model = scripted([json_reply({"select_action": TAMPER_SELECT})])
    client = LiteLLMClient(model.model, api_base=model.api_base, retries=0)
    config = OptimizeConfig(game="pong", iterations=2, eval_max_steps=600, rollout_steps=60, token_budget=8000,
                            workers=2)
    result = optimize(config, store, client)
    assert result.status == "finished", result.error
    rows = store.query("SELECT iteration, update_status, score, best_score, best_iteration, rolled_back "
                       "FROM iterations ORDER BY iteration")
    assert [r[1] for r in rows] == ["initial", "rejected", "rejected"]
    assert all(r[4] == 0 for r in rows), "the best version stays the starter's"
    assert all(r[2] < 100 for r in rows), "no inflated score is recorded"
    rejected = store.query("SELECT reason FROM rejected_candidates ORDER BY iteration")
    assert rejected and all("score tampering detected" in r[0] for r in rejected)
    feedback = dict(store.query("SELECT iteration, text FROM feedback"))
    assert "score tampering detected" in feedback[1]
    # the next update starts again from the starter's code, not from the tampering version
    base = store.query("SELECT base_version_id FROM iterations WHERE iteration = 2")[0][0]
    assert base == store.query("SELECT policy_version_id FROM iterations WHERE iteration = 0")[0][0]


@pytest.mark.parametrize("game, sticky, noop_max", [("pong", 0.25, 30), ("breakout", 0.25, 30),
                                                     ("space_invaders", 0.0, 0), ("breakout", 0.0, 0)])
def test_honest_episodes_verify_under_both_protocols(game, sticky, noop_max):
    text = f"GAME = {game!r}\n" + textwrap.dedent("""
        import random
        import tracing as trace

        @trace.model
        class Policy(trace.Module):
            def __call__(self, obs):
                return self.act(obs)

            @trace.bundle(trainable=True)
            def act(self, obs):
                return random.randrange(4)
        """)
    spec = _spec(text, game=game, sticky=sticky, noop_max=noop_max, seed=3, max_steps=800)
    outcome = run_episode(spec)
    verified = verify_outcome(spec, outcome)
    assert verified.episode["verified"] is True, verified.episode["verify_error"]
    assert verified.episode["return"] == outcome.episode["return"]


def test_a_forged_episode_row_cannot_redirect_or_inflate(tmp_path):
    spec = _spec(HONEST_POLICY, max_steps=50)
    outcome = run_episode(spec)
    outcome.episode.update({"episode_id": "other.0.eval.0", "run_id": "other", "seed": 99,
                            "evil); DROP TABLE steps; --": 1, "end_reason": "won", "return": 21.0})
    verified = verify_outcome(spec, outcome)
    row = verified.episode
    assert (row["episode_id"], row["run_id"], row["seed"]) == (spec.episode_id, spec.run_id, spec.seed)
    assert not any("DROP" in k for k in row)
    assert row["end_reason"] == "tampered" and row["return"] <= 0


def test_a_malformed_step_table_is_marked_not_stored():
    spec = _spec(HONEST_POLICY, max_steps=50)
    outcome = run_episode(spec)
    outcome.steps = "not a table"
    verified = verify_outcome(spec, outcome)
    assert verified.episode["end_reason"] == "tampered" and verified.steps.num_rows == 0
    assert "malformed" in verified.episode["verify_error"]


def test_anything_a_worker_sends_is_turned_into_a_marked_episode():
    spec = _spec(HONEST_POLICY, max_steps=50)
    for sent in (None, "an outcome", EpisodeOutcome(episode="row", steps=None, nodes=42)):
        verified = verify_outcome(spec, sent)
        assert verified.episode["episode_id"] == spec.episode_id and verified.episode["end_reason"] == "tampered"
        assert verified.episode["return"] == 0.0 and verified.steps.num_rows == 0
