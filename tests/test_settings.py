"""Settings declared once (``pipeline/settings.py``): a new optimize option is one field, and what is derived from
the declarations (flags, checks, batch keys, ``--resume``'s rules, the reproduce command) is what it was before.

``tests/fixtures/settings_before.json`` was captured from main before the settings were declared once: the argparse
actions of ``codearcade optimize``, ``eval`` and ``compare`` (every flag, its dest, default, type, choices, metavar,
group and help) and what ``OptimizeConfig``'s settings derived to (``RESUME_OVERRIDES``, batch keys, defaults, ...).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import textwrap
from dataclasses import asdict, fields

import pytest

from pipeline.cli import build_parser
from pipeline.optimizer.config import BEFORE_RECORDED, BUDGET_FIELDS, RESUME_OVERRIDES, OptimizeConfig, model_defaults
from pipeline.play.config import CompareConfig, EvalConfig
from pipeline.settings import EpisodeLimits, declarations
from tests.conftest import ROOT

BEFORE = json.loads((ROOT / "tests" / "fixtures" / "settings_before.json").read_text())

REWORDED = {
    ("optimize", "--call-time-limit"): ("per policy call (default: 1)",
                                        "time limit of one policy call, 0 for none (default: 1)"),
    ("eval", "--call-time-limit"): ("time limit of one policy call (default: 1.0)",
                                    "time limit of one policy call, 0 for none (default: 1)"),
    ("optimize", "--eval-max-steps"): ("evaluation cap (default: the task's, 4000)",
                                       "evaluation cap (default: the game's, 4000; asterix 20000; enduro 5000; "
                                       "freeway 2500)"),
    ("optimize", "--model"): ('litellm model: anthropic/claude-sonnet-4-5 (ANTHROPIC_API_KEY), openai/gpt-4o (OPENAI_API_KEY), gemini/..., mistral/..., ollama_chat/NAME (a local Ollama), hosted_vllm/NAME or openai/NAME with --api-base (your own server) (default: the offline SmolLM2 server)',
                              'litellm model: anthropic/claude-sonnet-4-5 (ANTHROPIC_API_KEY), openai/gpt-4o (OPENAI_API_KEY), gemini/..., mistral/..., ollama_chat/NAME (a local Ollama), hosted_vllm/NAME or openai/NAME with --api-base (your own server) (default: the offline SmolLM2 server); give it several times for an ensemble, each as MODEL[,weight=W][,api_base=URL] (see --model-choice)'),
    ("compare", "--seed"): ("versions: the first seed (default: 0)",
                            "versions: the first seed, under the paper's protocol (default: 0; --audit draws its own)"),
    ("optimize", "--temperature"): ("LLM temperature (default: 0; not sent to models that take none)",
                                    "LLM temperature, 0 to 2 (default: 0; not sent to models that take none)"),
}
"""Help texts that changed on purpose: one flag of two verbs now has one declaration (``EpisodeLimits``);
--call-time-limit says what 0 means, now that a negative
limit is refused (2026-12-05: it forfeited every episode); --eval-max-steps names the games' own caps, read from their modules (it said 4000 for all of them); --model may be
given several times (an ensemble, issue 32); compare's --seed says --audit draws its own (issue 37: sealed);
--temperature names its range, now held to it (2026-12-05: -1 and 5 ran the loop)."""

RETYPED = {("eval", "--seed"): ("int", "non_negative_int"),
           **{(verb, "--store"): (None, "_store_path") for verb in ("optimize", "eval", "compare")}}
"""Flags whose value is checked by argparse now (2026-12-05: a negative seed reached Gymnasium's refusal mid-run
and was stored as a crashed episode; an empty --store was taken for none, and the run went to the per-user
store)."""

ADDED = {"optimize": ("--rng-key", "--audit-episodes", "--repairs", "--model-choice", "--pool"), "eval": ("--rng-key",),
         "compare": ("--audit", "--rng-key")}
"""Flags added on purpose since the snapshot (issue 33: the policies' random stream, the held-out audit, compare
on audit seeds; issue 32: repair turns, model ensembles, the proposal pool; issue 36: compare's random stream,
so that a test can pin it); every other flag is as it was."""
ADDED_FIELDS = {"rng_key": None, "audit_episodes": 3, "repairs": 1, "model_choice": "fixed", "models": None,
                "pool": False}
"""``OptimizeConfig``'s fields behind them, with their defaults (``models``, an ensemble, has no flag of its own:
``--model`` given several times sets it)."""
NO_FLAG = ("models",)


def _verb(name: str) -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _actions(parser: argparse.ArgumentParser) -> list[dict]:
    """What the fixture holds of each action (see the module docstring)."""
    groups = {id(a): g.title for g in parser._action_groups for a in g._group_actions}
    mutex = {id(a): i for i, g in enumerate(parser._mutually_exclusive_groups) for a in g._group_actions}
    return [{"flags": list(a.option_strings), "dest": a.dest, "default": a.default,
             "type": getattr(a.type, "__name__", None) if a.type else None,
             "choices": list(a.choices) if a.choices is not None else None, "const": a.const, "nargs": a.nargs,
             "metavar": a.metavar, "help": a.help, "group": groups.get(id(a)), "mutex": mutex.get(id(a))}
            for a in parser._actions if not isinstance(a, argparse._HelpAction)]


@pytest.mark.parametrize("verb", ["optimize", "eval", "compare"])
def test_the_flags_are_todays(verb):
    """Same flags in the same order, same dests (optimize's are the config's fields), defaults, types, choices,
    metavars, groups and help (but for :data:`REWORDED`)."""
    before, now = BEFORE["parsers"][verb], _actions(_verb(verb))
    added = [a for a in now if a["flags"] and a["flags"][0] in ADDED.get(verb, ())]
    assert sorted(a["flags"][0] for a in added) == sorted(ADDED.get(verb, ())) and all(a["help"] for a in added)
    now = [a for a in now if a not in added]
    assert [a["flags"] for a in now] == [a["flags"] for a in before]
    for old, new in zip(before, now):
        flag = (old["flags"] or [old["dest"]])[0]
        if verb == "eval" and old["dest"] in ("call_time_limit", "episode_time_limit"):
            old = {**old, "dest": old["dest"] + "_s"}  # eval's handler reads the config's field names now
        if (verb, flag) in RETYPED:
            assert (old["type"], new["type"]) == RETYPED[verb, flag]
            old = {**old, "type": new["type"]}
        if (verb, flag) in REWORDED:
            assert (old["help"], new["help"]) == REWORDED[verb, flag]
            old = {**old, "help": new["help"]}
        assert new == old, flag


def test_what_the_declarations_derive_is_todays():
    """--resume's rules, budgets, the values that replay old runs, batch keys and run-key rules, defaults."""
    from pipeline.cli.optimize import OPTIMIZE_OPTIONS
    from pipeline.jobs.experiments import KEYED_WHEN_SET, NOT_IN_KEY, RUN_KEYS

    before = BEFORE["optimize"]

    def old(names) -> list[str]:  # what was there before the fields added since (ADDED_FIELDS)
        return [n for n in names if n not in ADDED_FIELDS]

    # an audit may change; so may an ensemble's models, as --model may
    assert sorted(RESUME_OVERRIDES) == sorted(before["resume"] + ["audit_episodes", "models"])
    assert list(BUDGET_FIELDS) == before["budgets"]
    assert BEFORE_RECORDED == {**before["before"], "repairs": 0}  # runs before repairs made none
    assert old(RUN_KEYS) == before["run_keys"] and sorted(OPTIMIZE_OPTIONS) == sorted(
        before["options"] + [f for f in ADDED_FIELDS if f not in NO_FLAG])
    assert sorted(NOT_IN_KEY) == sorted(before["not_in_key"] + ["audit_episodes"])  # it measures, changes nothing
    assert sorted(KEYED_WHEN_SET) == sorted(before["keyed_when_set"] + ["rng_key", "repairs", "model_choice", "models",
                                                                        "pool"])
    defaults = asdict(OptimizeConfig())
    assert {k: defaults.pop(k) for k in ADDED_FIELDS} == ADDED_FIELDS
    assert defaults.pop("observation") >= before["defaults"].pop("observation")  # moves with the conventions
    assert defaults == before["defaults"]  # the stored runs.config keeps its keys, in order, and its defaults
    assert old(asdict(OptimizeConfig())) == list(BEFORE["optimize"]["run_keys"])


@pytest.mark.parametrize("config", [OptimizeConfig, EvalConfig, CompareConfig, EpisodeLimits])
def test_every_setting_is_declared_with_its_help(config):
    declared = declarations(config)
    undeclared = [f.name for f in fields(config) if f.name not in declared]
    assert not undeclared, f"{config.__name__}: fields without a setting(): {undeclared}"
    for name, (_, setting) in declared.items():
        assert setting.help.strip() and setting.help == setting.help.strip(), name
        assert all(s.help.strip() for s in setting.switches), name


def test_episode_limits_are_one_declaration():
    """eval, optimize, compare, the candidate checks and the episode specs all take their limits' defaults from
    EpisodeLimits: change one there and every one of them follows."""
    from pipeline.boundary.confine import Limits
    from pipeline.play.spec import EpisodeSpec
    from pipeline.play.validate import RuntimeCheck

    limits = EpisodeLimits()
    spec = EpisodeSpec("e", "r", "pong", "", "v")
    for config in (EvalConfig(), OptimizeConfig(), CompareConfig(), spec, RuntimeCheck("", "pong", [])):
        assert EpisodeLimits.of(config) == limits, type(config).__name__
    assert Limits().memory_mb == limits.memory_limit_mb
    assert EpisodeLimits.of(EvalConfig(max_steps=7, call_time_limit_s=0.5)) == EpisodeLimits(7, 0.5)


def test_model_defaults_fill_only_what_is_not_given():
    assert model_defaults({"game": "pong"}) == {"game": "pong", "max_tokens": 512, "token_budget": 3000}
    assert model_defaults({"max_tokens": 64})["max_tokens"] == 64
    assert model_defaults({"model": "openai/x", "game": "pong"}) == {"model": "openai/x", "game": "pong"}


@pytest.mark.slow
def test_the_cli_and_a_batch_entry_record_the_same_config(tmp_path):
    """The same settings, once on the command line and once in a batch file, with the offline model (whose
    defaults the two used to apply differently: 512-token replies against 4,096): the same runs.config, but for
    the batch's own keys and the worker count (each machine's own)."""
    from store import Store

    exe = os.path.join(os.path.dirname(sys.executable), "codearcade")
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "LITELLM_LOCAL_MODEL_COST_MAP": "True"}
    store = tmp_path / "s.duckdb"
    settings = {"game": "pong", "iterations": 0, "rollout_steps": 20, "eval_max_steps": 40, "seed": 3}
    flags = ["--game", "pong", "--iterations", "0", "--rollout-steps", "20", "--eval-max-steps", "40", "--seed", "3"]
    cli = subprocess.run([exe, "optimize", *flags, "--store", str(store)], capture_output=True, text=True, env=env,
                         timeout=600)
    assert cli.returncode == 0, cli.stdout + cli.stderr
    experiments = tmp_path / "same.toml"
    experiments.write_text('name = "same"\n[[run]]\n' + "".join(f"{k} = {json.dumps(v)}\n" for k, v in settings.items()))
    batch = subprocess.run([exe, "batch", str(experiments), "--store", str(store)], capture_output=True, text=True,
                           env=env, timeout=600)
    assert batch.returncode == 0, batch.stdout + batch.stderr
    rows = Store(store).query("SELECT config FROM runs WHERE kind = 'optimize' ORDER BY created_at")
    assert len(rows) == 2
    by_cli, by_batch = (json.loads(config) for (config,) in rows)
    assert by_batch.pop("batch") == "same" and by_batch.pop("batch_key")
    by_cli.pop("workers"), by_batch.pop("workers")
    assert by_cli.pop("rng_key") != by_batch.pop("rng_key"), "each run's policies draw from a stream of its own"
    assert by_cli == by_batch
    assert by_cli["max_tokens"] == 512 and by_cli["token_budget"] == 3000


NEW_OPTION = '''
    patience: int = setting(
        3, "stop after N iterations without a better score (default: %(default)s)", metavar="N", minimum=1,
        resumable=True, group="search")
'''
"""The option the next test adds: one field, written once, in pipeline/optimizer/config.py."""


def test_a_new_optimize_option_is_written_in_one_place(tmp_path):
    """Add one field to OptimizeConfig (in a copy of the pipeline package) and nothing else: it is a flag of
    ``codearcade optimize`` with its help and type, a key of a batch file, checked in both, taken by --resume, kept
    in the stored config and in the command that reproduces a run."""
    copy = tmp_path / "pipeline"
    shutil.copytree(ROOT / "pipeline", copy, ignore=shutil.ignore_patterns("__pycache__"))
    config = copy / "optimizer" / "config.py"
    source = config.read_text()
    anchor = "\n    @classmethod\n    def from_record("
    assert source.count(anchor) == 1
    config.write_text(source.replace(anchor, NEW_OPTION + anchor))

    experiments = tmp_path / "patient.toml"
    experiments.write_text('name = "patient"\n[defaults]\ngame = "pong"\nmodel = "openai/x"\n[matrix]\npatience = [2, 5]\n')
    wrong = tmp_path / "impatient.toml"
    wrong.write_text('name = "impatient"\n[[run]]\ngame = "pong"\npatience = 0\n')
    probe = textwrap.dedent(f"""
        import contextlib, io, json
        from pipeline.cli import build_parser
        from pipeline.cli.optimize import OPTIMIZE_OPTIONS
        from pipeline.cli.report import reproduce_command
        from pipeline.jobs.experiments import ExperimentError, RUN_KEYS, load_experiments
        from pipeline.optimizer.config import RESUME_OVERRIDES, OptimizeConfig, validate_config

        out = {{}}
        help = io.StringIO()
        with contextlib.redirect_stdout(help), contextlib.suppress(SystemExit):
            build_parser().parse_args(["optimize", "--help"])
        out["help"] = " ".join(help.getvalue().split())
        out["parsed"] = build_parser().parse_args(["optimize", "--game", "pong", "--patience", "4"]).patience
        bad = io.StringIO()
        with contextlib.redirect_stderr(bad), contextlib.suppress(SystemExit):
            build_parser().parse_args(["optimize", "--patience", "0"])
        out["bad_flag"] = bad.getvalue().strip().splitlines()[-1]
        out["options"], out["resume"], out["keys"] = list(OPTIMIZE_OPTIONS), list(RESUME_OVERRIDES), list(RUN_KEYS)
        out["batch"] = [run.config.patience for run in load_experiments({str(experiments)!r}).runs]
        try:
            load_experiments({str(wrong)!r})
        except ExperimentError as exc:
            out["batch_error"] = str(exc)
        try:
            validate_config(OptimizeConfig(patience=0))
        except ValueError as exc:
            out["check"] = str(exc)
        out["default"] = OptimizeConfig().patience
        out["reproduce"] = reproduce_command({{"kind": "optimize", "game": "pong"}}, {{"patience": 7, "seed": 1}})
        print(json.dumps(out))
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)]),
           "LITELLM_LOCAL_MODEL_COST_MAP": "True"}
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert "search: how versions are chosen" in out["help"]
    assert "--patience N stop after N iterations without a better score (default: 3)" in out["help"]
    assert out["parsed"] == 4 and "--patience: must be at least 1, got 0" in out["bad_flag"]
    assert "patience" in out["options"] and "patience" in out["resume"] and "patience" in out["keys"]
    assert out["batch"] == [2, 5]
    assert out["batch_error"].endswith("--patience must be at least 1, got 0") and "\n" not in out["batch_error"]
    assert out["check"] == "--patience must be at least 1, got 0"
    assert out["default"] == 3
    assert out["reproduce"] == "codearcade optimize --game pong --seed 1 --patience 7"


def test_the_reply_length_default_is_written_once():
    """--max-tokens's default is the client's (a client made without one asks for what a run asks for), and the
    help of --max-tokens and --token-budget names the offline model's own defaults as model_defaults applies them."""
    import inspect

    from pipeline.llm.client import LiteLLMClient

    assert inspect.signature(LiteLLMClient).parameters["max_tokens"].default == OptimizeConfig().max_tokens
    offline = model_defaults({})
    declared = declarations(OptimizeConfig)
    assert f"{offline['max_tokens']} with the offline model" in declared["max_tokens"][1].help
    assert f"{offline['token_budget']} with the offline model" in declared["token_budget"][1].help


CONFIG_MODULES = ("pipeline.settings", "pipeline.optimizer.config", "pipeline.play.config", "pipeline.serve.config")
"""Where the config classes are declared (a class of these modules with declared settings is walked)."""

BUDGETS_NO_LIMIT = "a budget: a huge one is no limit, and works (--max-total-tokens 10**20, --max-wall 1.8e308 ran)"

TAKES_ANY_VALUE = {
    ("OptimizeConfig", "memory"): "only the run's own earlier iterations can be shown (2**62 ran as 5 does)",
    ("OptimizeConfig", "token_budget"): "the prompt is built to fit it, held to the model's context by fit_to_model "
                                        "(2**62 ran)",
    ("OptimizeConfig", "workers"): "no more workers start than there are episodes to play (2**62 ran)",
    ("OptimizeConfig", "beam_width"): "only the versions the run has are kept (2**62 ran)",
    ("OptimizeConfig", "max_concurrent_calls"): "no more calls are in flight than an iteration's proposals, each "
                                                "bounded (2**62 ran)",
    ("OptimizeConfig", "screen_margin"): "only compared with scores (1.8e308 ran)",
    ("OptimizeConfig", "seed"): "validate_config holds the tuning seeds below the audit seeds",
    ("OptimizeConfig", "max_cost_usd"): BUDGETS_NO_LIMIT,
    ("OptimizeConfig", "max_total_tokens"): BUDGETS_NO_LIMIT,
    ("OptimizeConfig", "max_llm_calls"): BUDGETS_NO_LIMIT,
    ("OptimizeConfig", "max_wall_minutes"): BUDGETS_NO_LIMIT,
    ("OptimizeConfig", "observation"): "games.base Game.observing refuses a version this codearcade does not build, "
                                       "saying to upgrade",
    ("EvalConfig", "observation"): "games.base Game.observing refuses a version this codearcade does not build",
    ("EvalConfig", "workers"): "no more workers start than there are episodes to play (2**62 ran)",
    ("CompareConfig", "workers"): "no more workers start than there are episodes to play (2**62 ran)",
    ("ServeConfig", "workers"): "a submission's games start at most as many workers as it has games (2**62 ran a "
                                "submission and the finalize)",
    ("CompareConfig", "seed"): "each side plays it as eval does, in EvalConfig's range (compare --seed -1 and 2**64 "
                               "were refused, 2**62 ran)",
    ("CompareConfig", "context"): "the steps shown are those the episodes have (pipeline/play/versus.py)",
}
"""The numeric settings without a maximum, each proven to take any value, with why: each ran at 2**62 (floats at
1.8e308) as a flag, and the optimize settings all at once as a batch file's keys, resumed with its recorded settings."""


def _config_classes() -> list[type]:
    import importlib
    from dataclasses import is_dataclass

    found = []
    for module in map(importlib.import_module, CONFIG_MODULES):
        found += [c for c in vars(module).values() if isinstance(c, type) and is_dataclass(c)
                  and c.__module__ == module.__name__ and declarations(c)]
    return found


def test_every_numeric_setting_has_a_maximum_or_is_proven_to_take_any_value():
    """A setting of a count, a size or a time without a maximum was taken at any size (2**62, 1.8e308) and hung,
    filled the memory, or ended in a traceback when it reached a timer or the store (``--max-tokens``,
    ``--rollout-steps``, ``--eval-max-steps``, ``--screen-steps``, ``--candidates``, ``--call-time-limit``,
    ``--episode-time-limit``, ``compare --context``): a new numeric setting needs a maximum in its declaration, or
    a line in TAKES_ANY_VALUE that says why it takes any value."""
    from pipeline.settings import value_type

    classes = _config_classes()
    assert {c.__name__ for c in classes} >= {"OptimizeConfig", "EvalConfig", "CompareConfig", "ServeConfig",
                                             "EpisodeLimits"}
    walked, missing = set(), []
    for config in classes:
        for name, (_, declared) in declarations(config).items():
            kind = value_type(config, name)
            if kind not in (int, float):
                continue
            walked.add((config.__name__, name))
            if declared.maximum is None and (config.__name__, name) not in TAKES_ANY_VALUE:
                missing.append(f"{config.__name__}.{name}")
    assert not missing, f"numeric settings without a maximum, not proven to take any value: {missing}"
    assert set(TAKES_ANY_VALUE) <= walked, "TAKES_ANY_VALUE names no setting"
    assert not [key for key in TAKES_ANY_VALUE if declarations(next(c for c in classes if c.__name__ == key[0]))
                [key[1]][1].maximum is not None], "a setting with a maximum is listed as taking any value"


HUGE, LARGEST_FLOAT = str(2**62), "1.7976931348623157e308"


@pytest.mark.parametrize("argv", [
    ["optimize", "p.py", "--max-tokens", HUGE], ["optimize", "p.py", "--rollout-steps", HUGE],
    ["optimize", "p.py", "--eval-max-steps", HUGE], ["optimize", "p.py", "--screen-steps", HUGE],
    ["optimize", "p.py", "--candidates", HUGE], ["optimize", "p.py", "--call-time-limit", HUGE],
    ["optimize", "p.py", "--call-time-limit", LARGEST_FLOAT], ["eval", "p.py", "--call-time-limit", "1e308"],
    ["eval", "p.py", "--episode-time-limit", HUGE], ["eval", "p.py", "--episode-time-limit", LARGEST_FLOAT],
    ["serve", "--call-time-limit", HUGE]] + [argv + [HUGE] for argv in (
        ["eval", "p.py", "--episodes"], ["eval", "p.py", "--noop-max"], ["compare", "a.py", "b.py", "--episodes"],
        ["optimize", "p.py", "--eval-episodes"], ["optimize", "p.py", "--robust-episodes"],
        ["optimize", "p.py", "--audit-episodes"], ["serve", "--budget"], ["serve", "--per-submission"],
        ["serve", "--validation-episodes"], ["serve", "--heldout-episodes"])])
def test_a_huge_size_count_or_time_is_refused_before_anything_plays(argv, capsys):
    """Each of these was taken at 2**62: ``--max-tokens`` ended the run in a DuckDB conversion error when its first
    call was stored; the step caps played a whole game and ended in one when the episode was stored; best-of-n's
    ``--candidates`` planned proposals without end; a time limit crashed every episode at step 0
    (``OverflowError``), a forfeit each, at 2**62, 1e308 and the largest float alike; ``eval --noop-max`` was taken
    and its episode never ended; a served run's validation and held-out counts, optimize's robust and audit games
    had no bound (a served run recorded with 10**9 validation games would have its finalize draw 10**9 seeds)."""
    with pytest.raises(SystemExit) as exited:
        build_parser().parse_args(argv)
    err = capsys.readouterr().err
    assert exited.value.code == 2 and ("must be within [" in err or "must be at most" in err), err


def test_a_huge_size_is_refused_as_a_batch_key_and_as_a_recorded_setting(tmp_path):
    """The same declaration checks a batch file's keys and a stored run's recorded settings."""
    from pipeline.jobs.experiments import ExperimentError, load_experiments
    from pipeline.settings import flag_of
    path = tmp_path / "huge.toml"
    for key in ("max_tokens", "rollout_steps", "eval_max_steps", "screen_steps", "candidates", "call_time_limit_s",
                "episode_time_limit_s"):
        path.write_text(f"[defaults]\ngame = 'pong'\nstrategy = 'best-of-n'\n{key} = {2**62}\n[[run]]\nseed = 1\n")
        with pytest.raises(ExperimentError, match=f"{flag_of(OptimizeConfig, key)} must be (within|at most)"):
            load_experiments(path)
        with pytest.raises(ValueError, match=f"cannot be read: {key} must be (within|at most)"):
            OptimizeConfig.from_record({key: 2**62}, "01RUN")


def test_a_compare_context_past_the_episodes_shows_their_steps(monkeypatch):
    """``compare A B --context 4611686018427387904`` was taken, and the steps listed around the first divergent
    step grew without end (8.3 GB at 60 s): the steps shown are those the episodes have."""
    from pipeline.play import versus

    rows = {"a": {"episode_id": "a", "seed": 0, "return": 0.0, "length": 10, "end_reason": "truncated"},
            "b": {"episode_id": "b", "seed": 0, "return": 0.0, "length": 12, "end_reason": "truncated"}}
    monkeypatch.setattr(versus, "episode_rows", lambda con, ids: rows)
    monkeypatch.setattr(versus, "first_divergent_step", lambda con, a, b: 4)
    monkeypatch.setattr(versus, "episode_steps", lambda con, episode_id, start, stop, *rest: [
        {"step": s, "action": 0, "reward": 0.0, "score": 0.0, "obs": {}}
        for s in range(start, min(stop, rows[episode_id]["length"]))])
    monkeypatch.setattr(versus, "step_outputs", lambda con, episode_id, start, stop: [])
    found = versus._divergence(None, "pong", rows["a"], rows["b"], 10**6)
    assert [e["step"] for e in found["around"]][:1] == [0] and len(found["around"]) <= 13
    assert found["around"][11]["A"] is None and found["around"][11]["B"]["action"] == 0
    assert versus._divergence(None, "pong", rows["a"], rows["b"], 1)["around"][0]["step"] == 3


def test_an_episode_plays_at_the_longest_time_limits(tmp_path, capsys):
    """The maxima of the time limits are limits the episodes play under: 30 days had crashed every episode at step
    0 (``OverflowError: timeout is too large``: the policy channel's ``poll()`` takes milliseconds as a C int)."""
    from pipeline.cli import main
    from pipeline.settings import MAX_TIME_LIMIT_S

    code = main(["eval", str(ROOT / "games" / "scaffolds" / "pong.py"), "--max-steps", "20", "--json",
                 "--call-time-limit", str(MAX_TIME_LIMIT_S), "--episode-time-limit", str(MAX_TIME_LIMIT_S),
                 "--store", str(tmp_path / "s.duckdb")])
    out = capsys.readouterr().out
    played = json.loads(out[out.index("{"):])
    assert code == 0 and not played["forfeits"] and played["episodes"][0]["length"] == 20, out
