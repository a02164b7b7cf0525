"""The experiment file of ``codearcade batch``: read and checked into a :class:`Batch` of runs, each with its key
and its label (running them is ``pipeline/jobs/batch.py``).

An experiment file declares defaults, a matrix (every combination becomes a run) and/or explicit runs::

    name = "ablation"                 # identifies the batch in the store
    store = "ablation.duckdb"         # optional, relative to the working directory; --store wins
    [defaults]
    iterations = 20
    model = "anthropic/claude-sonnet-4-5"
    [matrix]
    game = ["pong"]
    feedback = ["staged", "rollout"]
    seed = [0, 1, 2]
    [[run]]                           # optional extra runs, merged over the defaults
    game = "breakout"
    name = "breakout-extra"           # optional: the run's label (default: "{batch}:{entry}")

Keys are the fields of :class:`~pipeline.optimizer.config.OptimizeConfig` (``game``, ``policy``, ``model``,
``api_base``, ``iterations``, ``memory``, ``token_budget``, ``eval_episodes``, ``feedback``, ``seed``, ...).
Each run has a stable key (a hash of the batch name and its settings) stored in its config, so running the
same command again skips finished runs, resumes interrupted ones from the store, and starts the rest.

Each run is labelled in the store (``runs.name``, what every verb takes in place of its id): a ``[[run]]`` table's
``name``, else ``{batch}:{entry}``, the entry being the game (or the policy file's stem) and the matrix's settings
of the run, joined by commas (``pong-ablation:pong,feedback=rollout,seed=0``); entries that would share a label
get ``#2``, ``#3``, ... after it, in the file's order, and a label that cannot be a run name (over 64 characters,
or a batch name that does not start with a letter) is left out.
"""

from __future__ import annotations

import difflib
import hashlib
import itertools
import json
import os
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping

from games import get_game
from games.base import one_life_setting
from pipeline.optimizer.config import OptimizeConfig, model_defaults, validate_config
from pipeline.optimizer.ensemble import split_model_flags
from pipeline.settings import declarations
from store.runs import check_run_name

TOP_LEVEL_KEYS = ("name", "store", "defaults", "matrix", "run")
RUN_KEYS = tuple(declarations(OptimizeConfig))
"""The settings a batch file may give: every declared setting of :class:`OptimizeConfig`, by its field name."""
ENTRY_KEYS = ("name",)
"""Keys of a ``[[run]]`` table beside :data:`RUN_KEYS`: its label, which is no setting (nor part of the run's key)."""
NOT_IN_KEY = tuple(n for n, (_, s) in declarations(OptimizeConfig).items() if s.run_key == "never" or s.budget)
"""Settings that do not change a run's results (or only how far it goes), so they do not change its identity:
rerunning a batch with a larger budget resumes its runs (each setting's ``run_key``)."""
KEYED_WHEN_SET = tuple(n for n, (_, s) in declarations(OptimizeConfig).items()
                       if s.run_key == "if_set" and not s.budget)
"""Settings added after run keys were introduced: they count in a key only away from their default, so the
runs of an existing experiment file keep their keys (and are skipped or resumed, not run again)."""


class ExperimentError(ValueError):
    """An experiment file that cannot be used; one line that says where and why."""


@dataclass
class BatchRun:
    key: str
    label: str
    """How the batch's log and display name the run (its game and matrix settings)."""
    config: OptimizeConfig
    name: str | None = None
    """Its label in the store (``runs.name``): the entry's ``name``, else ``{batch}:{entry}`` (module docstring)."""
    legacy_key: str | None = None
    """The key a run of a policy file in the batch's folder had before keys took its path from there (its
    absolute path): such a run is found by it too, and keeps it."""

    def found_as(self, stored: Mapping[str, Any]) -> str:
        """The key this run has among ``stored`` (keyed by batch key): its key, else its legacy key if that is
        there."""
        return self.key if self.key in stored or self.legacy_key is None else self.legacy_key


@dataclass
class Batch:
    name: str
    path: Path
    store: str | None
    runs: list[BatchRun]


def _suggest(key: str, known: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(key, known, n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _check_settings(settings: dict[str, Any], where: str) -> None:
    for key, value in settings.items():
        if key not in RUN_KEYS:
            raise ExperimentError(f"{where}: unknown setting '{key}'{_suggest(key, RUN_KEYS)}; "
                                  f"known: {', '.join(RUN_KEYS)}")
        if not _plain_value(value):  # a TOML date or time: no setting takes one
            raise ExperimentError(f"{where}: {key} = {value!r}: give a number, a string, true/false, or a list or "
                                  "table of them")
    if "game" in settings and settings["game"] is not None:
        try:
            get_game(str(settings["game"]))
        except ValueError as exc:
            raise ExperimentError(f"{where}: {exc}") from None


def _plain_value(value: Any) -> bool:
    """Whether ``value`` is what a setting can take from TOML: a number, string, boolean, or a list or table of
    them (an ensemble's ``models``), never a date or a time."""
    if isinstance(value, list):
        return all(_plain_value(v) for v in value)
    if isinstance(value, dict):
        return all(_plain_value(v) for v in value.values())
    return isinstance(value, (str, int, float, bool))


def _run_key(name: str, config: OptimizeConfig, folder: Path | None = None) -> str:
    """The run's key in the batch ``name``: a hash of its identifying settings. A policy file inside ``folder``
    (the batch file's) counts by its path from there, so that a batch folder that is moved or copied whole keeps
    its runs; ``folder`` None: by its absolute path, as keys were made before 2026-12-06 (:attr:`BatchRun.
    legacy_key`)."""
    defaults = OptimizeConfig()
    identity = {k: v for k, v in asdict(config).items()
                if k not in NOT_IN_KEY and not (k in KEYED_WHEN_SET and v == getattr(defaults, k))}
    if folder is not None and identity.get("policy") and Path(identity["policy"]).is_relative_to(folder):
        identity["policy"] = Path(identity["policy"]).relative_to(folder).as_posix()
    text = json.dumps({"batch": name, "config": identity}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _label_parts(settings: dict[str, Any], varying: list[str]) -> list[str]:
    parts = [str(settings.get("game") or Path(settings.get("policy") or "?").stem)]
    return parts + [f"{k}={settings[k]}" for k in varying if k != "game" and k in settings]


def _label(settings: dict[str, Any], varying: list[str]) -> str:
    return " ".join(_label_parts(settings, varying))


def _run_names(batch: str, runs: list[tuple[dict[str, Any], str | None]], varying: list[str]) -> list[str | None]:
    """Each run's label in the store: its entry's ``name``, else ``{batch}:{entry}`` (``#k`` after labels that
    several entries would share; None where the label cannot be a run name)."""
    defaults = [f"{batch}:{','.join(_label_parts(settings, varying))}" for settings, _ in runs]
    seen: dict[str, int] = {}
    names: list[str | None] = []
    for (_, given), default in zip(runs, defaults):
        if given is not None:
            names.append(given)
            continue
        seen[default] = seen.get(default, 0) + 1
        label = default if defaults.count(default) == 1 else f"{default}#{seen[default]}"
        try:
            names.append(check_run_name(label))
        except ValueError:
            names.append(None)
    return names


def load_experiments(path: str | os.PathLike) -> Batch:
    """Read and expand an experiment file; :class:`ExperimentError` for anything wrong with it."""
    path = Path(path)
    if not path.exists():
        raise ExperimentError(f"experiment file '{path}' does not exist")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ExperimentError(f"{path.name}: not valid TOML: {exc}") from None
    for key in data:
        if key not in TOP_LEVEL_KEYS:
            raise ExperimentError(f"{path.name}: unknown key '{key}'{_suggest(key, TOP_LEVEL_KEYS)}; "
                                  f"known: {', '.join(TOP_LEVEL_KEYS)}")
    name = str(data.get("name") or path.stem)
    if "/" in name or name.startswith(".") or not name.isprintable():  # it names the batch's log file
        raise ExperimentError(f"{path.name}: name {name!r}: a batch's name names its log file beside the store, so "
                              "no '/', no leading '.' and no control characters")
    for table in ("defaults", "matrix"):
        if not isinstance(data.get(table, {}), dict):
            raise ExperimentError(f"{path.name}: '{table}' must be a table: [{table}] with a setting per line")
    defaults = dict(data.get("defaults", {}))
    _check_settings(defaults, f"{path.name} [defaults]")
    matrix = {k: (v if isinstance(v, list) else [v]) for k, v in dict(data.get("matrix", {})).items()}
    _check_settings({k: v[0] for k, v in matrix.items() if v}, f"{path.name} [matrix]")
    for key, values in matrix.items():
        for value in values:
            _check_settings({key: value}, f"{path.name} [matrix] {key}")
    explicit = data.get("run", [])
    if not isinstance(explicit, list):
        raise ExperimentError(f"{path.name}: 'run' must be an array of tables: [[run]]")

    points: list[dict[str, Any]] = []
    if matrix:
        keys = list(matrix)
        for combo in itertools.product(*(matrix[k] for k in keys)):
            points.append({**defaults, **dict(zip(keys, combo))})
    given_names: list[str | None] = [None] * len(points)
    named: dict[str, int] = {}  # each [[run]] name given: its entry's number
    for i, entry in enumerate(explicit):
        if not isinstance(entry, dict):
            raise ExperimentError(f"{path.name}: 'run' must be an array of tables: [[run]]")
        entry = dict(entry)
        label = entry.pop("name", None)
        if label is not None:
            try:
                check_run_name(str(label))
            except ValueError as exc:
                raise ExperimentError(f"{path.name} [[run]] #{i + 1}: name: {exc}") from None
            if str(label) in named:  # two runs under one name: every command would find it ambiguous
                raise ExperimentError(f"{path.name} [[run]] #{i + 1}: name {str(label)!r} is the name of [[run]] "
                                      f"#{named[str(label)]} too; give each its own")
            named[str(label)] = i + 1
        _check_settings(entry, f"{path.name} [[run]] #{i + 1}")
        points.append({**defaults, **entry})
        given_names.append(None if label is None else str(label))
    if not points:
        raise ExperimentError(f"{path.name}: no runs: add a [matrix] or [[run]] tables")

    kept: list[tuple[dict[str, Any], str | None]] = []
    runs: list[BatchRun] = []
    seen: dict[str, str] = {}  # each run's key: the entry that has it
    problems: dict[str, str | None] = {}  # each policy file checked once
    for settings, given in zip(points, given_names):
        if settings.get("policy"):
            policy = Path(settings["policy"])
            settings["policy"] = str(policy if policy.is_absolute() else (path.parent / policy).resolve())
            if not Path(settings["policy"]).is_file():  # said now, not when its run starts (and fails to resume)
                raise ExperimentError(f"{path.name}: policy file {settings['policy']} does not exist (a relative "
                                      "path is read from the batch file's folder)")
            if settings["policy"] not in problems:
                problems[settings["policy"]] = _policy_problem(settings["policy"])
            problem = problems[settings["policy"]]
            if problem is not None:  # as optimize checks it before its run starts (which no resume would mend)
                raise ExperimentError(f"{path.name}: {problem}")
        if not settings.get("game") and not settings.get("policy"):
            raise ExperimentError(f"{path.name}: every run needs a game or a policy (add game = ... to [defaults])")
        if settings.get("game") and settings.get("one_life"):  # a policy file's own GAME: checked as its run starts
            try:
                get_game(str(settings["game"])).check_one_life(one_life_setting(settings["one_life"]))
            except ValueError as exc:
                raise ExperimentError(f"{path.name}: {_label(settings, list(matrix))}: {exc}") from None
        try:
            # the key is the entry's settings', before the model's defaults (a function of them): an experiment
            # file keeps its keys
            settings = split_model_flags(settings)  # an ensemble: models = [...] (pipeline/optimizer/ensemble.py)
            key = _run_key(name, OptimizeConfig(**settings), path.parent.resolve())
            legacy_key = _run_key(name, OptimizeConfig(**settings))
            config = OptimizeConfig(**model_defaults(settings))
            validate_config(config)
        except ValueError as exc:
            raise ExperimentError(f"{path.name}: {_label(settings, list(matrix))}: {exc}") from None
        if key in seen:  # one run would stand for both: the second was dropped without a word
            raise ExperimentError(f"{path.name}: {_label(settings, list(matrix))}"
                                  f"{f' ({given!r})' if given else ''} has the same settings as "
                                  f"{seen[key]}: give it a setting of its own, or leave it out")
        seen[key] = _label(settings, list(matrix)) + (f" ({given!r})" if given else "")
        runs.append(BatchRun(key, _label(settings, list(matrix)), config,
                             legacy_key=legacy_key if legacy_key != key else None))
        kept.append((settings, given))
    labels = _run_names(name, kept, list(matrix))
    for given, label in zip((g for _, g in kept), labels):
        if given is not None and labels.count(label) > 1:  # a [[run]] name that a matrix entry's label has too
            raise ExperimentError(f"{path.name}: name {given!r} is a matrix entry's label too: give the [[run]] "
                                  "another name")
    for run, label in zip(runs, labels):
        run.name = label
    return Batch(name, path, data.get("store"), runs)


def _policy_problem(policy: str) -> str | None:
    """Why the policy file at ``policy`` cannot start a run (it does not parse, has no Policy class or no
    trainable method: ``resolve_start``'s checks, in a confined worker), or None."""
    from pipeline.optimizer.task import resolve_start
    from tracing.policy_file import PolicyLoadError

    try:
        resolve_start(OptimizeConfig(policy=policy))
    except (PolicyLoadError, ValueError) as exc:
        return str(exc).splitlines()[0]
    return None
