"""A value nested thousands deep stops neither a run nor its resume (tracing/bounded.py), tested by effect.

A trainable method that raises its recursion limit (through ``typing.sys``) can return a list nested 3,000 or
100,000 deep. It used to be stored as it was, and the optimizer (and ``--resume``, again and again) died with a
RecursionError building the next prompt. Now: through a policy file (``eval``, then ``optimize`` and its
``--resume``) and through a candidate a scripted model proposes, the run finishes, its resume finishes, and every
stored value parses with the interpreter's usual recursion limit, nested at most 64 levels, the cut marked; a
worker that forges its node values (replacing ``to_json`` in its own process) is held to the same bound by the
parent; and a store already holding such values (written with SQL into ``nodes``) still resumes and builds its
prompt, which shows the marker.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from pipeline.cli import main
from tests.conftest import ROOT, json_reply, pong_policy
from tracing.bounded import MAX_DEPTH, TOO_DEEP, bound_json_text, deeper_than, load_json
from tracing.capture import to_json

DEPTHS = (3_000, 100_000)
ROOMY = ("--call-time-limit", "30")
"""Building a 100,000-deep list each step takes ~0.1-0.3 s of a call, past the default 1 s limit on a loaded
machine: these tests are about depth, not time, so they give the calls room."""
EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")


def _deep_method(name: str, depth: int) -> str:
    return textwrap.dedent(f'''\
        def {name}(self, obs):
            """Returns a list nested {depth:,} deep, with the recursion limit raised so json.dumps could follow it."""
            typing.sys.setrecursionlimit({depth * 4 + 10_000})
            value = None
            for _ in range({depth}):
                value = [value]
            return value
        ''')


def _deep_policy(depth: int) -> str:
    """A Pong policy whose ``predict_ball_trajectory`` returns the deep list and whose action ignores it."""
    text = pong_policy("return 0", prelude="import typing\n")
    head, _, rest = text.partition("    @trace.bundle(trainable=True)\n    def predict_ball_trajectory")
    _, _, tail = rest.partition("    @trace.bundle(trainable=True)\n    def select_action")
    deep = textwrap.indent(_deep_method("predict_ball_trajectory", depth), "    ")
    return (head + "    @trace.bundle(trainable=True)\n" + deep
            + "\n    @trace.bundle(trainable=True)\n    def select_action" + tail)


def _depth_ok(store) -> int:
    """Every stored node value parses with the usual recursion limit and nests at most MAX_DEPTH; how many
    were cut."""
    cut = 0
    for inputs, output in store.query("SELECT inputs, output FROM nodes"):
        for text in (inputs, output):
            if text is not None:
                value = json.loads(text)  # would raise RecursionError on a deeper value
                assert not deeper_than(value, MAX_DEPTH)
                cut += TOO_DEEP in text or "$too_deep" in text
    return cut


def _optimize(store, model, *args: str) -> int:
    return main(["optimize", *args, "--model", model.model, "--api-base", model.api_base, "--store", str(store.path)])


def test_bounds_hold_for_any_text_and_any_value():
    deep_text = "[" * 100_000 + "]" * 100_000
    assert load_json(deep_text, max_chars=None)["$too_deep"] == "more than 64 levels"
    assert load_json(deep_text)["$truncated"] == 200_000
    assert load_json("{not json")["$not_json"] == "{not json"
    nested = json.loads("[" * 70 + "1" + "]" * 70)
    cut = load_json(json.dumps(nested))
    assert not deeper_than(cut) and TOO_DEEP in json.dumps(cut) and json.dumps(cut).startswith("[" * 64)
    fine = json.dumps({"ball": [{"x": 1, "y": [2, 3]}] * 200})
    assert bound_json_text(fine) is fine  # within the bounds: the same text, not parsed and dumped again
    limit = sys.getrecursionlimit()
    try:
        sys.setrecursionlimit(1_000_000)  # what a policy does in its own process
        value = None
        for _ in range(100_000):
            value = [value]
        text = to_json({"a": value})  # json.dumps is never handed the deep value: no stack overflow
    finally:
        sys.setrecursionlimit(limit)
    assert not deeper_than(json.loads(text)) and TOO_DEEP in text


@pytest.mark.slow
@pytest.mark.parametrize("depth", DEPTHS)
def test_a_deep_value_from_a_policy_file_stops_no_run_and_no_resume(depth, store, scripted, tmp_path, capfd):
    path = tmp_path / "deep.py"
    path.write_text(_deep_policy(depth))
    assert main(["eval", str(path), "--trace", "--max-steps", "30", *ROOMY, "--store", str(store.path)]) == 0
    assert store.query("SELECT end_reason FROM episodes") == [("truncated",)]  # not crashed
    model = scripted(["no suggestion in this reply"])
    common = ("--iterations", "1", "--eval-max-steps", "40", "--rollout-steps", "30", "--workers", "2", *ROOMY)
    assert _optimize(store, model, str(path), *common) == 0
    run_id = store.query("SELECT run_id FROM runs WHERE kind = 'optimize'")[0][0]
    assert _optimize(store, model, "--resume", run_id, "--iterations", "2") == 0
    capfd.readouterr()
    assert store.query("SELECT status FROM runs WHERE run_id = ?", [run_id]) == [("finished",)]
    assert store.query("SELECT count(*) FROM llm_calls WHERE run_id = ? AND purpose = 'update'", [run_id]) == [(2,)]
    assert _depth_ok(store) > 0
    assert TOO_DEEP in " ".join(m["content"] for m in model.requests()[-1])  # the prompt shows the cut value


@pytest.mark.slow
@pytest.mark.parametrize("depth", DEPTHS)
def test_a_deep_value_from_a_candidate_stops_no_run_and_no_resume(depth, store, scripted, tmp_path, capfd):
    path = tmp_path / "start.py"
    path.write_text(pong_policy("return 0", prelude="import typing\n"))
    model = scripted([json_reply({"predict_ball_trajectory": _deep_method("predict_ball_trajectory", depth)}),
                      "no suggestion in this reply"])
    common = ("--eval-max-steps", "40", "--rollout-steps", "30", "--workers", "2", *ROOMY)
    assert _optimize(store, model, str(path), "--iterations", "2", *common) == 0
    run_id = store.query("SELECT run_id FROM runs")[0][0]
    assert store.query("SELECT update_status FROM iterations WHERE iteration = 1") == [("accepted",)]
    assert _optimize(store, model, "--resume", run_id, "--iterations", "3") == 0
    capfd.readouterr()
    assert store.query("SELECT status FROM runs") == [("finished",)]
    assert store.query("SELECT count(*) FROM llm_calls WHERE purpose = 'update'") == [(3,)]
    assert _depth_ok(store) > 0
    assert TOO_DEEP in " ".join(m["content"] for m in model.requests()[1])  # the accepted version's rollout, cut


FORGER = pong_policy("return 0", prelude="import typing\n").replace(
    '        ball = obs.get("Ball")\n',
    '        capture = typing.sys.modules["tracing.capture"]\n'
    '        capture.to_json = lambda value: "[" * 3000 + "]" * 3000  # its own process: it may\n'
    '        capture.NodeRecorder._encode_inputs = lambda recorder, fn, args, kwargs: capture.to_json(args)\n'
    '        ball = obs.get("Ball")\n', 1)


def test_forged_deep_node_values_are_refused_where_the_parent_receives_them(store, tmp_path, capfd):
    """The recorder cuts an honest value at 64 levels: one nested deeper was forged, and the episode's node rows
    are refused as a malformed trace (``pipeline/boundary/nodes.py``), the run going on."""
    path = tmp_path / "forger.py"
    path.write_text(FORGER)
    assert main(["eval", str(path), "--trace", "--max-steps", "30", "--store", str(store.path)]) == 1
    capfd.readouterr()
    assert store.query("SELECT end_reason, error, length FROM episodes") == [
        ("policy_error", "malformed trace at step 0: a node's inputs is nested deeper than 64 levels", 30)]
    assert store.query("SELECT count(*) FROM nodes") == [(0,)]
    assert store.query("SELECT status FROM runs") == [("finished",)]


@pytest.mark.slow
@pytest.mark.parametrize("depth", DEPTHS)
def test_a_store_already_holding_a_deep_value_still_resumes(depth, store, scripted, capfd):
    model = scripted(["no suggestion in this reply"])
    assert _optimize(store, model, "--game", "pong", "--iterations", "1", "--eval-max-steps", "40",
                     "--rollout-steps", "30", "--workers", "2") == 0
    run_id = store.query("SELECT run_id FROM runs")[0][0]
    deep = "[" * depth + "]" * depth
    with store.write() as con:  # as an older codearcade stored it, or a hand edit
        con.execute("UPDATE nodes SET output = ?, inputs = ?", [deep, '{"obs": {"$ref": "obs"}, "y": ' + deep + "}"])
    assert store.query("SELECT count(*) FROM nodes WHERE length(output) = ?", [2 * depth])[0][0] > 0
    # resumed by a new process, as after a crash (this one keeps the last rollouts it read in memory)
    done = subprocess.run([EXE, "optimize", "--resume", run_id, "--iterations", "2", "--model", model.model,
                           "--api-base", model.api_base, "--store", str(store.path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    capfd.readouterr()
    for query in ("SELECT output FROM nodes LIMIT 3", "SELECT inputs FROM nodes LIMIT 3"):
        assert main(["sql", query, "--json", "--store", str(store.path)]) == 0
        assert json.loads(capfd.readouterr().out)[0]  # the stored text itself, as a string
    assert store.query("SELECT status FROM runs") == [("finished",)]
    prompt = " ".join(m["content"] for m in model.requests()[-1])
    # shown bounded: decoded with a marker where it is short enough to read whole, else only its head, cut
    # (store.readers reads at most 300 characters of a long value: docs/sandbox.md, readers read slices)
    assert "$too_deep" in prompt or "$truncated" in prompt or "[" * 100 + "…" in prompt, prompt[-3000:]
    assert "[" * 400 not in prompt, "never the whole value"
