"""Nothing from policy code is trusted text (pipeline/boundary/untrusted.py): capped and scrubbed of secrets.

The worst case is modelled: a policy that got hold of a key. The test puts canary secrets in this process's
environment (``CODEARCADE_CANARY_TOKEN``, ``OPENAI_API_KEY``), which the worker processes inherit; the policy
reads them (through a module that re-exports ``sys``, or, where a sandboxed worker's environment no longer has
them, rebuilds them from a reversed copy in its source) and puts them everywhere it can: a bundled method's
return value, an exception message, a rejected candidate's validation error. Afterwards neither canary is on
stdout or stderr, in any text of the store, or in any request the scripted model received. The second half:
8 MB exception messages do not make the next prompt exceed its token budget; ``--resume`` honours
``--token-budget``.
"""

from __future__ import annotations

import json
import textwrap
import uuid

import pytest

from pipeline.boundary.untrusted import clean_json_text, clean_step_objects, clean_untrusted_text, secret_env_names
from pipeline.cli import main
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.propose import repair_limit
from tests.conftest import json_reply
from tracing.steps import StepLog

HEX = uuid.uuid4().hex
CANARY_TOKEN = f"tok{HEX}"
CANARY_KEY = f"sk-canary{HEX[::-1]}"

LEAKY_POLICY = textwrap.dedent(f'''
    import typing
    import tracing as trace

    GAME = "pong"
    HIDDEN = ({CANARY_TOKEN[::-1]!r}, {CANARY_KEY[::-1]!r})

    @trace.model
    class Policy(trace.Module):
        def __call__(self, obs):
            leaked = self.predict_ball_trajectory(obs)
            return self.select_action(leaked, obs)

        @trace.bundle(trainable=True)
        def predict_ball_trajectory(self, obs):
            """Returns the leaked secrets (a string), to show up as this node's output."""
            env = typing.sys.modules["os"].environ
            token = env.get("CODEARCADE_CANARY_TOKEN") or HIDDEN[0][::-1]
            key = env.get("OPENAI_API_KEY") or HIDDEN[1][::-1]
            return token + " " + key

        @trace.bundle(trainable=True)
        def select_action(self, predicted_ball_y, obs):
            """Plays NOOP for 20 steps, then raises with the secrets in the message."""
            self.calls = getattr(self, "calls", 0) + 1
            if self.calls > 20:
                raise ValueError("leaking " + predicted_ball_y)
            return 0
    ''')

LEAKY_SELECT = textwrap.dedent(f'''\
    def select_action(self, predicted_ball_y, obs):
        """Raises with the secrets at once: rejected at validation, with the message as the reason."""
        raise RuntimeError("candidate leaks " + {CANARY_TOKEN[::-1]!r}[::-1] + " " + {CANARY_KEY[::-1]!r}[::-1])
    ''')


@pytest.fixture
def canaries(monkeypatch):
    monkeypatch.setenv("CODEARCADE_CANARY_TOKEN", CANARY_TOKEN)
    monkeypatch.setenv("OPENAI_API_KEY", CANARY_KEY)
    return (CANARY_TOKEN, CANARY_KEY)


def _store_texts(store) -> str:
    """Every value of every table of the store, as text (VARCHAR, JSON, lists, structs; blobs included)."""
    with store.read() as con:
        tables = [r[0] for r in con.execute(
            "SELECT table_name FROM information_schema.tables WHERE table_catalog = current_database() "
            "AND table_type = 'BASE TABLE'").fetchall()]
        return "\n".join(repr(con.execute(f'SELECT * FROM "{t}"').fetchall()) for t in tables)


def _assert_clean(text: str, where: str) -> None:
    assert CANARY_TOKEN not in text and CANARY_KEY not in text, f"a canary secret reached {where}"


def test_secret_values_and_key_shapes_are_redacted(monkeypatch):
    monkeypatch.setenv("SOME_SERVICE_PASSWORD", "hunter2-long-enough")
    monkeypatch.setenv("SHORT_KEY", "1")
    assert "SOME_SERVICE_PASSWORD" in secret_env_names()
    text = clean_untrusted_text("pw hunter2-long-enough, aws AKIAABCDEFGHIJKLMNOP, ant sk-ant-api03-abcdefghij, 1")
    assert text == "pw [redacted], aws [redacted], ant [redacted], 1"
    long = clean_untrusted_text("x" * 8_000_000)
    assert len(long) < 2100 and long.endswith("[cut 7,998,000 characters]")
    assert json.loads(clean_json_text('{"k": "hunter2-long-enough"}')) == {"k": "[redacted]"}
    shown = json.loads(clean_json_text(json.dumps("y" * 100_000)))  # 100,002 characters of JSON, 16,000 bytes kept
    assert shown.startswith('"yyy') and shown.endswith(f"[cut {100_002 - len(shown.split('…')[0]):,} characters]")


def test_a_cleaned_node_value_is_json_of_at_most_its_bytes_whatever_it_holds(monkeypatch):
    """``clean_json_text`` is what the store holds of a node value: at most ``JSON_LIMIT`` (16,000) UTF-8 bytes, JSON
    that ``json.loads`` and the store's JSON type accept. A cut value is a JSON string of the value's first bytes,
    and written as JSON a quote, a backslash or a line break takes two: ``[`` and 16,000 line breaks were stored as
    32,000 bytes. Over 1,500 drawn values within what the parent accepts (21,024 bytes of JSON: strings of escapes,
    quotes, line breaks, astral and accented characters, whitespace between items, secrets and key shapes that
    become ``[redacted]``, lists nested 64 levels), the bound and the JSON hold, and a cut one shows the start of
    the value, its cut counted."""
    import random

    import duckdb

    from pipeline.boundary.nodes import MAX_VALUE_BYTES, _not_json
    from pipeline.boundary.untrusted import JSON_LIMIT, scrub_secrets, utf8_prefix

    monkeypatch.setenv("SOME_SERVICE_PASSWORD", "hunter2-8")  # 9 characters, 10 as "[redacted]": a longer value
    pieces = ['"', "\\", "\n", "\t", "\u0001", "é", "😀", "x", " ", "hunter2-8", "sk-" + "a" * 20, "AKIA" + "B" * 16]
    rng, stored, cut = random.Random(20261208), [], 0
    for _ in range(1500):
        size, kind = rng.choice([20, 2_000, 12_000, 16_000, 17_000, 21_000]), rng.randrange(4)
        if kind == 0:
            value = json.dumps("".join(rng.choice(pieces) for _ in range(size // 6)), ensure_ascii=rng.random() < 0.5)
        elif kind == 1:
            value = json.dumps(["".join(rng.choice(pieces) for _ in range(rng.randrange(1, 12)))
                                for _ in range(size // 40)], ensure_ascii=rng.random() < 0.5)
        elif kind == 2:
            value = "[" + "".join(rng.choice(["\n", " ", "\t", "\r"]) * rng.randrange(1, 60) + "1,"
                                  for _ in range(size // 32)) + "1]"
        else:
            value = "[" * 63 + json.dumps(["hunter2-8"] * (size // 14)) + "]" * 63
        if len(value.encode()) > MAX_VALUE_BYTES:  # more than the parent lets through
            continue
        assert _not_json(value) is None
        kept = clean_json_text(value)
        assert len(kept.encode()) <= JSON_LIMIT and _not_json(kept) is None, (len(kept.encode()), value[:80])
        stored.append(kept)
        if len(value.encode()) > JSON_LIMIT:
            start, _, count = json.loads(kept).rpartition("… [cut ")
            assert scrub_secrets(value).startswith(start[:200]) and len(start) > 2_000
            past_the_bytes = len(value) - len(utf8_prefix(value, JSON_LIMIT))
            assert int(count.removesuffix(" characters]").replace(",", "")) >= past_the_bytes
            cut += 1
    assert cut > 300, "the draws cut values"
    refused = duckdb.connect().execute("SELECT count(*) FROM (SELECT unnest(?) AS t) WHERE try_cast(t AS JSON) IS NULL",
                                       [stored]).fetchone()[0]
    assert refused == 0


def test_object_names_in_step_rows_are_cleaned_and_clean_ones_kept(monkeypatch):
    monkeypatch.setenv("SOME_SERVICE_PASSWORD", "hunter2-long-enough")
    box = {"x": 1, "y": 2, "w": 3, "h": 4, "dx": 0, "dy": 0}
    log = StepLog()
    for step in range(3):  # a forging worker's names beside honest ones, repeated over steps
        log.append(step, {"Ball": box, "Alien0": box, "hunter2-long-enough": box, "AKIAABCDEFGHIJKLMNOP": box,
                          "N" * 300: box}, 0, 0.0, 0.0, False, False, 3)
    steps = log.table()
    cleaned = clean_step_objects(steps)
    keys = [o["key"] for o in cleaned.column("objects")[0].as_py()]
    categories = [o["category"] for o in cleaned.column("objects")[2].as_py()]
    assert keys[:4] == ["Ball", "Alien0", "[redacted]", "[redacted]"] and keys[4].endswith("[cut 200 characters]")
    assert categories[:2] == ["Ball", "Alien"] and "hunter2" not in repr(categories)
    assert cleaned.column("step").to_pylist() == [0, 1, 2]
    honest = StepLog()
    honest.append(0, {"Ball": box, "Alien0": box}, 0, 0.0, 0.0, False, False, 3)
    table = honest.table()
    assert clean_step_objects(table) is table  # the usual case: nothing rebuilt


def test_a_leaking_policy_file_leaks_nothing_through_eval(canaries, store, tmp_path, capfd):
    path = tmp_path / "leaky.py"
    path.write_text(LEAKY_POLICY)
    code = main(["eval", str(path), "--trace", "--max-steps", "60", "--store", str(store.path), "--json"])
    out, err = capfd.readouterr()
    assert code == 1
    episode = json.loads(out)["episodes"][0]
    assert episode["end_reason"] == "policy_error" and "leaking [redacted] [redacted]" in episode["error"]
    _assert_clean(out + err, "the terminal")
    texts = _store_texts(store)
    assert "[redacted]" in texts
    _assert_clean(texts, "the store")
    outputs = store.query("SELECT DISTINCT output FROM nodes WHERE function = 'predict_ball_trajectory'")
    assert outputs == [('"[redacted] [redacted]"',)]


@pytest.mark.slow
def test_a_leaking_policy_leaks_nothing_through_optimize(canaries, store, scripted, tmp_path, capfd):
    path = tmp_path / "leaky.py"
    path.write_text(LEAKY_POLICY)
    model = scripted([json_reply({"select_action": LEAKY_SELECT})])
    code = main(["optimize", str(path), "--model", model.model, "--api-base", model.api_base, "--iterations", "2",
                 "--eval-max-steps", "60", "--rollout-steps", "40", "--token-budget", "8000", "--workers", "2",
                 "--store", str(store.path)])
    out, err = capfd.readouterr()
    assert code == 0, err
    requests = model.log_path.read_text()
    # two updates, each rejected and given a repair turn whose prompt quotes the (redacted) error
    assert len(model.requests()) == 4 and "[redacted]" in requests
    assert [r[0] for r in store.query("SELECT purpose FROM llm_calls ORDER BY created_at")] == ["update", "repair"] * 2
    _assert_clean(requests, "a request the model received")
    _assert_clean(out + err, "the terminal")
    texts = _store_texts(store)
    _assert_clean(texts, "the store")
    reasons = store.query("SELECT reason FROM rejected_candidates")
    assert reasons and all("candidate leaks [redacted] [redacted]" in r[0] for r in reasons)


HUGE_POLICY = LEAKY_POLICY.replace('raise ValueError("leaking " + predicted_ball_y)',
                                   'raise ValueError("x" * 8_000_000)')
HUGE_SELECT = ('def select_action(self, predicted_ball_y, obs):\n'
               '    """Raises an 8 MB message."""\n    raise RuntimeError("y" * 8_000_000)\n')


@pytest.mark.slow
def test_megabyte_messages_do_not_break_the_next_prompt(store, scripted, tmp_path, capfd):
    path = tmp_path / "huge.py"
    path.write_text(HUGE_POLICY)
    model = scripted([json_reply({"select_action": HUGE_SELECT}), "z" * 8_000_000])
    budget = 4000
    code = main(["optimize", str(path), "--model", model.model, "--api-base", model.api_base, "--iterations", "3",
                 "--eval-max-steps", "60", "--rollout-steps", "40", "--token-budget", str(budget), "--workers", "2",
                 "--store", str(store.path)])
    out, err = capfd.readouterr()
    assert code == 0, err[-3000:]
    assert len(out) + len(err) < 20_000
    counted = store.query("SELECT iteration, purpose, prompt_tokens_counted FROM llm_calls ORDER BY created_at")
    # iteration 1's reply raises an 8 MB message: its repair turn quotes it cut short, and is answered by 8 MB of
    # "z"; the later replies are the same 8 MB, too long to send back: no repair for them
    assert [c[:2] for c in counted] == [(1, "update"), (1, "repair"), (2, "update"), (3, "update")], counted
    assert all(tokens <= (budget if purpose == "update" else repair_limit(OptimizeConfig(token_budget=budget)))
               for _, purpose, tokens in counted), counted
    assert max(len(r) for r in model.log_path.read_text().splitlines()) < budget * 8
    longest = store.query("SELECT max(length(error)) FROM episodes")[0][0]
    assert 1000 <= longest <= 2000  # the message bounded, the location after it kept (describe_exception)
    assert store.query("SELECT max(length(exc_message)) FROM nodes")[0][0] < 2100
    assert store.query("SELECT max(length(text)) FROM feedback")[0][0] < 5000


@pytest.mark.slow
def test_resume_honours_the_token_budget_given(store, scripted, tmp_path, capfd):
    model = scripted(["no suggestion here"])
    common = ["--model", model.model, "--api-base", model.api_base, "--store", str(store.path)]
    assert main(["optimize", "--game", "pong", "--iterations", "1", "--eval-max-steps", "60", "--rollout-steps", "40",
                 "--token-budget", "8000", "--workers", "1", "--rng-key", "budget", *common]) == 0
    run_id = store.query("SELECT run_id FROM runs")[0][0]
    capfd.readouterr()
    assert main(["optimize", "--resume", run_id, "--iterations", "2", "--token-budget", "2500",
                 "--call-time-limit", "0.5", *common]) == 0
    capfd.readouterr()
    config = json.loads(store.query("SELECT config FROM runs")[0][0])
    assert (config["token_budget"], config["call_time_limit_s"], config["iterations"]) == (2500, 0.5, 2)
    counted = dict(store.query("SELECT iteration, prompt_tokens_counted FROM llm_calls WHERE purpose = 'update'"))
    assert counted[1] > 2500 >= counted[2], counted


@pytest.mark.slow
@pytest.mark.parametrize("words, why", [
    (36_000, "keep the methods short"),  # 180 KB of docstring: a valid method no later prompt could show
    (80_000, "a policy file holds at most 200,000"),  # 400 KB: longer than any policy (MAX_POLICY_CHARS)
])
def test_a_huge_candidate_that_validates_does_not_end_the_run(store, scripted, capfd, words, why):
    huge = ('def select_action(self, predicted_ball_y, obs):\n    """' + "word " * words + '"""\n'
            '    return 0\n')
    model = scripted([json_reply({"select_action": huge})])
    code = main(["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                 "--iterations", "2", "--eval-max-steps", "60", "--rollout-steps", "40", "--token-budget", "8000",
                 "--workers", "1", "--store", str(store.path)])
    out, err = capfd.readouterr()
    assert code == 0, err[-2000:]
    rows = store.query("SELECT update_status FROM iterations WHERE iteration > 0 ORDER BY iteration")
    assert rows == [("rejected",), ("rejected",)]
    assert why in store.query("SELECT text FROM feedback WHERE iteration = 1")[0][0]
    assert all(t <= 8000 for (t,) in store.query("SELECT prompt_tokens_counted FROM llm_calls"))
    assert store.query("SELECT DISTINCT purpose FROM llm_calls") == [("update",)], "a huge reply is not sent back"
