"""Every field of a node row is checked against its episode (pipeline/boundary/nodes.py), and a store write the
store refuses loses no other episode (store/writer.py), asserted on the tables themselves: an honest traced
episode (nested calls, an exception, lines) passes as it is; each field forged as a compromised policy process
can forge it is refused as ``malformed trace at step N: ...``, which the parent turns into the episode's
``policy_error`` with its node rows dropped (tests/faults/test_bounded_frames.py shows it through the CLI)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from pipeline.boundary import wire
from pipeline.boundary.nodes import MalformedTrace, read_nodes
from pipeline.play import episodes
from pipeline.play.rollout import run_episode
from pipeline.play.spec import EpisodeSpec
from store.writer import EpisodeWriter
from tests.conftest import ROOT, pong_policy

NESTED = pong_policy("""
if obs.get("Ball") is None:
    return self.fallback(predicted_ball_y)
return 0 if predicted_ball_y is None else 3
""") + """
    @trace.bundle()
    def fallback(self, y):
        if y is not None and y > 10**9:
            raise ValueError("never")
        return 0
"""
RAISES = pong_policy("""
if obs["frame"] >= 3:
    raise KeyError("at step 3")
return 0
""")


@pytest.fixture(scope="module")
def honest():
    spec = EpisodeSpec("run.0.eval.0", "run", "pong", NESTED, "v", max_steps=8, trace=True)
    outcome = run_episode(spec)
    assert outcome.nodes.num_rows >= 16
    return spec, outcome


def _payload(table: pa.Table) -> bytes:
    return wire.arrow_frame(table)[wire.HEADER.size:]


def _read(spec, outcome, table):
    return read_nodes(_payload(table), spec, outcome.steps.num_rows, outcome.episode["duration_s"])


def _set(table: pa.Table, name: str, row: int, value) -> pa.Table:
    values = table.column(name).to_pylist()
    values[row] = value
    index = table.schema.get_field_index(name)
    return table.set_column(index, table.schema.field(index), pa.array(values, table.schema.field(index).type))


def test_honest_node_rows_pass_as_they_are(honest):
    spec, outcome = honest
    assert _read(spec, outcome, outcome.nodes).equals(outcome.nodes)
    raising = EpisodeSpec("run.0.eval.1", "run", "pong", RAISES, "v", max_steps=8, trace=True)
    failed = run_episode(raising)
    assert failed.end_reason == "policy_error" and failed.nodes.column("exc_type").null_count < failed.nodes.num_rows
    assert _read(raising, failed, failed.nodes).num_rows == failed.nodes.num_rows


FORGERIES = [
    ("step", 2**31 - 1, "a node row for step 2147483647"),
    ("step", -1, "a node row for step -1"),
    ("call_index", 7, "at step 0: call indexes that are not 0..n-1"),
    ("call_index", None, "call_index missing"),
    ("function", "os_system", "at step 0: a call of 'os_system', which is not a bundled method"),
    ("trainable", False, "at step 0: a call whose trainable flag is not its method's"),
    ("duration_us", 2**62, "at step 0: a call lasting"),
    ("duration_us", -5, "at step 0: a call lasting -5 us"),
    ("parents", [32767], "at step 0: a parent that is not an earlier call of the same step"),
    ("parents", [0, 0], "at step 0: a parent that is not an earlier call of the same step"),
    ("output", "{not json", "at step 0: a node's output is not JSON"),
    ("output", "NaN", "at step 0: a node's output is not JSON"),
    ("output", "1" + "0" * 5000, "at step 0: a node's output is not JSON"),  # Python reads 4,300 digits at most
    ("output", '"\\ud800"', "at step 0: a node's output is not JSON (a lone surrogate)"),
    ("output", "[" * 65 + "]" * 65, "at step 0: a node's output is nested deeper than 64 levels"),
    ("output", '"' + "y" * 90_000 + '"', "at step 0: a node's output of more than 21,024 bytes"),
    ("inputs", None, "at step 0: a node without its inputs"),
    ("exc_type", "KeyError", "at step 0: a node with both an output and an exception"),
    ("exc_line", 10_000, "at step 0: an exception line outside the policy's"),
    ("lines_run", [999], "lines_run of predict_ball_trajectory outside"),
]


@pytest.mark.parametrize("column, value, error", FORGERIES, ids=[f"{c}={str(v)[:20]}" for c, v, _ in FORGERIES])
def test_a_forged_field_is_a_malformed_trace(column, value, error, honest):
    spec, outcome = honest
    with pytest.raises(MalformedTrace, match="^malformed trace.*" + error.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[")):
        _read(spec, outcome, _set(outcome.nodes, column, 0, value))


def test_honest_json_the_fast_path_leaves_out_is_parsed_and_accepted(honest):
    spec, outcome = honest
    for text in ('{"a": [1, {"b": [true, null]}], "c": "\\u00e9\\ud83d\\ude00"}', '"caf\u00e9"', "[[[]]]", "-0.5e-3"):
        assert _read(spec, outcome, _set(outcome.nodes, "output", 0, text)).num_rows == outcome.nodes.num_rows


_JSON_PIECES = ["NaN", "Infinity", "-Infinity", "\\ud800", "\\udc00", "\\ud83d\\ude00", "\\u00e9", "\\u12",
                "\\x", "\\/", "\ufeff", ",", ":", "[", "]", "{", "}", '"', "\\", "\n", " ", "\t", "\x00", "\x1f", "1",
                "0", "01", "-", "+", ".", "e", "E", "true", "tru", "null", "nul", "false", '{"$ref":"obs"}', "0" * 5000,
                "[" * 65 + "]" * 65]
"""Tokens a forger (or a cut) puts in a node value: JSON's own, and what it forbids."""


def _json_text(rng) -> str:
    """A text near JSON: an honest node value (nested, spaced, escaped), a token soup, or one with a cut, a token
    spliced in or a repeat."""
    import json
    import string

    def value(depth: int):
        kind = rng.randrange(9 if depth < 3 else 5)
        if kind == 0:
            return rng.choice([None, True, False])
        if kind == 1:
            return rng.choice([0, -1, 7, 10**12, rng.randint(-10**6, 10**6)])
        if kind == 2:
            return rng.choice([0.5, -0.0, 1e300, 2.5e-8, rng.uniform(-1e3, 1e3)])
        if kind in (3, 4):
            return "".join(rng.choice(string.printable + "\u00e9\u2028\U0001f600") for _ in range(rng.randrange(8)))
        if kind in (5, 6):
            return [value(depth + 1) for _ in range(rng.randrange(4))]
        return {rng.choice(["x", "y", "nearest_item", "", "\u00e9"]): value(depth + 1) for _ in range(rng.randrange(4))}

    if rng.random() < 0.3:
        return "".join(rng.choice(_JSON_PIECES[:-2]) for _ in range(rng.randrange(1, 10)))
    text = json.dumps(value(rng.randrange(3)), ensure_ascii=rng.random() < 0.5,
                      separators=rng.choice([(",", ":"), (",", ":"), (", ", ": ")]), indent=rng.choice([None, None, 1]))
    for _ in range(rng.choice([0, 0, 0, 0, 0, 1, 2])):
        at, how = rng.randrange(len(text) + 1), rng.randrange(3)
        text = text[:at] if how == 0 else text[:at] + rng.choice(_JSON_PIECES) + text[at:] if how == 1 else text + text
    return text


def test_a_node_value_is_judged_by_the_fast_path_as_json_loads_and_the_store_judge_it_alone():
    """``nodes._invalid_json`` lets a value of :data:`SIMPLE_JSON`'s shape through on a regular expression, and parses
    the others once per distinct text. Over 1,500 drawn columns of texts near JSON (honest values, nested, spaced,
    escaped, cut, spliced; token soups of numbers, escapes, surrogates, NaN, control characters), it names the
    same first row, for the same reason, as ``_not_json`` of each text alone; and every text it accepts, by the
    expression or parsed, is JSON that ``json.loads`` and the store's JSON type both accept. (The expression let
    an integer of 5,000 digits through, which the store held and Python refuses to read: such a number is parsed
    now, and refused.)"""
    import random

    import duckdb

    from pipeline.boundary.nodes import SIMPLE_JSON, _invalid_json, _not_json

    rng, passed, accepted, verdicts = random.Random(20261208), [], [], {True: 0, False: 0}
    for _ in range(1500):
        texts = [_json_text(rng) for _ in range(rng.randrange(1, 5))]
        column = pa.chunked_array([pa.array(texts, pa.string())])
        alone = next(((i, why) for i, text in enumerate(texts) if (why := _not_json(text)) is not None), None)
        assert _invalid_json(column) == alone, texts
        verdicts[alone is None] += 1
        simple = pc.match_substring_regex(column, SIMPLE_JSON).to_pylist()
        passed += [text for text, fast in zip(texts, simple) if fast]
        accepted += [text for text in texts if _not_json(text) is None]
    assert min(verdicts.values()) > 300, f"the draws hold both accepted and refused columns: {verdicts}"
    assert len(passed) > 1000 and [t for t in passed if _not_json(t) is not None] == []
    refused = duckdb.connect().execute("SELECT list(t) FROM (SELECT unnest(?) AS t) WHERE try_cast(t AS JSON) IS NULL",
                                       [accepted]).fetchone()[0]
    assert not refused, f"the store refuses texts the check accepts: {refused[:5]}"


def test_a_method_that_returns_an_int_python_will_not_write_plays_traced_as_untraced():
    """Python writes an int of at most 4,300 digits (``sys.get_int_max_str_digits``): a traced method that returned
    ``10**5000`` ended its episode in that ValueError (``policy_error``), where the same policy untraced played on.
    Now its node holds a marker, and the traced episode is the untraced one."""
    policy = pong_policy("self.huge(3)\nreturn 0") + """
    @trace.bundle()
    def huge(self, n):
        return 10 ** 5000 + n
"""
    played = {trace: run_episode(EpisodeSpec(f"run.0.eval.{trace:d}", "run", "pong", policy, "v", max_steps=30,
                                             trace=trace)) for trace in (False, True)}
    assert [(o.end_reason, o.episode["return"], o.episode["length"]) for o in played.values()] == \
        [(played[False].end_reason, played[False].episode["return"], 30)] * 2
    assert played[False].end_reason != "policy_error"
    outputs = {o for f, o in zip(played[True].nodes.column("function").to_pylist(),
                                 played[True].nodes.column("output").to_pylist()) if f == "huge"}
    assert outputs == {'"<int of 16,610 bits>"'}


def test_too_many_rows_are_refused_before_they_are_read(honest):
    spec, outcome = honest
    steps = outcome.steps.num_rows
    many = pa.concat_tables([outcome.nodes] * (256 * steps // outcome.nodes.num_rows + 1)).combine_chunks()
    with pytest.raises(MalformedTrace, match=f"more than {256 * steps:,} rows \\(a traced episode records at most "
                                             "256 calls of bundled methods a step: call a helper that is not"):
        _read(spec, outcome, many)
    one_step = outcome.nodes.filter(pc.equal(outcome.nodes.column("step"), 0))
    crowded = pa.concat_tables([one_step] * 200).combine_chunks()  # 200 times step 0's calls, in step 0
    calls = 200 * one_step.num_rows
    with pytest.raises(MalformedTrace, match=f"at step 0: {calls} calls of bundled methods in one step \\(at most 256: "
                                             "call a helper that is not bundled in a loop"):
        _read(spec, outcome, crowded)


def test_the_parent_records_a_malformed_trace_as_the_episodes_policy_error(honest):
    spec, outcome = honest
    row = episodes.episode_to_json(outcome.episode)
    forged = _payload(_set(outcome.nodes, "output", 5, "{not json"))
    checked = episodes.episode_from_worker(spec, row, outcome.steps, forged)
    assert checked.end_reason == "policy_error" and checked.nodes is None
    step = outcome.nodes.column("step")[5].as_py()
    assert checked.episode["error"] == f"malformed trace at step {step}: a node's output is not JSON"
    assert checked.steps.num_rows == outcome.steps.num_rows and checked.episode["return"] == outcome.episode["return"]
    fine = episodes.episode_from_worker(spec, dict(row), outcome.steps, _payload(outcome.nodes))
    assert fine.end_reason == "truncated" and fine.nodes.num_rows == outcome.nodes.num_rows


def test_a_write_the_store_refuses_loses_no_other_episode(honest, store, capfd):
    """Should a value the store refuses ever get past the checks, only its own episode goes unstored."""
    spec, outcome = honest
    bad = _set(outcome.nodes, "output", 0, "[1,")  # no JSON at all: the store's JSON column refuses it
    with EpisodeWriter(store, every_s=3600) as writer:
        for i, nodes in enumerate((outcome.nodes, bad, outcome.nodes)):
            writer.add(dict(outcome.episode, episode_id=f"e{i}", run_id="run"), outcome.steps, nodes)
    assert [r[0] for r in store.query("SELECT episode_id FROM episodes ORDER BY 1")] == ["e0", "e2"]
    assert store.query("SELECT count(*) FROM nodes")[0][0] == 2 * outcome.nodes.num_rows
    assert "episode e1 not stored" in capfd.readouterr().err


def test_a_continued_game_goes_on_past_an_episode_whose_trace_is_refused():
    """The host played the game's next episode (it saw the first end normally): the parent keeps it, and only the
    episode whose node rows are malformed is the policy's error."""
    from pipeline.play.rollout import run_game

    first = EpisodeSpec("run.0.eval.0", "run", "breakout", _BREAKOUT, "v", max_steps=6, trace=True,
                        one_life="continue")
    second = EpisodeSpec("run.0.eval.1", "run", "breakout", _BREAKOUT, "v", index=1, max_steps=6, trace=True,
                         one_life="continue", continues=first.episode_id)
    outcomes = run_game([first, second])
    assert [o.end_reason for o in outcomes] == ["truncated", "truncated"]
    msg = {"episodes": [episodes.episode_to_json(o.episode) for o in outcomes], "nodes": [True, True]}
    tables = [_payload(outcomes[0].steps), _payload(_set(outcomes[0].nodes, "output", 0, "{not json")),
              _payload(outcomes[1].steps), _payload(outcomes[1].nodes)]
    checked = episodes._decode_game([first, second], msg, tables)
    assert [o.end_reason for o in checked] == ["policy_error", "truncated"]
    assert checked[0].nodes is None and checked[1].nodes.num_rows == outcomes[1].nodes.num_rows
    assert checked[1].episode["start_step"] == outcomes[0].episode["length"]


_BREAKOUT = (ROOT / "games" / "scaffolds" / "breakout.py").read_text()


def _eval_traced(path, store, *extra):
    from pipeline.cli import main

    code = main(["eval", str(path), "--trace", "--episodes", "1", "--store", str(store.path), *map(str, extra)])
    rows = store.query("SELECT traced, end_reason, error, length FROM episodes")
    return code, rows, store.query("SELECT count(*) FROM nodes")[0][0]


# The policy process ends (os._exit, no finally) as it makes its node frame, after the episode's last action.
DIES_SENDING_NODES = pong_policy("""
import typing
mods = typing.sys.modules

def die(table, os=mods['os']):
    os._exit(3)

mods['pipeline.boundary.wire'].arrow_frame = die
return 0
""")

# 33,000 calls of a bundled method in one step: the call index overflowed the node table's int16 as it was made
# ("ArrowInvalid: Value 32768 too large to fit in C integer type"); past 32,768 calls a step is recorded no further.
TOO_MANY_CALLS_TO_ENCODE = pong_policy("""
for _ in range(33_000):
    self.tick()
return 0
""") + """
    @trace.bundle()
    def tick(self):
        return 0
"""


@pytest.mark.parametrize("policy, steps, end_reason, error", [
    (DIES_SENDING_NODES, 2, "crashed",
     "trace missing: the policy process ended at the episode's end, before sending its node rows"),
    (TOO_MANY_CALLS_TO_ENCODE, 1, "policy_error",
     "trace missing: the policy process sent no node rows (ValueError: step 0 made 33,002 calls of bundled methods; "
     "a traced step records at most 32,768: call a helper that is not bundled in a loop"),
], ids=["process dies sending its rows", "rows fail to encode"])
def test_a_traced_episode_whose_node_rows_never_arrive_says_why(policy, steps, end_reason, error, store, tmp_path,
                                                                 capsys):
    """Stored as a traced episode that played out, with no node rows and no error, it claimed a trace it did not
    have (the optimizer took it for a policy that made no calls): it is the policy's forfeit, and its error says
    why its trace is missing."""
    path = tmp_path / "policy.py"
    path.write_text(policy)
    code, rows, nodes = _eval_traced(path, store, "--max-steps", steps, "--call-time-limit", 20)
    assert nodes == 0 and len(rows) == 1
    traced, ended, said, length = rows[0]
    assert traced and ended == end_reason and said.startswith(error) and length == steps, said
    assert error.split(" (")[0] in capsys.readouterr().err


def test_the_calls_a_step_may_make_fit_the_call_index():
    """A policy of more than 511 bundled methods was allowed 64 calls of each a step, past the 32,768 indexes that
    call_index (int16) holds: its steps overflowed the table as it was made. The parent allows no more than the
    policy process records."""
    from pipeline.boundary.nodes import row_limits
    from tracing.capture import MAX_CALLS_PER_STEP

    assert MAX_CALLS_PER_STEP - 1 == np.iinfo(np.int16).max
    assert row_limits(512, 10) == (MAX_CALLS_PER_STEP, 10 * MAX_CALLS_PER_STEP)
    assert row_limits(600, 10)[0] == row_limits(5_000, 10)[0] == MAX_CALLS_PER_STEP
    assert row_limits(4, 10)[0] == 256


def test_a_method_longer_than_lines_run_holds_keeps_its_trace(store, tmp_path, capsys):
    """A trainable method of 34,000 lines: its line numbers overflowed lines_run's int16 as the node table was made,
    and the episode was stored traced with no node rows and no error. Its calls are recorded, their lines not
    (NULL, as when lines are not recorded); a method that fits keeps its lines."""
    path = tmp_path / "policy.py"
    path.write_text(pong_policy("action = 0" + "\n" * 34_000 + "return action"))
    code, rows, nodes = _eval_traced(path, store, "--max-steps", 3)
    assert code == 0 and rows == [(True, "truncated", None, 3)] and nodes == 6
    lines = dict(store.query("SELECT function, count(lines_run) FROM nodes GROUP BY ALL"))
    assert lines == {"select_action": 0, "predict_ball_trajectory": 3}


def test_the_parent_never_stores_a_traced_episode_without_rows_as_traced_and_fine(honest):
    """A host that sends a traced episode that played out without its node rows (the host says why, channels.py):
    the parent records the trace missing as the policy's error, not a traced episode with no calls."""
    spec, outcome = honest
    checked = episodes.episode_from_worker(spec, episodes.episode_to_json(outcome.episode), outcome.steps, None)
    assert checked.end_reason == "policy_error" and checked.nodes is None
    assert checked.episode["error"] == "trace missing: the game host sent no node rows for a traced episode"
    untraced = EpisodeSpec("run.0.eval.2", "run", "pong", NESTED, "v", max_steps=8)
    plain = run_episode(untraced)
    kept = episodes.episode_from_worker(untraced, episodes.episode_to_json(plain.episode), plain.steps, None)
    assert kept.end_reason == "truncated" and kept.episode["error"] is None
