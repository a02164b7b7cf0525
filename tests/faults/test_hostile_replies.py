"""Hostile LLM replies: through the real HTTP path into the loop, and a fuzzed parser.

The parser's contract: whatever the text, ``parse_reply`` returns ``{name: source}`` or raises
``ReplyParseError``, and nothing else.
"""

from __future__ import annotations

import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.optimizer.reply import ReplyParseError, parse_reply
from tests.conftest import COMPETENT_SELECT, json_reply

HUGE = "x" * (10 * 2**20)
HOSTILE_REPLIES = [
    ("empty", "", "empty"),
    ("huge", HUGE, "over the"),
    ("non-UTF-8 bytes", {"raw": json.dumps({"id": "x", "object": "chat.completion", "created": 0, "model": "s",
                                            "choices": [{"index": 0, "message": {"role": "assistant",
                                                                                 "content": "\udcff"},
                                                         "finish_reason": "stop"}]},
                                           ensure_ascii=False).replace('"\\udcff"', '"\xff\xfe garbage"')},
     None),
    ("JSON with wrong keys", json.dumps({"answer": "use a better paddle", "code": "def f(): pass"}), "neither"),
    ("suggestion of the wrong type", json.dumps({"suggestion": ["def select_action(self): pass"]}), "must be an object"),
    ("function that does not exist", json_reply({"shoot_lasers": "def shoot_lasers(self, obs):\n    return 1\n"}),
     "does not have"),
    ("changed signature", json_reply({"select_action": "def select_action(self, obs, extra=1):\n    return 0\n"}),
     "must keep its parameters"),
    ("markdown without code", "# Plan\n\n* move the paddle\n* win\n", "neither"),
    ("code block that does not parse", "```python\ndef select_action(self, predicted_ball_y, obs):\n    return (\n```",
     "does not parse"),
    ("two defs under one name", json_reply({"select_action": COMPETENT_SELECT + "\ndef helper():\n    pass\n"}),
     "exactly one"),
]


@pytest.mark.slow
def test_hostile_replies_through_the_loop(store, scripted):
    model = scripted([reply for _, reply, _ in HOSTILE_REPLIES])
    client = LiteLLMClient(model.model, api_base=model.api_base, retries=0)  # one script entry per iteration
    config = OptimizeConfig(game="pong", iterations=len(HOSTILE_REPLIES), eval_max_steps=100, rollout_steps=60,
                            token_budget=6000, workers=2, repairs=0)  # each reply is judged as it came
    result = optimize(config, store, client)
    assert result.status == "finished", result.error
    rows = store.query("SELECT i.iteration, i.update_status, f.text FROM iterations i JOIN feedback f "
                       "USING (run_id, iteration) WHERE i.iteration > 0 ORDER BY i.iteration")
    assert len(rows) == len(HOSTILE_REPLIES)
    starter = store.query("SELECT policy_version_id FROM iterations WHERE iteration = 0")[0][0]
    for (name, _, fragment), (iteration, status, feedback) in zip(HOSTILE_REPLIES, rows):
        assert status in ("rejected", "llm_error"), (name, status)
        if fragment:
            assert fragment in feedback, (name, feedback)
    assert {r[0] for r in store.query("SELECT DISTINCT policy_version_id FROM iterations")} == {starter}
    stored = store.query("SELECT max(b.chars) FROM llm_calls c JOIN blobs b ON b.hash = c.reply_hash")[0][0]
    assert stored >= len(HUGE), "even the 10 MB reply is kept, once, as a blob"


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(max_size=2000))
def test_fuzz_parser_arbitrary_text(text):
    try:
        result = parse_reply(text)
    except ReplyParseError:
        return
    assert isinstance(result, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in result.items())


JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=30),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=15), children, max_size=5),
    max_leaves=30,
)


@settings(max_examples=300, deadline=None)
@given(JSONISH, st.sampled_from(["suggestion", "suggestions", "answer"]), st.text(max_size=40), st.text(max_size=40))
def test_fuzz_parser_json_shapes(value, key, before, after):
    text = before + json.dumps({"reasoning": "r", key: value}) + after
    try:
        result = parse_reply(text)
    except ReplyParseError:
        return
    assert all(isinstance(v, str) for v in result.values())


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from(["```", "```python\n", "```json\n", "def f(self):\n", "    return 1\n", "{", "}",
                                 '"suggestion":', "class Policy:\n", "\n", "(", "\x00", "\udcff"]), max_size=30))
def test_fuzz_parser_fences_and_fragments(parts):
    try:
        parse_reply("".join(parts))
    except ReplyParseError:
        pass


def test_deeply_nested_json_is_our_error():
    deep = '{"suggestion": ' + "[" * 100_000 + "]" * 100_000 + "}"
    try:
        parse_reply(deep)
    except ReplyParseError:
        pass
