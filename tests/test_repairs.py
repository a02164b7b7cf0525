"""Repair turns (``--repairs``): a reply rejected before it is played goes back to the model with the exact error, in
the same conversation, and the corrected reply is validated exactly as a first one — against a scripted model
behind a real HTTP endpoint, called through litellm."""

from __future__ import annotations

import json

import pytest

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.optimizer.replay import replay
from tests.conftest import COMPETENT_REPLY, json_reply

RAISES = json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return obs['Nope']\n"})
WRONG_SIGNATURE = json_reply({"select_action": "def select_action(self, obs):\n    return 0\n"})


def _client(model):
    return LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)


def _config(**kwargs):
    defaults = dict(game="pong", iterations=1, eval_max_steps=600, workers=2, token_budget=8000, audit_episodes=0,
                    rng_key="repairs")
    return OptimizeConfig(**{**defaults, **kwargs})


def _calls(store):
    return store.query("SELECT call_id, iteration, candidate, purpose, repair_of, repair_turn FROM llm_calls "
                       "ORDER BY created_at")


def test_a_reply_that_raises_then_a_corrected_one_is_one_accepted_update_with_two_linked_calls(store, scripted):
    model = scripted([RAISES, COMPETENT_REPLY])
    result = optimize(_config(), store, _client(model))
    assert result.status == "finished"
    assert [(i.iteration, i.update_status, i.repairs) for i in result.iterations] == [(0, "initial", 0),
                                                                                     (1, "accepted", 1)]
    first, repair = _calls(store)
    assert first[1:4] == (1, 0, "update") and first[4] is None and first[5] == 0
    assert repair[1:4] == (1, 0, "repair") and repair[4] == first[0] and repair[5] == 1, "linked to the call it repairs"
    # the repair is the same conversation: the first prompt, the model's own reply, then the exact error
    requests = model.requests()
    assert len(requests) == 2
    asked, again = requests[0], requests[1]
    assert again[: len(asked)] == asked
    assert again[len(asked)]["role"] == "assistant" and "obs['Nope']" in again[len(asked)]["content"]
    error = again[len(asked) + 1]
    assert error["role"] == "user" and "KeyError" in error["content"] and "'Nope'" in error["content"]
    # the candidate is the repaired reply's: its version, its call, the repair counted
    candidate = store.query("SELECT update_status, repairs, llm_call_id, proposed_version_id FROM candidates "
                            "WHERE iteration = 1")[0]
    assert candidate[:3] == ("accepted", 1, repair[0])
    made_by = store.query("SELECT llm_call_id FROM policy_versions WHERE policy_version_id = ?", [candidate[3]])
    assert made_by == [(repair[0],)]
    # counted where people look: the learning curve and the run's summary
    curve = store.query("SELECT iteration, llm_calls, repair_calls, saved_by_repair, repairs FROM learning_curve "
                        "ORDER BY iteration")
    assert curve == [(0, 0, 0, 0, 0), (1, 2, 1, 1, 1)]
    assert store.query("SELECT llm_calls, repair_calls, saved_by_repair FROM run_summary") == [(2, 1, 1)]


def test_the_repaired_reply_is_validated_like_a_first_one_and_the_conversation_grows(store, scripted):
    model = scripted(["Sorry, I cannot help with that.", WRONG_SIGNATURE, RAISES])
    result = optimize(_config(repairs=2), store, _client(model))
    assert result.status == "finished" and result.iterations[1].update_status == "rejected"
    assert result.iterations[1].repairs == 2
    calls = _calls(store)
    assert [c[3] for c in calls] == ["update", "repair", "repair"] and [c[5] for c in calls] == [0, 1, 2]
    assert calls[1][4] == calls[0][0] and calls[2][4] == calls[1][0], "each repair links to the call before it"
    sizes = [len(r) for r in model.requests()]
    assert sizes[1] == sizes[0] + 2 and sizes[2] == sizes[1] + 2
    second, third = model.requests()[1][-1]["content"], model.requests()[2][-1]["content"]
    assert "not usable" in second
    assert "must keep its parameters" in third, "the wrong signature is caught exactly as in a first reply"
    # the last rejection is what the next prompt's feedback says, and nothing was saved
    feedback = store.query("SELECT text FROM feedback WHERE iteration = 1")[0][0]
    assert "KeyError" in feedback
    assert store.query("SELECT repair_calls, saved_by_repair FROM run_summary") == [(2, 0)]


@pytest.mark.slow
def test_no_repairs_with_zero_and_none_past_the_call_budget(store, scripted):
    model = scripted([RAISES, COMPETENT_REPLY])
    result = optimize(_config(repairs=0), store, _client(model))
    assert result.iterations[1].update_status == "rejected" and len(model.requests()) == 1
    # the call budget counts repairs: one call allowed, so the rejected reply stays rejected and the run goes on
    model = scripted([RAISES, COMPETENT_REPLY])
    result = optimize(_config(max_llm_calls=1), store, _client(model))
    assert result.status == "finished" and result.iterations[1].update_status == "rejected"
    assert len(model.requests()) == 1
    # two calls allowed: the repair is made and saves the update
    model = scripted([RAISES, COMPETENT_REPLY])
    result = optimize(_config(max_llm_calls=2), store, _client(model))
    assert result.iterations[1].update_status == "accepted" and len(model.requests()) == 2


@pytest.mark.slow
def test_a_reply_cut_off_at_the_token_limit_is_told_to_fit_and_the_person_to_raise_the_limit(store, scripted):
    """A reply that stopped at the token limit was sent back saying "raise --max-tokens": advice the model cannot
    take. Its repair turn and the next prompt's feedback tell it the limit and to send less; the stored reason, which
    a person reads, still says what they can do."""
    cut = {"content": COMPETENT_REPLY[: len(COMPETENT_REPLY) // 2], "finish": "length"}
    config = _config(max_tokens=1500)
    model = scripted([cut, COMPETENT_REPLY])
    result = optimize(config, store, _client(model))
    assert result.iterations[1].update_status == "accepted" and result.iterations[1].repairs == 1
    told = model.requests()[1][-1]["content"]
    assert "at most 1,500 tokens" in told and "only the methods you change" in told, told
    assert "--max-tokens" not in told, told
    stored = store.query("SELECT parse_error FROM llm_calls WHERE run_id = ? AND purpose = 'update'",
                         [result.run_id])[0][0]
    assert "stopped at the token limit" in stored and "raise --max-tokens" in stored, stored
    # without a repair turn, the next iteration's prompt says the same in its feedback
    model = scripted([cut, COMPETENT_REPLY])
    result = optimize(_config(max_tokens=1500, repairs=0, iterations=2), store, _client(model))
    assert [i.update_status for i in result.iterations] == ["initial", "rejected", "accepted"]
    prompt = "\n".join(message["content"] for message in model.requests()[1])
    assert "at most 1,500 tokens" in prompt and "--max-tokens" not in prompt
    # nor when the limit came before any text (a call that failed, its error stored as it was)
    model = scripted([{"content": "", "finish": "length"}, COMPETENT_REPLY])
    result = optimize(_config(max_tokens=1500, repairs=0, iterations=2), store, _client(model))
    assert [i.update_status for i in result.iterations] == ["initial", "llm_error", "accepted"]
    prompt = "\n".join(message["content"] for message in model.requests()[1])
    assert "at most 1,500 tokens" in prompt and "--max-tokens" not in prompt, prompt[-2000:]
    assert "raise --max-tokens" in store.query("SELECT error_message FROM llm_calls WHERE run_id = ? AND iteration = 1",
                                               [result.run_id])[0][0]


def test_a_failed_repair_call_leaves_the_rejection_and_the_run_goes_on(store, scripted):
    model = scripted([RAISES, {"status": 400, "message": "context too long"}, COMPETENT_REPLY])
    result = optimize(_config(iterations=2), store, _client(model))
    assert result.status == "finished"
    assert [i.update_status for i in result.iterations] == ["initial", "rejected", "accepted"]
    errors = store.query("SELECT iteration, purpose, error_type FROM llm_calls WHERE error_type IS NOT NULL")
    assert errors == [(1, "repair", "BadRequestError")]


@pytest.mark.slow
def test_a_replay_makes_the_same_repairs(store, scripted):
    model = scripted([RAISES, COMPETENT_REPLY])
    result = optimize(_config(), store, _client(model))
    report = replay(store, result.run_id)
    assert report.status == "finished" and all(row.matches for row in report.rows)
    replayed = store.query("SELECT purpose, replayed FROM llm_calls WHERE run_id = ? ORDER BY created_at",
                           [report.replay_run_id])
    assert replayed == [("update", True), ("repair", True)]
    assert store.query("SELECT update_status, repairs FROM candidates WHERE run_id = ? AND iteration = 1",
                       [report.replay_run_id]) == [("accepted", 1)]
    assert len(model.requests()) == 2, "a replay never calls the model"
    assert json.loads(store.query("SELECT config FROM runs WHERE run_id = ?", [result.run_id])[0][0])["repairs"] == 1


@pytest.mark.slow
def test_the_report_says_what_repairs_saved_and_draws_the_calls(store, scripted, tmp_path):
    from store.showing import llm_call_outcomes
    from viewers.report import write_report

    model = scripted([RAISES, COMPETENT_REPLY])
    result = optimize(_config(), store, _client(model))
    with store.read() as con:
        calls = llm_call_outcomes(con, result.run_id)
    assert [(c["purpose"], c["outcome"]) for c in calls] == [("update", "repaired"), ("repair", "accepted")]
    assert calls[0]["started_at"] < calls[0]["ended_at"] <= calls[1]["started_at"]
    readme = write_report(store, result.run_id, tmp_path / "report")
    text = readme.read_text()
    assert "1 repair call, 1 update saved by a repair" in text and "| accepted after 1 repair |" in text
    assert (tmp_path / "report" / "calls.png").stat().st_size > 10_000 and "calls.png" in text
