"""Trainable code parameters, node capture and policy files."""

from __future__ import annotations

import json

import pytest

import tracing as trace
from tests.conftest import EXAMPLES, pong_policy
from tracing.bounded import TOO_DEEP as TOO_DEEP_MARK
from tracing.capture import OBS_REF, NodeRecorder, to_json
from tracing.metrics import function_metrics, max_if_depth, policy_metrics
from tracing.policy_file import PolicyLoadError, inspect_policy, load_policy, replace_methods, version_id
from tracing.sandbox import PolicyCodeError

BALL_OBS = {"Player": {"x": 140, "y": 100, "w": 4, "h": 15, "dx": 0, "dy": 0},
            "Ball": {"x": 100, "y": 50, "w": 2, "h": 4, "dx": 2, "dy": 1}}


def test_paper_style_policy_runs_with_only_the_import_changed():
    loaded = load_policy((EXAMPLES / "pong.py").read_text(), "pong.py")
    policy = loaded.policy
    assert isinstance(policy, trace.Module)
    assert policy(BALL_OBS) in (2, 3)
    names = [p.name for p in policy.parameters()]
    assert names == ["predict_ball_trajectory", "select_action"]


def test_parameter_source_docstring_and_replacement():
    policy = load_policy((EXAMPLES / "pong.py").read_text(), "pong.py").policy
    param = policy.parameter("select_action")
    assert param.source.startswith("def select_action(self, predicted_ball_y, obs):")
    assert "@trace.bundle" not in param.source
    assert "Actions: 0 NOOP" in param.docstring
    assert param.signature == "select_action(self, predicted_ball_y, obs)"

    param.set_source('''
        def select_action(self, predicted_ball_y, obs):
            """Always stay."""
            return 0
    ''')
    assert policy(BALL_OBS) == 0, "new source text in, new behaviour out"
    assert param.docstring == "Always stay."
    assert policy.parameter("predict_ball_trajectory").fn(policy, BALL_OBS) == 50


def test_set_source_rejects_and_keeps_the_old_code():
    policy = load_policy((EXAMPLES / "pong.py").read_text(), "pong.py").policy
    param = policy.parameter("select_action")
    before = param.source
    for bad in ("def other(self, a, b):\n    return 0\n", "def select_action(self, a, b):\n    return (\n",
                "def select_action(self, a, b):\n    import os\n    return 0\n", "x = 1\n"):
        with pytest.raises(PolicyCodeError):
            param.set_source(bad)
        assert param.source == before
    assert policy(BALL_OBS) in (2, 3)


def test_model_decorator_and_forward():
    @trace.model
    class Plain:
        def forward(self, obs):
            return 1

    assert issubclass(Plain, trace.Module) and Plain()({}) == 1


def test_node_capture_records_inputs_outputs_and_parents():
    policy = load_policy((EXAMPLES / "space_invaders.py").read_text(), "si.py").policy
    recorder = NodeRecorder()
    obs = {"Player": {"x": 50, "y": 185, "w": 7, "h": 10, "dx": 0, "dy": 0}}
    with recorder:
        for step in range(3):
            recorder.begin_step(step, obs)
            policy(obs)
    rows = recorder.table().to_pylist()
    assert len(rows) == 9
    by_step = [r for r in rows if r["step"] == 1]
    assert [r["function"] for r in by_step] == ["decide_shoot", "decide_movement", "combine_actions"]
    shoot, move, combine = by_step
    assert json.loads(shoot["inputs"]) == {"obs": OBS_REF}
    assert combine["parents"] == [0, 1]
    assert json.loads(combine["inputs"]) == {"shoot": json.loads(shoot["output"]), "movement": 0}
    assert all(r["duration_us"] >= 0 and r["trainable"] for r in rows)


def test_node_capture_records_exceptions_with_the_failing_line():
    text = pong_policy("""
        x = obs["Nothing"]
        return 0
    """)
    policy = load_policy(text, "broken.py").policy
    recorder = NodeRecorder()
    with recorder:
        recorder.begin_step(0, BALL_OBS)
        with pytest.raises(KeyError):
            policy(BALL_OBS)
    rows = recorder.table().to_pylist()
    failing = [r for r in rows if r["exc_type"]]
    assert len(failing) == 1
    assert failing[0]["function"] == "select_action"
    assert failing[0]["exc_source"] == 'x = obs["Nothing"]'
    assert text.splitlines()[failing[0]["exc_line"] - 1].strip() == 'x = obs["Nothing"]'


def test_capture_is_off_without_a_recorder():
    policy = load_policy((EXAMPLES / "pong.py").read_text(), "pong.py").policy
    assert policy(BALL_OBS) in (2, 3)  # no recorder active: nothing is recorded, nothing fails


def test_to_json_is_deterministic_and_valid():
    class Thing:
        pass

    text = to_json({"a": float("nan"), "b": Thing(), "c": (1, 2), "d": {3}})
    data = json.loads(text)
    assert data["a"] == "NaN" and data["c"] == [1, 2] and data["d"] == [3]
    assert "0x" not in data["b"]
    assert len(to_json(list(range(100_000)))) < 3000


def test_inspect_policy_reads_constants_and_methods_without_running():
    text = (EXAMPLES / "breakout.py").read_text().replace('GAME = "breakout"', 'GAME = "breakout"\nROLLOUT_STEPS = 120\nFEEDBACK = {"high": 50, "low": 0}')
    info = inspect_policy(text, "breakout.py")
    assert info.game == "breakout"
    assert info.constants["ROLLOUT_STEPS"] == 120 and info.constants["FEEDBACK"]["high"] == 50
    assert [m.name for m in info.trainable] == [
        "predict_ball_trajectory", "generate_paddle_target", "select_paddle_action"]
    assert info.version_id == version_id(info.text)


def test_task_settings_come_from_the_game_module_unless_the_file_overrides_them():
    from pipeline.optimizer.task import task_settings

    scaffold = inspect_policy((EXAMPLES / "breakout.py").read_text(), "breakout.py")
    assert "ROLLOUT_STEPS" not in scaffold.constants, "the task lives in games/breakout.py, not the scaffold"
    settings = task_settings(scaffold, "breakout")
    assert settings.rollout_steps == 300 and settings.eval_max_steps == 4000 and settings.feedback.high == 300
    own = inspect_policy(scaffold.text.replace('GAME = "breakout"', 'GAME = "breakout"\nROLLOUT_STEPS = 120'), "b.py")
    assert task_settings(own, "breakout").rollout_steps == 120 and task_settings(own, "breakout").feedback.high == 300


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("import os\nclass Policy: pass\n", "import of 'os' is not allowed"),
        ("class Policy(:\n", "syntax error"),
        ("x = 1\n", "no class named 'Policy'"),
        ("from random import _os\nclass Policy: pass\n", "private name"),
        # bundled methods the trace could not attribute: they played untraced and forfeited every traced game
        ("import opto.trace as trace\nclass Base(trace.Module):\n    @trace.bundle(trainable=True)\n"
         "    def predict(self, obs):\n        return 0\nclass Mid(Base):\n    pass\nclass Policy(Mid):\n"
         "    def __call__(self, obs):\n        return self.predict(obs)\n",
         "bad.py:4: Base.predict is bundled in a base class of Policy"),
        ("import opto.trace as trace\nTRAIN = True\nclass Policy(trace.Module):\n    @trace.bundle(trainable=TRAIN)\n"
         "    def act(self, obs):\n        return 0\n", "bad.py:5: write @trace.bundle(trainable=True)"),
        ("import opto.trace as trace\nclass Policy(trace.Module):\n    @trace.bundle(True)\n"
         "    def act(self, obs):\n        return 0\n", "bad.py:4: write @trace.bundle(trainable=True)"),
        ("import tracing as trace\nclass Policy(trace.Module):\n    @trace.bundle(trainable=1)\n"
         "    def act(self, obs):\n        return 0\n", "bad.py:4: write @trace.bundle(trainable=True)"),
    ],
)
def test_inspect_policy_errors_are_one_line(text, fragment):
    with pytest.raises(PolicyLoadError) as err:
        inspect_policy(text, "bad.py")
    assert fragment in str(err.value) and "\n" not in str(err.value) and "bad.py" in str(err.value)


def test_a_policy_s_own_dataclasses_take_typed_fields():
    """``@dataclass`` with a typed field failed to load ("'NoneType' object has no attribute '__dict__'"): the
    policy's annotations are strings (the loader's ``from __future__ import annotations``), which dataclasses
    resolves through the class's module, and the policy had none in ``sys.modules``."""
    text = pong_policy("self.memory.calls += 1\nreturn 0").replace(
        "@trace.model\nclass Policy", "from dataclasses import dataclass, field\n\n\n@dataclass\nclass Memory:\n"
        "    calls: int = 0\n    seen: list = field(default_factory=list)\n\n\n@trace.model\nclass Policy").replace(
        "    def __call__", "    def __init__(self):\n        self.memory = Memory()\n\n    def __call__")
    loaded = load_policy(text, "dc.py")
    # Trace's own bundle takes a description first: with the flag a keyword, it is not refused
    assert [m.trainable for m in inspect_policy(text.replace("@trace.bundle(trainable=True)\n    def select_action",
                                                             '@trace.bundle("acts", trainable=True)\n    def '
                                                             "select_action"), "d.py").methods] == [True, True]
    assert loaded.policy.memory.calls == 0 and loaded.policy.memory.seen == []


def test_a_bundled_lambda_is_refused_with_what_to_write():
    """A lambda under the bundle decorator said "RuntimeError: Error calling __set_name__ on 'BundledMethod'
    instance": the error of the bundle itself, wrapped by Python, said nothing of what to fix."""
    text = pong_policy("return 0") + "\n    act = trace.bundle(trainable=True)(lambda self, obs: 0)\n"
    line = text.count("\n")
    with pytest.raises(PolicyLoadError) as err:
        load_policy(text, "lam.py")
    assert str(err.value).startswith(f"lam.py:{line}: cannot find the source of Policy.<lambda>: bundle a method "
                                     "written with `def`"), str(err.value)


def test_load_policy_reports_errors_in_constructor():
    text = pong_policy("return 0").replace("    def __call__", "    def __init__(self):\n        1 / 0\n\n    def __call__")
    with pytest.raises(PolicyLoadError) as err:
        load_policy(text, "p.py")
    assert "ZeroDivisionError" in str(err.value) and "p.py:" in str(err.value)


def test_load_policy_times_out_module_code():
    with pytest.raises(PolicyLoadError) as err:
        load_policy("while True:\n    pass\nclass Policy: pass\n", "loop.py", time_limit_s=0.2)
    assert "time limit" in str(err.value)


def test_replace_methods_keeps_everything_else():
    text = (EXAMPLES / "pong.py").read_text()
    new = replace_methods(text, {"select_action": "def select_action(self, predicted_ball_y, obs):\n    return 0\n"})
    assert "        return 0\n" in new
    assert new.count("@trace.bundle(trainable=True)") == 2
    assert "def predict_ball_trajectory" in new and "random.choice" not in new
    policy = load_policy(new, "new.py").policy
    assert policy(BALL_OBS) == 0
    with pytest.raises(PolicyCodeError):
        replace_methods(text, {"no_such_method": "def no_such_method(self):\n    pass\n"})


def test_metrics():
    source = (
        "def f(self, x):\n"
        "    if x > 1:\n"
        "        if x > 2:\n"
        "            return 1\n"
        "    elif x < 0:\n"
        "        return 2\n"
        "    return 3\n"
    )
    m = function_metrics(source)
    assert m.complexity == 4 and m.max_if_depth == 2 and m.loc == 7
    import ast

    assert max_if_depth(ast.parse("if a:\n    pass\nelif b:\n    pass\nelif c:\n    pass\n")) == 1
    whole = policy_metrics((EXAMPLES / "pong.py").read_text())
    assert whole.loc > 50 and whole.complexity >= 4 and whole.max_if_depth == 1


@pytest.mark.parametrize("workers", [1, 0], ids=["policy process", "in process"])
def test_traced_node_rows_are_stored_as_before(workers, store):
    """Node capture's fast paths (the usual values encoded without ``json.dumps``, rows kept as tuples) store
    exactly what it stored before them: every column but ``duration_us`` of each node of fixed traced episodes,
    against the rows the earlier code left (``tests/fixtures/make_traced_nodes.py``). ``pong_traced_values.py``
    passes every kind of value capture encodes, exceptions, cut and truncated values included."""
    import gzip

    from pipeline.play.evaluate import EvalConfig, evaluate
    from tests.fixtures.make_traced_nodes import HERE, POLICIES, RNG_KEY, STEPS, node_rows

    with gzip.open(HERE / "traced_nodes.json.gz", "rt", encoding="utf-8") as fixture:
        before = json.load(fixture)
    root = HERE.parents[1]
    for policy in POLICIES:
        config = EvalConfig(episodes=1, max_steps=STEPS, trace=True, workers=workers, rng_key=RNG_KEY)
        rows = node_rows(store, evaluate(root / policy, config, store).run_id)
        assert json.loads(json.dumps(rows, ensure_ascii=False)) == before[policy], policy


@pytest.mark.parametrize("value", [
    None, True, False, 0, -7, 2**70, 1.5, -0.0, 1e300, 5e-324, float("nan"), float("inf"), "", "plain",
    "bällé ✓ \"q\" \\ \n\t\x00 \ud800", "[" * 80, "x" * 25_000, (1, "a"), [1, [2, [3]]], {"k": {"j": None}},
    {3: "int key", "s": {1, 2}}, [float("nan")], {"deep": [[[[]]]] * 3},
    pytest.param(10**5000, id="an int of 5,001 digits"), pytest.param([1, {"n": -10**4400}], id="one inside"),
])
def test_to_json_writes_what_json_dumps_writes(value):
    """The fast paths of ``to_json`` (scalars, a reused C encoder) give json.dumps's own text for every value it
    can write, and the documented markers for the rest."""
    import math

    from tracing.capture import _jsonable

    try:
        expected = json.dumps(value, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError):  # NaN, infinities, sets, int keys beside str keys: written as documented
        expected = json.dumps(_jsonable(value), separators=(",", ":"))
    text = to_json(value)
    if len(expected) > 20_000:
        assert json.loads(text)["$truncated"] == len(expected)
    elif expected.count("[") + expected.count("{") <= 64:
        assert text == expected
    else:
        assert text == expected or TOO_DEEP_MARK in text
    if isinstance(value, float) and math.isfinite(value):
        assert text == repr(value)


def test_to_json_recovers_after_a_value_it_cannot_write():
    """The reused encoder forgets the containers it was inside of when a value fails half-way (here a circular
    list): the same list, no longer circular, is then written as json.dumps writes it (a stale mark would send it
    down the fallback, which writes the key ``True`` as ``"True"``, not ``"true"``)."""
    circular: list = [{True: 1}]
    circular.append(circular)
    assert TOO_DEEP_MARK in to_json(circular)
    circular.pop()
    assert to_json(circular) == json.dumps(circular, separators=(",", ":")) == '[{"true":1}]'


def test_to_json_inside_to_json_leaves_the_outer_value_alone():
    """A dict subclass's ``items()`` runs while the encoder is inside it: a value it encodes there (one that fails,
    even) gets an encoder of its own, so the outer value is still written as json.dumps writes it."""
    inner = []

    class Talkative(dict):
        def items(self):
            inner.append(to_json([float("nan")]))
            return super().items()

    value = [Talkative(a=1), {True: 1}]
    assert to_json(value) == json.dumps(value, separators=(",", ":")) == '[{"a":1},{"true":1}]'
    assert inner and set(inner) == {'["NaN"]'}


def test_inputs_of_the_usual_call_are_the_json_of_their_dict():
    """A call with positional scalars and the observation is encoded directly; its text is the generic one."""
    recorder = NodeRecorder()
    obs = {"Ball": {"x": 1, "y": 2, "w": 1, "h": 1, "dx": 0, "dy": 0}}
    recorder.begin_step(0, obs)

    def method(self, obs, y, flag, name, ratio, nothing):
        return None

    args = (obs, 7, True, "ünï", 0.25, None)
    generic = to_json({"obs": OBS_REF, "y": 7, "flag": True, "name": "ünï", "ratio": 0.25, "nothing": None})
    assert recorder._encode_inputs(method, args, {}) == generic
    with_keyword = to_json({"obs": OBS_REF, "y": 7, "flag": False})
    assert recorder._encode_inputs(method, args[:2], {"flag": False}) == with_keyword
    assert recorder._encode_inputs(method, (float("nan"),), {}) == to_json({"obs": "NaN"})


UNPRINTABLE = pong_policy("""
class Unprintable(Exception):
    def __str__(self):
        raise RuntimeError("no text for you")
raise Unprintable()
""")
LONG_MESSAGE = pong_policy("""
raise ValueError("x" * 100_000)
""")


@pytest.mark.parametrize("workers", ["1", "0"], ids=["policy process", "in process"])
@pytest.mark.parametrize("text, raising, message", [
    (UNPRINTABLE, "raise Unprintable()", "<message not shown: its __str__ raised RuntimeError>"),
    (LONG_MESSAGE, 'raise ValueError("x" * 100_000)', "x" * 960 + "… [cut 99,040 characters]"),
], ids=["__str__ raises", "100,000-character message"])
def test_a_policy_exception_is_named_at_its_own_line_whatever_its_message(text, raising, message, workers, store,
                                                                          tmp_path, capsys):
    """An exception whose ``__str__`` raised lost its node row, and the episode's error named the ``__str__``'s
    RuntimeError at its line; a 100,000-character message pushed ``at line N`` past the error's cap. The node row
    is kept, and the error names the policy's exception, its message bounded (or a placeholder), then its line."""
    from pipeline.cli import main

    path = tmp_path / "policy.py"
    path.write_text(text)
    line = text.splitlines().index(" " * 8 + raising) + 1
    name = raising.split()[1].split("(")[0]
    main(["eval", str(path), "--trace", "--episodes", "1", "--max-steps", "3", "--workers", workers,
          "--store", str(store.path)])
    error = f"{name}: {message} at line {line}: `{raising}`"
    assert store.query("SELECT end_reason, error FROM episodes") == [("policy_error", error)]
    assert f"ended with policy_error: {error}" in capsys.readouterr().err
    node = store.query("SELECT exc_type, exc_line, exc_source, exc_message FROM nodes WHERE exc_type IS NOT NULL "
                       "AND function = 'select_action'")
    assert [row[:3] for row in node] == [(name, line, raising)]
    kept = node[0][3]
    assert kept == (message if name == "Unprintable" else "x" * 1_960 + "… [cut 98,040 characters]")


def test_a_policy_file_s_step_caps_are_held_to_their_flags_ranges():
    """A file's ``ROLLOUT_STEPS = 4611686018427387904`` was taken: the run played its whole training game and ended in
    a DuckDB conversion error (a traceback) when the episode was stored; it is held to ``--rollout-steps``' range."""
    from pipeline.optimizer.task import task_settings

    scaffold = (EXAMPLES / "breakout.py").read_text()
    for constant in ("ROLLOUT_STEPS", "EVAL_MAX_STEPS"):
        own = inspect_policy(scaffold.replace('GAME = "breakout"', f'GAME = "breakout"\n{constant} = {2**62}'), "b.py")
        with pytest.raises(ValueError, match=f"^b.py: {constant} must be within \\[1, 2147483647\\]"):
            task_settings(own, "breakout")


HOSTILE_BAND_VALUES = ["5", None, True, [], {}, -1, 0, 2.5, 10**400, -(10**400), 1e999, -1e999, "{score}"]
"""What a policy file's FEEDBACK may hold for a number or a message (a literal ``1e999`` is infinity)."""
HOSTILE_TEMPLATES = ["{score:g} of {target}", "{nope}", "{score", "{0}", "{score.real}", "{gap:d}", "{target[0]}",
                     "plain", "{{score}}", "}"]


def test_a_policy_file_s_feedback_bands_are_refused_in_a_line_or_read_back_as_recorded():
    """A file's ``FEEDBACK`` with a number past a float (an int of 401 digits) ended ``optimize`` in an
    OverflowError's traceback; one with a message that is no template (``{nope}``) started the run, which then
    refused its own record as a store "changed by hand or damaged". Over 600 drawn FEEDBACK constants (numbers,
    texts, infinities, huge ints, templates good and bad, keys missing), each is refused in one line naming the file,
    or taken; and what is taken, recorded as the loop records it, reads back as the same bands
    (``FeedbackBands.from_record``)."""
    import random
    from dataclasses import asdict

    from pipeline.optimizer.feedback import FeedbackBands
    from pipeline.optimizer.task import task_settings

    scaffold = (EXAMPLES / "pong.py").read_text()
    rng, taken, refused = random.Random(20261208), 0, 0
    for _ in range(600):
        band: dict = {}
        for key in ("high", "low", "target"):
            if rng.random() < 0.8:
                band[key] = rng.choice(HOSTILE_BAND_VALUES) if rng.random() < 0.25 else rng.choice([21, -21, 0.5])
        if rng.random() < 0.7:
            band["messages"] = {stage: rng.choice(HOSTILE_TEMPLATES + [5, None]) if rng.random() < 0.3 else "{gap:g}"
                                for stage in rng.sample(["high", "medium", "low", 3], rng.randrange(4))}
        feedback = rng.choice([band, band, band, [band], "bands"])
        written = repr(feedback).replace("inf", "1e999")  # a literal Python reads as infinity
        info = inspect_policy(scaffold.replace('GAME = "pong"', f'GAME = "pong"\nFEEDBACK = {written}'), "f.py")
        assert info.constants["FEEDBACK"] == feedback
        try:
            bands = task_settings(info, "pong").feedback
        except ValueError as exc:
            assert str(exc).startswith("f.py: FEEDBACK ") and "\n" not in str(exc), str(exc)
            refused += 1
            continue
        assert FeedbackBands.from_record(json.loads(json.dumps(asdict(bands))), "run") == bands
        taken += 1
    assert taken > 50 and refused > 300, (taken, refused)



@pytest.mark.parametrize("constant", ["ROLLOUT_STEPS", "EVAL_MAX_STEPS", "INSTRUCTION"])
def test_a_policy_file_s_task_constants_of_another_type_are_refused_in_a_line(constant):
    """``ROLLOUT_STEPS = 1e999`` ended ``optimize`` in an OverflowError's traceback, ``= None`` or ``= []`` in a
    TypeError's, ``= 3.7`` and ``= True`` were taken as 3 and 1, ``INSTRUCTION = None`` was sent to the model as the
    text "None": each value of another type is one line naming the file and the constant; a right one is taken."""
    from games import get_game
    from pipeline.optimizer.task import task_settings

    scaffold = (EXAMPLES / "pong.py").read_text()
    right = '"Play well."' if constant == "INSTRUCTION" else "120"
    refused = 0
    for written in HOSTILE_BAND_VALUES_WRITTEN + [right]:
        info = inspect_policy(scaffold.replace('GAME = "pong"', f'GAME = "pong"\n{constant} = {written}'), "f.py")
        value = info.constants.get(constant, getattr(get_game("pong").task, constant.lower()))  # no literal: the game's
        if isinstance(value, str) if constant == "INSTRUCTION" else type(value) is int and 1 <= value < 2**31:
            assert getattr(task_settings(info, "pong"), constant.lower()) == value
            continue
        with pytest.raises(ValueError, match=f"^f.py: {constant} must be "):
            task_settings(info, "pong")
        refused += 1
    assert refused >= 9


HOSTILE_BAND_VALUES_WRITTEN = ['"5"', "None", "True", "[]", "{}", "2.5", "10 ** 400", str(10**400), "1e999", "-1e999",
                               "(1, 2)"]
"""The same values as policy-file text (``10 ** 400`` is no literal: its constant is not read, the game's is)."""

ECHO_POLICY = pong_policy("return 0") + """
    @trace.bundle()
    def echo(self, value, other=None):
        return value
"""


def _hostile_values(rng) -> object:
    """A value drawn from what a policy can return or pass that runs its own code when written: a ``__repr__``
    that raises, exits or returns no text, a key whose ``__str__`` raises, a ``__class__`` property that raises,
    a dict subclass whose ``items`` raises, list and tuple subclasses whose ``__iter__`` or ``__len__`` raise, ints
    longer than Python writes; nested among plain values, as values and as keys."""

    class ReprRaises:
        def __repr__(self):
            raise RuntimeError("no repr")

    class ReprExits:
        def __repr__(self):
            raise SystemExit(3)

    class ReprNotText:
        def __repr__(self):
            return 5

    class KeyStrRaises:
        def __str__(self):
            raise ValueError("no str")

        def __repr__(self):
            raise ValueError("no repr")

    class ClassRaises:
        @property
        def __class__(self):
            raise RuntimeError("no class")

    class ItemsRaise(dict):
        def items(self):
            raise KeyError("no items")

    class IterRaises(list):
        def __iter__(self):
            raise RuntimeError("no iter")

    class LenRaises(tuple):
        def __len__(self):
            raise OverflowError("no len")

    leaves = [lambda: ReprRaises(), lambda: ReprExits(), lambda: ReprNotText(), lambda: ClassRaises(),
              lambda: ItemsRaise(a=1), lambda: IterRaises([1, 2]), lambda: LenRaises((1, 2)), lambda: 10**5000,
              lambda: -10**4400, lambda: 7, lambda: "text", lambda: 2.5, lambda: None]
    keys = [lambda: KeyStrRaises(), lambda: 10**5000, lambda: (1, 2), lambda: 3, lambda: "k"]

    def draw(depth: int):
        kind = rng.randrange(3 if depth < 3 else 1)
        if kind == 0:
            return rng.choice(leaves)()
        if kind == 1:
            return [draw(depth + 1) for _ in range(rng.randrange(3))]
        return {rng.choice(keys)(): draw(depth + 1) for _ in range(rng.randrange(3))}

    return draw(0)


def test_recording_a_call_never_ends_what_the_same_policy_plays_untraced():
    """Writing a node's values can run the policy's own code (its classes' ``__repr__``, ``__str__``, ``__class__``,
    ``items``, ``__iter__``, ``__len__``), and Python refuses to write an int of more than 4,300 digits. Each of these
    ended a traced call, and so its episode, where the untraced call returned. Over 400 drawn values, each passed
    to a bundled method and returned by it twice (the second call looks inside the first one's output for its
    parents), recording returns what the untraced call returns, records every call, and every recorded value is
    JSON the parent accepts (``nodes._not_json``); only the call's time limit still ends it."""
    import random

    from pipeline.boundary.nodes import _not_json
    from tracing.sandbox import PolicyTimeout

    policy = load_policy(ECHO_POLICY, "echo.py").policy
    rng, recorder = random.Random(20261208), NodeRecorder(lines=True)
    for step in range(400):
        value = _hostile_values(rng)
        assert policy.echo(value) is value  # untraced: no recorder is active
        with recorder:
            recorder.begin_step(step, BALL_OBS)
            assert policy.echo(policy.echo(value), other=value) is value
    rows = recorder.table()
    assert rows.num_rows == 800
    texts = rows.column("inputs").to_pylist() + rows.column("output").to_pylist()
    assert [t for t in texts if _not_json(t) is not None] == []
    assert any("not shown: writing it raised" in t for t in texts) and any("<int of 16,610 bits>" in t for t in texts)

    class OutOfTime:
        def __repr__(self):
            raise PolicyTimeout("the call's limit")

    with NodeRecorder() as recorder, pytest.raises(PolicyTimeout):
        recorder.begin_step(0, BALL_OBS)
        policy.echo(OutOfTime())
