"""Line provenance: blame carried across versions of a real optimization run, and the lines each traced call ran.

One module-scoped run drives ``optimize`` through litellm against the scripted model: each reply changes known
lines of ``select_action``, so every line of the final version has a known iteration. The same run's traced
training rollouts (real ALE, real DuckDB file) answer the two SQL questions of docs/provenance.md.
"""

from __future__ import annotations

import json
import textwrap

import pyarrow as pa
import pytest

from pipeline.cli import main
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.boundary.nodes import MalformedTrace, check_nodes
from pipeline.play.rollout import run_episode
from pipeline.play.spec import EpisodeSpec
from store import Store
from tests.conftest import json_reply, pong_policy, run_main
from tracing.blame import blame_function
from tracing.lines import executable_lines
from tracing.policy_file import inspect_policy

# select_action of the starting policy; the comments say which iteration's reply leaves each line as it is.
V0 = """
player = obs.get("Player")
if player is None or predicted_ball_y is None:
    return 0
if obs.get("Nope"):
    return 1
if player["y"] + 7 < predicted_ball_y:
    return 3
return 2
"""
V1 = '''def select_action(self, predicted_ball_y, obs):
    player = obs.get("Player")
    if player is None or predicted_ball_y is None:
        return 0
    if obs.get("Nope"):
        return 1
    if player["y"] + 7 < predicted_ball_y:
        return 3
    if player["y"] + 7 > predicted_ball_y:
        return 2
    return 0
'''
BROKEN = 'def select_action(self, predicted_ball_y, obs):\n    return obs["Nope"]\n'
V3 = V1.replace('if player["y"] + 7 < predicted_ball_y:', 'if player["y"] + 8 < predicted_ball_y:')
FINAL_ORIGINS = {  # line of V3 -> iteration that introduced it
    1: 0, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0,
    7: 3,           # the constant changed in iteration 3
    8: 0,
    9: 1, 10: 1, 11: 1,  # the branch iteration 1 added (its `return 2` is re-indented: a new line, as in git)
}
DEAD_LINE = 6  # `return 1`: obs never has a key "Nope"
RETURNS = {4: 0, 6: 1, 8: 3, 9: 2}  # V0: the line of each `return` -> the action it returns


def _cli_json(*argv: str) -> object:
    result = run_main(*argv)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(store, run id) of a 3-iteration run: V1 accepted, a candidate that raises rejected, then V3."""
    from tests.scripted_llm import ScriptedModel

    tmp = tmp_path_factory.mktemp("provenance")
    policy = tmp / "start.py"
    policy.write_text(pong_policy(V0))
    store = Store(tmp / "store.duckdb", lock_timeout_s=20)
    script = [json_reply({"select_action": V1}), json_reply({"select_action": BROKEN}),
              json_reply({"select_action": V3})]
    with ScriptedModel(script, tmp / "model") as model:
        config = OptimizeConfig(game="pong", policy=str(policy), iterations=3, rollback=False, rollout_steps=400,
                                eval_max_steps=300, workers=1, token_budget=8000, repairs=0)  # one scripted reply per update (repairs: tests/test_repairs.py)
        result = optimize(config, store, LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05))
    assert result.status == "finished"
    return store, result.run_id


@pytest.mark.slow
def test_blame_attributes_every_line_of_the_final_version_to_its_iteration(run):
    store, run_id = run
    statuses = [r[0] for r in store.query("SELECT update_status FROM iterations WHERE run_id = ? ORDER BY iteration",
                                          [run_id])]
    assert statuses == ["initial", "accepted", "rejected", "accepted"]
    report = _cli_json("blame", run_id[:12], "--iteration", "3", "--json", "--store", str(store.path))
    functions = {f["name"]: f["lines"] for f in report["functions"]}
    select = functions["select_action"]
    assert "\n".join(line["text"] for line in select) + "\n" == V3
    assert {line["line_no"]: line["origin_iteration"] for line in select} == FINAL_ORIGINS
    calls = dict(store.query("SELECT iteration, llm_call_id FROM iterations WHERE run_id = ?", [run_id]))
    for line in select:
        expected = calls[line["origin_iteration"]]  # None for the starting policy's lines
        assert line["origin_call_id"] == expected, line
        assert line["origin_produced_by"] == ("initial" if line["origin_iteration"] == 0 else "llm")
    assert {line["origin_iteration"] for line in functions["predict_ball_trajectory"]} == {0}, "never changed"
    [(calls_traced,)] = store.query("SELECT count(*) FROM nodes WHERE policy_version_id = ? AND function = "
                                    "'select_action'", [report["policy_version_id"]])
    ran = {line["line_no"]: line["times_ran"] for line in select}
    assert ran[2] == calls_traced > 0 and ran[DEAD_LINE] == 0 and ran[8] + ran[10] + ran[11] + ran[4] == calls_traced
    # the rejected candidate of iteration 2 has its own lines, attributed to itself, and left no trace in V3
    rejected = store.query("SELECT DISTINCT origin_iteration FROM line_blame l JOIN policy_versions v USING "
                           "(run_id, policy_version_id) WHERE v.run_id = ? AND v.validation = 'rejected' AND "
                           "l.function = 'select_action' AND l.line_no = 2", [run_id])
    assert rejected == [(2,)]


def test_blame_text_and_errors(run, capsys):
    store, run_id = run
    assert main(["blame", run_id, "--store", str(store.path)]) == 0
    text = capsys.readouterr().out
    assert "select_action" in text and 'if player["y"] + 8 < predicted_ball_y:' in text
    assert main(["blame", run_id, "--version", "ffff", "--store", str(store.path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("codearcade: error: run ") and "no policy version 'ffff'" in err and "Traceback" not in err
    assert main(["blame", run_id, "--iteration", "9", "--store", str(store.path)]) == 2
    assert "no iteration 9 (iterations 0..3)" in capsys.readouterr().err, "the range is the run's, rejects too"
    # iteration 2's candidate was rejected: --iteration 2 shows iteration 1's version, and says so (it said nothing
    # of it: the header named iteration 1 and left the person to guess why)
    rejected = store.query("SELECT proposed_version_id FROM candidates WHERE run_id = ? AND iteration = 2",
                           [run_id])[0][0]
    assert main(["blame", run_id, "--iteration", "2", "--store", str(store.path)]) == 0
    header, note = capsys.readouterr().out.splitlines()[:2]
    assert header.endswith("(iteration 1)"), header
    assert note == ("iteration 2 wrote no version of its own (its update was rejected): shown is the version it "
                    f"evaluated, iteration 1's; its candidate {rejected[:8]}: --version {rejected[:8]}")
    report = _cli_json("blame", run_id, "--iteration", "2", "--json", "--store", str(store.path))
    assert (report["iteration"], report["asked_iteration"], report["note"]) == (1, 2, note)
    assert _cli_json("blame", run_id, "--iteration", "1", "--json", "--store", str(store.path))["note"] is None


def test_blame_is_computed_for_a_store_written_before_migration_7(run, tmp_path):
    """Dropping a run's lines (as a store from before line provenance has none) and blaming it recomputes them."""
    store, run_id = run
    copy = Store(tmp_path / "copy.duckdb")
    copy.path.write_bytes(store.path.read_bytes())
    with copy.write() as con:
        con.execute("DELETE FROM policy_lines WHERE run_id = ?", [run_id])
    report = _cli_json("blame", run_id, "--iteration", "3", "--json", "--store", str(copy.path))
    select = next(f["lines"] for f in report["functions"] if f["name"] == "select_action")
    assert {line["line_no"]: line["origin_iteration"] for line in select} == FINAL_ORIGINS


def test_unrun_lines_of_the_best_version(run):
    """docs/provenance.md's query: the executable lines of the best version that no traced call of it ran."""
    store, run_id = run
    rows = store.query(
        """SELECT u.function, u.line_no, u.text FROM unrun_lines u
           WHERE u.run_id = ? AND u.policy_version_id = (SELECT arg_max(best_version_id, iteration) FROM iterations
                                                         WHERE run_id = u.run_id)
           ORDER BY u.function, u.line_no""", [run_id])
    [(best, text)] = store.query(
        "SELECT v.policy_version_id, b.text FROM policy_versions v JOIN blobs b ON b.hash = v.source_hash "
        "WHERE v.run_id = ? AND v.policy_version_id = (SELECT arg_max(best_version_id, iteration) FROM iterations "
        "WHERE run_id = ?) LIMIT 1", [run_id, run_id])
    # the same answer from the raw node rows and the sources, without the views
    ran: dict[str, set[int]] = {}
    for function, lines in store.query(
            "SELECT n.function, n.lines_run FROM nodes n JOIN episodes e USING (episode_id) WHERE e.run_id = ? "
            "AND n.policy_version_id = ?", [run_id, best]):
        ran.setdefault(function, set()).update(lines)
    expected = []
    for method in inspect_policy(text).trainable:
        lines = method.source.splitlines()
        expected += [(method.name, k, lines[k - 1]) for k in executable_lines(method.source)
                     if k not in ran[method.name]]
    assert rows == sorted(expected)
    assert ("select_action", DEAD_LINE, "        return 1") in rows, "the branch no observation takes"
    assert ("select_action", 3) not in [(function, line) for function, line, _ in rows], "checked every step: it ran"


def test_lines_that_ran_before_each_lost_point(run):
    """docs/provenance.md's query: which lines of select_action ran in the 10 steps before each point the player lost;
    the return line that ran at each step is the one that returns the action the step played."""
    store, run_id = run
    [(episode,)] = store.query("SELECT train_episode_id FROM iterations WHERE run_id = ? AND iteration = 0", [run_id])
    rows = store.query(
        """SELECT s.step AS lost_at, n.step, list(n.line_no ORDER BY n.line_no) AS lines
           FROM steps s JOIN node_lines n ON n.episode_id = s.episode_id AND n.step BETWEEN s.step - 9 AND s.step
           WHERE s.episode_id = ? AND s.reward < 0 AND n.function = 'select_action'
           GROUP BY s.step, n.step ORDER BY lost_at, n.step""", [episode])
    lost = [r[0] for r in store.query("SELECT step FROM steps WHERE episode_id = ? AND reward < 0", [episode])]
    assert lost, "the starting policy's rollout loses points"
    assert sorted({r[0] for r in rows}) == lost
    actions = dict(store.query("SELECT step, action FROM steps WHERE episode_id = ?", [episode]))
    for lost_at, step, lines in rows:
        assert lost_at - 9 <= step <= lost_at
        returned = [line for line in lines if line in RETURNS]
        assert len(returned) == 1 and RETURNS[returned[0]] == actions[step], (step, lines, actions[step])


def test_lines_run_of_nested_and_failing_calls():
    """Lines are numbered within each method's source; a comprehension's lines count as its method's; a call that
    raises keeps the lines it reached."""
    text = pong_policy("""
        values = [v for v in (1, 2, 3)
                  if v > 1]
        if len(values) > 5:
            return 0
        return obs["Missing"]
    """)
    outcome = run_episode(EpisodeSpec("ep", "run", "pong", text, "v", max_steps=3, trace=True))
    nodes = outcome.nodes.to_pylist()
    select = [n for n in nodes if n["function"] == "select_action"]
    assert select[0]["exc_type"] == "KeyError"
    assert select[0]["lines_run"] == [2, 3, 4, 6], "line 5 (return 0) never ran; the def line is not code"
    predict = [n for n in nodes if n["function"] == "predict_ball_trajectory"]
    assert predict[0]["lines_run"] == [2, 3]
    untraced = run_episode(EpisodeSpec("ep", "run", "pong", text, "v", max_steps=3, trace=True, trace_lines=False))
    assert untraced.nodes.column("lines_run").null_count == untraced.nodes.num_rows


def test_the_parent_refuses_lines_a_worker_could_not_have_run():
    text = pong_policy("return 2")
    spec = EpisodeSpec("ep", "run", "pong", text, "v", max_steps=3, trace=True)
    outcome = run_episode(spec)
    good = outcome.nodes

    def check_lines_run(spec, nodes):
        check_nodes(nodes, spec, outcome.steps.num_rows, outcome.episode["duration_s"])

    check_lines_run(spec, good)  # what the worker sent is accepted
    column = good.schema.get_field_index("lines_run")

    def forged(lines: list) -> pa.Table:
        return good.set_column(column, good.schema.field(column), pa.array(lines, pa.list_(pa.int16())))

    n = good.num_rows
    for lines, why in (([[99]] * n, "outside"), ([[3, 2]] * n, "increasing"), ([[0]] * n, "outside")):
        with pytest.raises(MalformedTrace, match=why):
            check_lines_run(spec, forged(lines))
    renamed = forged([[2]] * n).set_column(good.schema.get_field_index("function"), "function",
                                           pa.array(["os_system"] * n))
    with pytest.raises(MalformedTrace, match="not a bundled method"):
        check_lines_run(spec, renamed)
    spec.trace_lines = False
    with pytest.raises(MalformedTrace, match="without line recording"):
        check_lines_run(spec, good)


def test_blame_function_carries_matched_lines():
    parent = [(text, "a") for text in ["def f(self):", "    x = 1", "    return x"]]
    lines = blame_function("def f(self):\n    y = 2\n    x = 1\n    return x\n", parent, "b")
    assert [(line.text, line.origin, line.executable) for line in lines] == [
        ("def f(self):", "a", False), ("    y = 2", "b", True), ("    x = 1", "a", True), ("    return x", "a", True)]
    fresh = blame_function(textwrap.dedent('''
        def g(self):
            """doc"""
            # why
            return 1
    ''').lstrip(), None, "c")
    assert [(line.line_no, line.origin, line.executable) for line in fresh] == [
        (1, "c", False), (2, "c", False), (3, "c", False), (4, "c", True)]


def test_blaming_a_method_prints_nothing_of_python_s_own_on_stderr():
    """Blame compiles each method (a reply's) in this process: `return x is 1` printed Python's SyntaxWarning,
    with the method's line, on the user's terminal."""
    import subprocess
    import sys

    program = ("from tracing.blame import blame_function\n"
               "lines = blame_function('def f(self, x):\\n    return x is 1\\n', None, 'a')\n"
               "print([line.executable for line in lines])")
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60,
                          cwd=str(__import__("pathlib").Path(__file__).parents[1]))
    assert done.returncode == 0 and done.stdout == "[False, True]\n" and done.stderr == "", done


@pytest.mark.slow
def test_rerun_recording_shows_the_lines_that_ran_at_every_step(tmp_path, capsys):
    """The live recording of a traced episode holds, per method, its source with ▶ on the lines that ran; at every
    step the latest document (what the viewer shows there) marks exactly that step's ``lines_run``."""
    from tests.test_rerun import dump

    store = Store(tmp_path / "store.duckdb")
    live = tmp_path / "live"
    assert main(["eval", "tests/policies/pong_competent.py", "--trace", "--max-steps", "120", "--rerun", str(live),
                 "--store", str(store.path), "--json"]) == 0
    [episode] = json.loads(capsys.readouterr().out)["episodes"]
    content = dump(live / f"{episode['episode_id']}.rrd")[str(live / f"{episode['episode_id']}.rrd")]
    for function in ("predict_ball_trajectory", "select_action"):
        docs = {int(k): v[0] if isinstance(v, list) else v
                for k, v in content["timelines"]["step"][f"/lines/{function}:TextDocument:text"].items()}
        assert 0 in docs and len(docs) < 120, "a document where the lines change, not one per step"
        nodes = dict(store.query("SELECT step, lines_run FROM nodes WHERE episode_id = ? AND function = ?",
                                 [episode["episode_id"], function]))
        for step, lines in nodes.items():
            shown = docs[max(k for k in docs if k <= step)]
            listing = shown.split("```python\n")[1].splitlines()
            marked = [int(row.split()[1]) for row in listing if row.startswith("▶")]
            assert marked == lines, (function, step)


def test_a_run_shipped_as_a_bundle_keeps_its_blame(run, tmp_path):
    """The Ray executor ships runs as bundles (store/bundle.py): the lines travel with the versions."""
    from store.bundle import export_run, import_run

    store, run_id = run
    with store.read() as con:
        bundle = export_run(con, run_id)
    other = Store(tmp_path / "driver.duckdb")
    with other.write() as con:
        import_run(con, bundle)
    query = "SELECT * FROM line_blame WHERE run_id = ? ORDER BY ALL"
    assert other.query(query, [run_id]) == store.query(query, [run_id]) != []


def test_a_rollback_version_carries_its_targets_origins(tmp_path):
    """Versions written as the optimizer writes them (pipeline/play/versions.py rows, store/writer.py): a rollback to
    the starting code keeps iteration 0's origins, and the next change is diffed against the rolled-back code."""
    from pipeline.play.versions import policy_version_row
    from store.lines import version_blame
    from store.writer import insert_policy_version, insert_run

    store = Store(tmp_path / "store.duckdb")
    v0 = inspect_policy(pong_policy(V0))
    v1 = inspect_policy(pong_policy(V1.split("\n", 1)[1]))
    v2 = inspect_policy(pong_policy(V3.split("\n", 1)[1]))
    with store.write() as con:
        insert_run(con, "run", "optimize", "pong", {}, v0.text, v0.version_id, {})
        insert_policy_version(con, policy_version_row(v0, "run", 0, "initial"))
        insert_policy_version(con, policy_version_row(v1, "run", 1, "llm", parent_id=v0.version_id))
        insert_policy_version(con, policy_version_row(v0, "run", 1, "rollback", parent_id=v1.version_id))
        insert_policy_version(con, policy_version_row(v2, "run", 2, "llm", parent_id=v0.version_id))
        origins = {version: [(r["line_no"], r["origin_iteration"]) for r in version_blame(con, "run", version)
                             if r["function"] == "select_action"]
                   for version in (v0.version_id, v2.version_id)}
    assert origins[v0.version_id] == [(k, 0) for k in range(1, 10)], "the rollback kept the starting code's origins"
    assert [i for _, i in origins[v2.version_id]] == [0, 0, 0, 0, 0, 0, 2, 0, 2, 2, 2], \
        "diffed against the rolled-back code, not iteration 1's: the lines iteration 1 added count as new in 2"
