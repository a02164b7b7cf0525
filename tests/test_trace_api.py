"""Policy files written for Microsoft's Trace (``import opto.trace as trace``) run unchanged: checked, played,
traced, optimized, blamed and compared like codearcade's own, with nothing named ``opto`` installed.

The authors' own files are the real test: set ``CODEARCADE_AUTHORS_REPO`` to a clone (a work tree or a bare git
directory) of ameliakuang/LLM-Game-Playing-Agents; by default the mirror at :data:`AUTHORS_MIRROR` is used,
and those tests skip when neither is there.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import POLICIES, json_reply, run_main
from tests.test_sandbox import REFUSED
from tracing.capture import NodeRecorder
from tracing.policy_file import PolicyLoadError, inspect_policy, load_policy, policy_from_script, replace_methods
from tracing.sandbox import TRACE_API, PolicyCodeError, check_source

TRACE_TWIN = POLICIES / "pong_competent_trace.py"
TRACING_TWIN = POLICIES / "pong_competent.py"
STEPS = 600

TRACE_HEADER = "import opto.trace as trace\nfrom opto.trace import bundle, node, Module, model, GRAPH\n"
BALL_OBS = {"Player": {"x": 140, "y": 100, "w": 4, "h": 15, "dx": 0, "dy": 0},
            "Ball": {"x": 100, "y": 50, "w": 2, "h": 4, "dx": 2, "dy": 1}}


def trace_policy(body: str, header: str = TRACE_HEADER) -> str:
    """A Trace-style policy: ``header``, then ``class Policy`` whose body (methods, 4 spaces in) is given."""
    return header + "\n\n@trace.model\nclass Policy(Module):\n" + body


# --- imports: Trace's policy API admitted, and nothing else of Trace --------------------------------------------

@pytest.mark.parametrize("source", [
    TRACE_HEADER,
    "from opto import trace\n",
    "import opto.trace\n",
    "from opto.trace.nodes import node, GRAPH, Node\nfrom opto.trace.modules import Module, model\n"
    "from opto.trace.bundle import bundle\nfrom opto.trace.errors import ExecutionError\n",
    "from opto.trace import *\n",
    "from opto.trace import nodes\n",
])
def test_trace_policy_imports_pass_the_source_check(source):
    check_source(source)


@pytest.mark.parametrize("source, fragment", [
    ("import opto\n", "import opto.trace as trace"),
    ("import opto.optimizers\n", "import of 'opto.optimizers' is not allowed"),
    ("from opto.optimizers import OptoPrime\n", "import of 'opto.optimizers' is not allowed"),
    ("from opto.trace.bundle import ExceptionNode\n", "'ExceptionNode' is not part of Trace's policy API"),
    ("from opto.trace import propagators\n", "'propagators' is not part of"),
    ("from opto import utils\n", "'utils' is not part of"),
    ("import opto.utils.llm as llm\n", "import of 'opto.utils.llm' is not allowed"),
    ("import optoprime\n", "import of 'optoprime' is not allowed"),
])
def test_the_rest_of_trace_is_refused_in_one_line(source, fragment):
    with pytest.raises(PolicyCodeError) as err:
        check_source(source, "<t>")
    assert fragment in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("source, fragment", REFUSED)
def test_everything_refused_before_is_refused_beside_trace_imports(source, fragment):
    with pytest.raises(PolicyCodeError) as err:
        check_source(TRACE_HEADER + source, "<t>")
    assert fragment in str(err.value)


def _call(body: str, header: str = TRACE_HEADER):
    """Load a Trace-style policy whose ``__call__`` body is given and call it on :data:`BALL_OBS`."""
    lines = "".join(f"        {line}\n" for line in body.splitlines())
    return load_policy(trace_policy(f"    def __call__(self, obs):\n{lines}", header), "p.py").policy(BALL_OBS)


@pytest.mark.parametrize("body, error", [
    ("return getattr(trace, 'TraceBundledMethod')", AttributeError),  # only Trace's names are offered
    ("return getattr(trace, '_Graph')", AttributeError),
    ("setattr(trace, 'bundle', None)", AttributeError),
    ("from opto.trace import ExceptionNode\nreturn 0", PolicyLoadError),  # refused by the check, statically
])
def test_the_trace_views_offer_only_the_policy_api(body, error):
    with pytest.raises(error):
        _call(body)


@pytest.mark.parametrize("name, fromlist", [("opto.optimizers", None), ("opto", None), ("opto.trace", ("Graph",)),
                                            ("opto", ("utils",)), ("opto.trace.bundle", ("FunModule",))])
def test_the_import_hook_refuses_the_rest_of_trace_at_run_time_too(name, fromlist):
    import tracing.trace_api as api
    from tracing.sandbox import safe_builtins

    with pytest.raises(ImportError):
        safe_builtins(api)["__import__"](name, None, None, fromlist, 0)


def test_every_name_of_the_api_is_codearcades_own():
    import tracing.trace_api as api

    assert sorted(api.__all__) == sorted(TRACE_API["opto.trace"])
    for module, names in TRACE_API.items():
        got = _call(f"import {module} as m\nreturn [getattr(m, n) for n in {list(names)!r}]"
                    if module == "opto.trace" else
                    f"from {module} import {', '.join(names)}\nreturn [{', '.join(names)}]")
        assert got == [getattr(api, n) for n in names], module
    assert _call("return [trace.bundle, trace.nodes.node]", "from opto import trace\nModule = trace.Module\n") == \
        [api.bundle, api.node]


def test_no_opto_package_is_installed_and_a_real_trace_is_not_shadowed(tmp_path):
    # a stand-in for a real Trace install: importing it leaves a file behind
    marker = tmp_path / "real_trace_imported"
    (tmp_path / "opto" / "trace").mkdir(parents=True)
    (tmp_path / "opto" / "__init__.py").write_text("")
    (tmp_path / "opto" / "trace" / "__init__.py").write_text(
        f"open({str(marker)!r}, 'w').close()\nREAL = True\n")
    script = (
        "import importlib.util, sys\n"
        "assert importlib.util.find_spec('opto') is None, 'codearcade must not install a package named opto'\n"
        f"sys.path.insert(0, {str(tmp_path)!r})\n"
        "from tracing.policy_file import load_policy\n"
        f"policy = load_policy(open({str(TRACE_TWIN)!r}).read(), 'p.py').policy\n"
        "assert 'opto' not in sys.modules and 'opto.trace' not in sys.modules\n"
        "print(policy({}))\n"
        "import opto.trace\n"  # the user's own import still finds the real one
        "print(opto.trace.REAL)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["0", "True"]
    assert marker.exists(), "the stand-in was importable, and imported only by the user's own import"


# --- Trace's semantics -----------------------------------------------------------------------------------------

def test_bundle_takes_tracing_parameters_in_traces_order_and_init_is_not_called():
    text = trace_policy('''    def init(self):
        raise RuntimeError("Trace never calls init")

    def __call__(self, obs):
        return self.act(self.see(obs), obs)

    @bundle("[see] where the ball is", trainable=True, allow_external_dependencies=True)
    def see(self, obs):
        return obs["Ball"]["y"]

    @trace.bundle(catch_execution_error=False)
    def act(self, y, obs):
        return 3 if y > obs["Player"]["y"] else 2
''')
    info = inspect_policy(text, "p.py")
    assert [(m.name, m.trainable) for m in info.methods] == [("see", True), ("act", False)]
    policy = load_policy(text, "p.py").policy
    assert [p.name for p in policy.parameters()] == ["see"]
    assert [(p.name, p.trainable) for p in policy.parameters(trainable_only=False)] == [("see", True), ("act", False)]
    assert policy(BALL_OBS) == 2
    with NodeRecorder() as recorder:
        recorder.begin_step(0, BALL_OBS)
        policy(BALL_OBS)
    nodes = recorder.table().to_pylist()
    assert [(n["function"], n["output"], n["parents"]) for n in nodes] == [("see", "50", []), ("act", "2", [0])]


def test_node_is_the_value_and_graph_and_stop_tracing_do_nothing():
    body = '''    def __call__(self, obs):
        GRAPH.clear()
        with trace.stop_tracing():
            y = self.see(node(obs, name="obs"))
        return node(y) if not isinstance(y, trace.Node) else -1

    @bundle(trainable=True)
    def see(self, obs):
        return 2 if obs["Ball"]["y"] < 100 else 3
'''
    policy = load_policy(trace_policy(body), "p.py").policy
    with NodeRecorder() as recorder:
        recorder.begin_step(0, BALL_OBS)
        assert policy(BALL_OBS) == 2
    assert json.loads(recorder.table().to_pylist()[0]["inputs"]) == {"obs": {"$ref": "obs"}}, "node(obs) is obs"


def test_a_trainable_value_is_refused_with_what_to_do():
    text = trace_policy("    def __init__(self):\n        self.k = node(3, trainable=True)\n\n"
                        "    def __call__(self, obs):\n        return 0\n")
    with pytest.raises(PolicyLoadError) as err:
        load_policy(text, "p.py")
    message = str(err.value)
    assert message.startswith("p.py:") and "trainable=True" in message and "@bundle(trainable=True)" in message


def test_an_error_in_a_bundled_method_is_an_execution_error_as_in_trace():
    body = '''    def __call__(self, obs):
        try:
            return self.see(obs)
        except trace.ExecutionError as e:
            return 0 if "(ZeroDivisionError) division by zero" in str(e) else 1

    @bundle(trainable=True)
    def see(self, obs):
        return obs["Ball"]["y"] / 0
'''
    policy = load_policy(trace_policy(body), "p.py").policy
    with NodeRecorder() as recorder:
        recorder.begin_step(0, BALL_OBS)
        assert policy(BALL_OBS) == 0, "caught as trace.ExecutionError"
    (row,) = recorder.table().to_pylist()
    assert (row["exc_type"], row["exc_source"]) == ("ZeroDivisionError", 'return obs["Ball"]["y"] / 0'), \
        "the node records the original exception and its line"

    from pipeline.boundary.policy import describe_exception

    text = trace_policy(body.replace("except trace.ExecutionError", "except KeyError"))
    line = text.splitlines().index('        return obs["Ball"]["y"] / 0') + 1
    with pytest.raises(Exception) as err:
        load_policy(text, "p.py").policy(BALL_OBS)
    assert describe_exception(err.value) == (f'ExecutionError: (ZeroDivisionError) division by zero at line {line}: '
                                             '`return obs["Ball"]["y"] / 0`'), "the episode's reason names the line"


# --- the twin: a Trace-API policy plays as its tracing twin ------------------------------------------------------

def test_the_twins_trainable_methods_are_the_same_text():
    trace_info, tracing_info = inspect_policy(TRACE_TWIN.read_text()), inspect_policy(TRACING_TWIN.read_text())
    assert [(m.name, m.source, m.trainable) for m in trace_info.methods] == \
        [(m.name, m.source, m.trainable) for m in tracing_info.methods]
    assert TRACE_TWIN.read_text().startswith('"""') and "import tracing" not in TRACE_TWIN.read_text()


def _eval(store, path) -> dict:
    code, out, err = run_main("eval", path, "--trace", "--max-steps", STEPS, "--store", store.path, "--json")
    assert code == 0, err
    (episode,) = json.loads(out)["episodes"]
    return episode


def test_a_trace_api_policy_plays_the_same_as_its_tracing_twin(store, capsys):
    a, b = _eval(store, TRACE_TWIN), _eval(store, TRACING_TWIN)
    assert a["length"] == b["length"] == STEPS and a["return"] == b["return"] and a["end_reason"] == "truncated"

    def steps(episode_id):
        return store.query("SELECT step, action, reward, score FROM steps WHERE episode_id = ? ORDER BY step",
                           [episode_id])

    def nodes(episode_id):
        return store.query("SELECT step, call_index, function, trainable, inputs, output, exc_type, parents, "
                           "lines_run FROM nodes WHERE episode_id = ? ORDER BY step, call_index", [episode_id])

    assert steps(a["episode_id"]) == steps(b["episode_id"])
    trace_nodes = nodes(a["episode_id"])
    assert len(trace_nodes) == 2 * STEPS and trace_nodes == nodes(b["episode_id"])
    assert len({row[1] for row in steps(a["episode_id"])}) == 3, "it really plays: NOOP, up and down"


# --- optimize, blame, compare: the file goes through unedited ---------------------------------------------------

@pytest.mark.slow
def test_a_trace_api_file_is_optimized_blamed_and_compared_without_edits(store, scripted):
    start = TRACE_TWIN.read_text()
    select = next(m.source for m in inspect_policy(start).methods if m.name == "select_action")
    changed_line = "    if paddle < target - DEAD_ZONE - 1:"
    new_select = select.replace("    if paddle < target - DEAD_ZONE:", changed_line)
    assert new_select != select
    model = scripted([json_reply({"select_action": new_select})])
    code, out, err = run_main("optimize", TRACE_TWIN, "--model", model.model, "--api-base", model.api_base,
                              "--iterations", 1, "--eval-max-steps", 300, "--rollout-steps", 40, "--workers", 1,
                              "--store", store.path, "--json")
    assert code == 0, err
    run_id = json.loads(out)["run_id"]
    rows = store.query("SELECT v.iteration, v.produced_by, v.validation, b.text FROM policy_versions v JOIN blobs b "
                       "ON b.hash = v.source_hash WHERE v.run_id = ? ORDER BY v.iteration", [run_id])
    assert [r[:3] for r in rows] == [(0, "initial", "accepted"), (1, "llm", "accepted")]
    assert rows[0][3] == start
    # the candidate is the same file with the method replaced: imports, decorators and init kept
    assert rows[1][3] == replace_methods(start, {"select_action": new_select})
    assert rows[1][3].startswith(start.split("GAME =")[0]) and rows[1][3].count("    @bundle(trainable=True)\n") == 2
    assert "    def init(self):\n        pass\n" in rows[1][3]

    code, out, err = run_main("blame", run_id, "--iteration", 1, "--json", "--store", store.path)
    assert code == 0, err
    blamed = json.loads(out)
    lines = {f["name"]: f["lines"] for f in blamed["functions"]}
    assert "\n".join(line["text"] for line in lines["select_action"]) + "\n" == new_select
    assert [line["text"] for line in lines["select_action"] if line["origin_iteration"] == 1] == [changed_line]
    assert {line["origin_iteration"] for line in lines["predict_ball_trajectory"]} == {0}

    code, out, err = run_main("compare", TRACE_TWIN, f"{run_id}:{blamed['policy_version_id']}",
                              "--max-steps", 300, "--store", store.path, "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["mode"] == "versions" and report["game"] == "pong"
    added = [line for line in report["diff"].splitlines() if line.startswith("+") and not line.startswith("+++")]
    assert added == [f"+    {changed_line}"], "the two files differ in the changed line only"


# --- new --from: the policy out of a Trace training script ---------------------------------------------------

TRAINING_LOOP = """import os
import gymnasium as gym
from opto.optimizers import OptoPrime
from opto.trace.bundle import ExceptionNode

env = gym.make("ALE/Pong-v5")
UNUSED_SETTING = 5


def optimize_policy(policy, steps=10):
    optimizer = OptoPrime(policy.parameters())
    for _ in range(steps):
        optimizer.step()


if __name__ == "__main__":
    optimize_policy(Policy())
"""


def test_new_from_a_training_script_keeps_the_policy_and_what_it_uses(store, capsys, tmp_path):
    twin = TRACE_TWIN.read_text()
    header, rest = twin.split("GAME = ", 1)
    script = tmp_path / "pong_training.py"
    script.write_text(TRAINING_LOOP.split("\nenv =")[0] + "\n" + header.split('"""', 2)[2] + "GAME = " + rest
                      + "\n\nenv =" + TRAINING_LOOP.split("\nenv =")[1])
    assert "OptoPrime" in script.read_text() and "class Policy" in script.read_text()
    code, out, err = run_main("eval", script, "--store", store.path)
    assert code == 2 and "os" in err, "the script itself is no policy file"

    written = tmp_path / "pong.py"
    code, out, err = run_main("new", written, "--from", script)
    assert code == 0, err
    assert "PADDLE_X" in out and "select_action" in out and "left out 4 import(s)" in out
    text = written.read_text()
    for gone in ("OptoPrime", "gymnasium", "__main__", "UNUSED_SETTING", "optimize_policy", "env =", "import os"):
        assert gone not in text, gone
    def methods(policy_text):
        return [(m.name, m.source, m.trainable) for m in inspect_policy(policy_text).methods]

    assert methods(text) == methods(twin)
    assert _eval(store, written)["return"] == _eval(store, TRACE_TWIN)["return"]


def test_new_from_keeps_every_binding_of_a_name_and_each_import_it_may_make(store, tmp_path):
    """The last binding of a name alone was kept (``SPEED = SPEED * 2``: a NameError at load; ``THRESH += 10``
    dropped, the policy ran on 5), and an import statement with one name policy code may not import was dropped
    whole (``import opto.trace as trace, os.path``: no ``trace``). Written, the policy plays as the script's."""
    script = tmp_path / "train.py"
    script.write_text(textwrap.dedent("""\
        import opto.trace as trace, os.path
        from math import floor, sqrt

        SPEED = 2
        SPEED = SPEED * 2
        THRESH = 5
        THRESH += 10
        UNUSED = os.path.join("a", "b")

        class Policy(trace.Module):
            def __call__(self, obs):
                return self.select_action(obs)

            @trace.bundle(trainable=True)
            def select_action(self, obs):
                if (SPEED, THRESH, floor(sqrt(16))) != (4, 15, 4):
                    raise ValueError(f"the script's values are lost: {SPEED}, {THRESH}")
                return 0
        """))
    written = tmp_path / "policy.py"
    code, out, err = run_main("new", written, "--from", script, "--game", "pong")
    assert code == 0 and "left out 1 import(s)" in out, out + err
    text = written.read_text()
    assert "import opto.trace as trace\nfrom math import floor, sqrt\n" in text and "os.path" not in text, text
    assert "SPEED = SPEED * 2" in text and "THRESH += 10" in text and "UNUSED" not in text
    code, out, err = run_main("eval", written, "--max-steps", "3", "--store", store.path)
    assert code == 0, err
    assert store.query("SELECT end_reason FROM episodes") == [("truncated",)]


def test_new_from_refuses_what_it_cannot_take_and_writes_nothing(tmp_path):
    script = tmp_path / "script.py"
    script.write_text("import os\n\ndef act(obs):\n    return 0\n")
    code, _, err = run_main("new", tmp_path / "p.py", "--from", script, "--game", "pong")
    assert code == 2 and "no class named 'Policy'" in err
    code, _, err = run_main("new", tmp_path / "p.py", "--from", TRACE_TWIN, "--game", "breakout")
    assert code == 2 and "declares GAME = 'pong'" in err
    no_game = tmp_path / "nogame.py"
    no_game.write_text(TRACE_TWIN.read_text().replace('GAME = "pong"\n', ""))
    code, _, err = run_main("new", tmp_path / "p.py", "--from", no_game)
    assert code == 2 and "--game" in err
    assert not (tmp_path / "p.py").exists()
    code, out, err = run_main("new", tmp_path / "p.py", "--from", no_game, "--game", "pong")
    assert code == 0, err
    assert inspect_policy((tmp_path / "p.py").read_text()).game == "pong"


# --- the authors' files ------------------------------------------------------------------------------------------

GAMES_OF_BEST_POLICIES = {"Pong": "pong", "Breakout": "breakout", "SpaceInvaders": "space_invaders"}


def _authors_git_dir() -> Path | None:
    if not os.environ.get("CODEARCADE_AUTHORS_REPO"):
        return None
    root = Path(os.environ["CODEARCADE_AUTHORS_REPO"])
    for candidate in (root / ".git", root):
        if (candidate / "HEAD").is_file():
            return candidate
    return None


def _git(git_dir: Path, *args: str) -> str:
    return subprocess.run(["git", f"--git-dir={git_dir}", *args], capture_output=True, text=True, check=True,
                          timeout=60).stdout


def authors_policy_files() -> list[tuple[str, str, str]]:
    """(path, game, policy text) of every policy in the authors' repository: best_policies/*.py as they are, and
    the policy part of each ``<game>_training.py``."""
    git_dir = _authors_git_dir()
    if git_dir is None:
        return []
    found = []
    for path in _git(git_dir, "ls-tree", "-r", "--name-only", "HEAD").split():
        if path.startswith("best_policies/") and path.endswith(".py"):
            found.append((path, GAMES_OF_BEST_POLICIES[Path(path).stem], _git(git_dir, "show", f"HEAD:{path}")))
        elif "/" not in path and path.endswith("_training.py"):
            found.append((path, path.removesuffix("_training.py"),
                          policy_from_script(_git(git_dir, "show", f"HEAD:{path}"), path).text))
    return found


AUTHORS_FILES = authors_policy_files()


@pytest.mark.skipif(not AUTHORS_FILES, reason="the authors' repository is not here (set CODEARCADE_AUTHORS_REPO)")
def test_every_policy_file_of_the_authors_repository_loads_and_plays():
    from games import get_game
    from games.envs import make_env
    from pipeline.boundary.policy import coerce_action

    assert {game for _, game, _ in AUTHORS_FILES} == {
        "asterix", "breakout", "enduro", "freeway", "pong", "qbert", "seaquest", "space_invaders"}
    loaded = []
    for path, game, text in AUTHORS_FILES:
        assert text.startswith("import opto.trace as trace") or "\nimport opto.trace as trace\n" in text, path
        info = inspect_policy(text, path)
        policy = load_policy(text, path).policy
        assert [p.name for p in policy.parameters()] == [m.name for m in info.trainable] and info.trainable, path
        env = make_env(get_game(game))
        try:
            obs, _ = env.reset(seed=0)
            for _ in range(30):
                obs, *_ = env.step(coerce_action(policy(obs), get_game(game).n_actions))
        finally:
            env.close()
        loaded.append(path)
    print(f"{len(loaded)} policy files of the authors' repository loaded and played: {', '.join(loaded)}")
    assert len(loaded) == len(AUTHORS_FILES) >= 11


def test_an_exception_without_a_message_is_described_without_an_empty_one():
    """``MemoryError()`` and the like say nothing: the episode's error read ``MemoryError:  at line 5``."""
    from pipeline.boundary.policy import describe_exception

    assert describe_exception(MemoryError()) == "MemoryError"
    assert describe_exception(ValueError("bad")) == "ValueError: bad"
