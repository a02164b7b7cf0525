"""Replies that parse: the near-misses models really send are read correctly and recorded as repaired; a reply
that is truly unusable still gives its one-line reason; ``llm_calls.reply_reading`` says how each was read.

The near-miss shapes are the ones in the authors' logged Pong run (7 of its 20 replies nest the whole answer one
level down under a key the model invented: ``json``, ``payload``, ``json_payload``, ``params``, ``value``; every
reply names methods by Trace's variable names, ``__code2``/``__code4``), written here around our own code.
"""

from __future__ import annotations

import gzip
import json
import shutil

import pytest

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.optimizer.reply import READINGS, ReplyParseError, read_reply
from store import Store
from tests.conftest import COMPETENT_PREDICT, COMPETENT_REPLY, COMPETENT_SELECT, ROOT, json_reply

ANSWER = {"reasoning": "Predict the crossing point and steer to it.",
          "suggestion": {"predict_ball_trajectory": COMPETENT_PREDICT, "select_action": COMPETENT_SELECT}}
WANTED = {"predict_ball_trajectory": COMPETENT_PREDICT, "select_action": COMPETENT_SELECT}


@pytest.mark.parametrize("key", ["json", "payload", "json_payload", "params", "value"])
def test_an_answer_nested_under_an_invented_key_is_read(key):
    inner = dict(ANSWER, answer="see the suggestion") if key == "json_payload" else ANSWER
    read = read_reply(json.dumps({key: inner}))
    assert read.suggestion == WANTED
    assert read.how == "repaired" and read.repairs == (f"the answer nested under '{key}'",)


def test_traces_variable_names_become_the_methods_they_define():
    # as the authors' replies: Trace's keys, the def's first line flush left and its body indented as in a class
    indented = "def select_action(self, predicted_ball_y, obs):\n" + "\n".join(
        "    " + line if line else line for line in COMPETENT_SELECT.splitlines()[1:]) + "\n"
    read = read_reply(json.dumps({"payload": {"reasoning": "r", "suggestion": {"__code4": indented,
                                                                               "__code2": COMPETENT_PREDICT}}}))
    assert set(read.suggestion) == {"select_action", "predict_ball_trajectory"}
    assert read.suggestion["predict_ball_trajectory"] == COMPETENT_PREDICT
    assert "Trace's variable names as keys" in read.repairs and "the answer nested under 'payload'" in read.repairs


PLAIN = json.dumps(ANSWER)
NEAR_MISSES = [
    ("code fence", f"```json\n{PLAIN}\n```", ["a code fence around the JSON"]),
    ("prose around", f"Here is my answer:\n{PLAIN}\nI hope the paddle wins now.", ["prose around the JSON"]),
    ("trailing comma", PLAIN[:-2] + "},}", ["a trailing comma"]),
    ("trailing comma in a list-free object", PLAIN[:-1] + ", }", ["a trailing comma"]),
    ("a brace too many", PLAIN + "}", ["a closing brace too many"]),
    ("braces missing", PLAIN[:-2], ["closing braces missing at the end"]),
    ("fence, comma and prose", f"Sure.\n```json\n{PLAIN[:-2]}\n}},}}\n```\nDone.",
     ["a code fence around the JSON", "a trailing comma"]),
    ("raw line breaks in strings", PLAIN.replace("\\n", "\n"), ["raw line breaks inside a JSON string"]),
    ("a Python dict", repr(ANSWER), ["a Python dict instead of JSON"]),
    ("suggestion as one code string", json.dumps({"reasoning": "r", "suggestion": COMPETENT_PREDICT + "\n"
                                                  + COMPETENT_SELECT}), ["the suggestion given as one string of code"]),
    ("code without a fence", "I rewrote both methods.\n\n" + COMPETENT_PREDICT + "\n" + COMPETENT_SELECT
     + "\nThat should do.", ["code without a fence"]),
]


@pytest.mark.parametrize("name,text,repairs", NEAR_MISSES, ids=[n[0] for n in NEAR_MISSES])
def test_near_misses_are_read_correctly_and_say_what_was_repaired(name, text, repairs):
    read = read_reply(text)
    assert read.suggestion == WANTED, name
    assert read.how == "repaired" and list(read.repairs) == repairs


def test_what_the_prompt_asks_for_is_parsed_and_a_schema_reply_is_structured():
    assert read_reply(PLAIN) == read_reply("  \n" + PLAIN + "\n")
    assert read_reply(PLAIN).how == "parsed" and read_reply(PLAIN).suggestion == WANTED
    assert read_reply(PLAIN, structured=True).how == "structured"
    fenced = f"```python\n{COMPETENT_PREDICT}```\n\n```python\n{COMPETENT_SELECT}```"
    assert read_reply(fenced).how == "parsed" and read_reply(fenced).suggestion == WANTED
    assert read_reply(json_reply({})).suggestion == {}, "an empty suggestion: no change"
    assert read_reply(json.dumps({"reasoning": "r", "suggestion": {"select_action": None}})).suggestion == {}
    # a schema reply that still needed a repair is repaired, not structured
    assert read_reply(PLAIN + "}", structured=True).how == "repaired"
    assert set(READINGS) == {"structured", "parsed", "repaired", "unusable"}


UNUSABLE = [
    ("empty", "   \n", False, "the reply is empty"),
    ("prose only", "I would move the paddle up when the ball is above it.", False,
     "neither a JSON suggestion nor a fenced ```python code block"),
    ("JSON without a suggestion", "{}", False, "neither a 'suggestion' object nor"),
    ("cut off inside the code", PLAIN[: len(PLAIN) // 2], False, "ends inside a string: it was cut off"),
    ("cut off at the token limit", PLAIN[: len(PLAIN) // 2], True, "raise --max-tokens"),
    ("suggestion of the wrong type", json.dumps({"suggestion": ["def f(self): pass"]}), False, "must be an object"),
    ("code that does not parse", "```python\ndef select_action(self, predicted_ball_y, obs):\n    return (\n```",
     False, "does not parse"),
]


@pytest.mark.parametrize("name,text,cut_off,reason", UNUSABLE, ids=[u[0] for u in UNUSABLE])
def test_a_truly_unusable_reply_gives_its_one_line_reason(name, text, cut_off, reason):
    with pytest.raises(ReplyParseError) as refused:
        read_reply(text, cut_off=cut_off)
    message = str(refused.value)
    assert reason in message and "\n" not in message, message


def test_a_cut_off_code_string_is_never_closed_into_code():
    """Closing braces may be added at the end, but a string cut off mid-code is refused, not completed."""
    cut = PLAIN[: PLAIN.index("return 3") + 3]
    with pytest.raises(ReplyParseError, match="cut off"):
        read_reply(cut)


@pytest.mark.slow
def test_the_loop_records_how_each_reply_was_read(store, scripted):
    """Through the real loop (OpenAI wire protocol, litellm): a nested answer is accepted; a fenced JSON with a
    trailing comma, a JSON in prose and one with a brace too many are read (the same code again); prose is refused
    with its reason; llm_calls says how each was read."""
    nested = json.dumps({"json_payload": json.loads(COMPETENT_REPLY)})
    fenced = "```json\n" + COMPETENT_REPLY[:-1] + ",}\n```"
    in_prose = f"Here is my answer:\n{COMPETENT_REPLY}\nThe paddle should win now."
    model = scripted([nested, fenced, in_prose, COMPETENT_REPLY + "}", "I would rather not change anything."])
    client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
    assert client.structured, "the OpenAI protocol takes a response_format"
    config = OptimizeConfig(game="pong", iterations=5, eval_max_steps=300, rollout_steps=60, workers=2, rng_key="reply")
    result = optimize(config, store, client)
    assert result.status == "finished", result.error
    rows = store.query("SELECT c.iteration, c.reply_reading, c.reply_repairs, c.parse_error, i.update_status "
                       "FROM llm_calls c JOIN iterations i USING (run_id, iteration) ORDER BY c.iteration")
    assert rows[0][:2] == (1, "repaired") and rows[0][2] == ["the answer nested under 'json_payload'"]
    assert rows[0][3] is None and rows[0][4] == "accepted"
    assert rows[1][1] == "repaired" and rows[1][2] == ["a code fence around the JSON", "a trailing comma"]
    assert rows[1][4] == "unchanged", "the same code again"
    assert rows[2][1:3] == ("repaired", ["prose around the JSON"]) and rows[2][4] == "unchanged"
    assert rows[3][1:3] == ("repaired", ["a closing brace too many"]) and rows[3][4] == "unchanged"
    assert rows[4][1] == "unusable" and rows[4][2] == [] and rows[4][4] == "rejected"
    assert "neither a JSON suggestion" in rows[4][3] and "\n" not in rows[4][3], "its one-line reason"
    body = model.raw_requests()[0]["body"]
    assert body["response_format"]["json_schema"]["schema"]["required"] == ["reasoning", "suggestion"]
    params = json.loads(store.query("SELECT request_params FROM llm_calls LIMIT 1")[0][0])
    assert params["response_format"] == body["response_format"], "recorded exactly as sent"


def test_old_stores_keep_their_refusals_as_unusable(tmp_path):
    """Migration 8 on a store written before it: calls whose reply was refused read 'unusable', the others NULL
    (parsed or repaired was not recorded then); the published figures arrive with the upgrade."""
    path = tmp_path / "old.duckdb"
    with gzip.open(ROOT / "tests" / "fixtures" / "greedy_run.duckdb.gz") as packed, open(path, "wb") as out:
        shutil.copyfileobj(packed, out)
    old = Store(path)
    rows = old.query("SELECT iteration, parse_error IS NOT NULL, reply_reading FROM llm_calls ORDER BY iteration")
    assert [r[2] for r in rows] == ["unusable" if refused else None for _, refused, _ in rows]
    assert any(refused for _, refused, _ in rows)
    assert old.query("SELECT score FROM published_scores WHERE game = 'pong' AND setting = 'paper'") == [(21.0,)]


PATHOLOGICAL_REPLIES = {
    "backticks": lambda n: "`" * n,  # 12 minutes of one regular expression at a million
    "a fence, then letters": lambda n: "```" + "a" * n,
    "many fences": lambda n: "```a" * (n // 4),
    "an open string": lambda n: '{"suggestion": "' + "x" * n,
    "braces": lambda n: "{" * n,
    "brackets in the JSON": lambda n: '{"suggestion": ' + "[" * n,
    "quotes": lambda n: '"' * n,
    "backslashes": lambda n: '{"a": "' + "\\" * n,
    "object starts": lambda n: '{"' * (n // 2),
    "trailing commas": lambda n: '{"suggestion": {"f": "x"' + ", " * (n // 2),
    "a code block of statements": lambda n: "```python\n" + "a\n" * (n // 2) + "```",  # ~1 KB of tree a character
    "bare code": lambda n: "def f():\n" + "    a\n" * (n // 6),
    "an f-string": lambda n: '```python\nX = f"' + "{1}" * (n // 3) + '"\n```',  # quadratic in CPython's parser
    "code in the JSON": lambda n: '{"suggestion": {"select_action": "' + "a\\n" * (n // 3) + '"}}',
}


@pytest.mark.parametrize("shape", PATHOLOGICAL_REPLIES)
def test_reading_any_reply_up_to_the_limit_costs_a_bounded_parse(shape, monkeypatch):
    """A reply is read in the optimizer's own process (after its store is let go), so what reading costs must be
    bounded whatever the model sent: each shape at sizes up to :data:`MAX_REPLY_CHARS`. The oracle is what the
    reader hands Python's parser (each piece at most a policy's :data:`MAX_POLICY_CHARS`: its tree, ~1 KB a
    character, is what this process holds; all of them at most twice the reply and a literal per place the JSON may
    start, each at most REPAIR_MAX_CHARS), and the CPU time of the whole
    read, within a budget 4-5 times the costliest case here (an f-string just under the limit: ~2 s)."""
    import ast
    import time

    from pipeline.optimizer.reply import MAX_OBJECT_STARTS, MAX_REPLY_CHARS, REPAIR_MAX_CHARS
    from tracing.policy_file import MAX_POLICY_CHARS

    parse = ast.parse
    parsed: list[int] = []

    def counted(source, *args, **kwargs):
        parsed.append(len(source))
        return parse(source, *args, **kwargs)

    monkeypatch.setattr(ast, "parse", counted)
    for size in (50_000, MAX_POLICY_CHARS - 1_000, MAX_REPLY_CHARS - 100):
        text = PATHOLOGICAL_REPLIES[shape](size)
        parsed.clear()
        began = time.process_time()
        try:
            read_reply(text)
        except ReplyParseError:
            pass
        spent = time.process_time() - began
        assert all(n <= MAX_POLICY_CHARS for n in parsed), (size, max(parsed))
        # the code twice at most, and each place that may start the JSON as a Python literal once
        assert sum(parsed) <= 2 * len(text) + (MAX_OBJECT_STARTS + 1) * REPAIR_MAX_CHARS, (size, sum(parsed))
        assert spent < 10, f"{shape} of {len(text):,} characters took {spent:.1f} s of CPU to read"
