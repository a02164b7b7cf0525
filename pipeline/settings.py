"""Settings declared once: a typed dataclass field carries its default and, in :class:`Setting`, everything the
rest of the code needs to know about it.

A config class (``OptimizeConfig``, ``EvalConfig``, ...) declares each setting with :func:`setting`: its default,
its help text, its checks (a range, choices, or a function), its flag (derived from the field's name unless
declared), and how runs treat it (``--resume`` may change it; a budget; what it does to a batch run's key).
From these declarations come the command line's flags (``pipeline/cli/common.py: add_settings``), the checks
(:func:`check_settings`, one line naming the flag), the keys of a batch file, the settings ``--resume`` takes, and
the flags of the command that reproduces a run. Adding a setting is writing one field.

:class:`EpisodeLimits` holds the limits every episode is played under (steps, time per call and per episode,
memory), with their defaults, written here once; the configs of ``eval``, ``optimize``, ``compare``, the
candidate checks and the episode specs declare their limit fields with :func:`limit`, a copy of these.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import reprlib
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable, Literal

UNSET = object()
"""An attribute of a :class:`Setting` left undeclared (``before_recorded``, ``flag_default``)."""


@dataclass(frozen=True)
class Switch:
    """A flag that takes no value and sets the setting to ``value`` (``--no-rollback``: False)."""

    flag: str
    value: Any
    help: str


@dataclass(frozen=True)
class Setting:
    """What a config field is, beside its type and default (see the module docstring)."""

    help: str
    """The flag's help text (``--help``; ``%(default)s`` stands for the default); the field's docstring, where there
    is one, tells readers of the code more."""
    flag_default: Any = UNSET
    """The flag's default where the command line works out the value itself (``None``: the handler decides, as
    eval's ``--workers`` from the episodes and the cores); else the field's default."""
    flag: str | None = None
    """The flag; None: ``--`` and the field's name with dashes (``eval_episodes``: ``--eval-episodes``)."""
    cli: bool = True
    """False: no flag (a batch key only, or a setting recorded for replays)."""
    positional: bool = False
    """The verb's positional argument (optional: ``nargs='?'``) instead of a flag."""
    metavar: str | None = None
    switches: tuple[Switch, ...] = ()
    """Flags without a value in place of the valued flag; several are mutually exclusive. A bool setting without
    any gets one: ``--no-NAME`` (to False) when its default is True, ``--NAME`` (to True) when it is False."""
    minimum: float | None = None
    maximum: float | None = None
    above: float | None = None
    """Exclusive lower bound (a budget must be above 0)."""
    choices: tuple[Any, ...] | None = None
    check: Callable[[Any], Any] | None = None
    """A further check of the value: raises ValueError with one line."""
    group: str | None = None
    """The flag's group in ``--help`` (budgets are in ``budgets``); None: the verb's own options."""
    resumable: bool = False
    """``--resume`` may change it (a budget always may)."""
    budget: bool = False
    """A limit of how far a run goes, not of what it does (``BUDGET_FIELDS``)."""
    run_key: Literal["always", "if_set", "never"] = "if_set"
    """What the setting does to a batch run's key: ``always`` part of it; ``if_set`` only away from its default (a
    setting added after run keys existed: the runs of an existing experiment file keep their keys); ``never``
    (how fast or how far a run goes, not what it does: rerunning a batch with a larger budget resumes its runs)."""
    before_recorded: Any = UNSET
    """The value that reproduces what a run stored before the setting existed did (``OptimizeConfig.from_record``),
    when that is not the default."""
    repeat: bool = False
    """The flag may be given several times; the handler gets the list of values (``--model`` for an ensemble)."""
    reproduce: bool = True
    """False: left out of the command line that reproduces a run (the machine's own, like worker counts)."""

    def flags(self, name: str) -> tuple[str, ...]:
        """The flags that set it on the command line (none without one)."""
        if not self.cli or self.positional:
            return ()
        return tuple(s.flag for s in self.switches) or (self.flag or "--" + name.replace("_", "-"),)

    def label(self, name: str) -> str:
        """How an error names it: its flag (the first of its switches), else its name (a batch key)."""
        return (self.flags(name) or (name,))[0]


def setting(default: Any, help: str, **declared: Any) -> Any:
    """A config field with its default and its :class:`Setting` (``help`` and any other attribute of it)."""
    return dataclasses.field(default=default, metadata={"setting": Setting(help=help, **declared)})


def declarations(cls: type) -> dict[str, tuple[dataclasses.Field, Setting]]:
    """Each declared field of a config class (or instance) and its setting, in the class's order, with the
    switches of bool settings filled in."""
    hints = _hints(cls if isinstance(cls, type) else type(cls))
    found = {}
    for f in dataclasses.fields(cls):
        declared = f.metadata.get("setting")
        if declared is None:
            continue
        if declared.cli and not declared.switches and not declared.positional and _base(hints[f.name]) is bool:
            stem = f.name.replace("_", "-")
            switch = Switch(f"--no-{stem}", False, declared.help) if f.default else Switch(f"--{stem}", True, declared.help)
            declared = dataclasses.replace(declared, switches=(switch,))
        found[f.name] = (f, declared)
    return found


def value_type(cls: type, name: str) -> type | tuple[type, ...]:
    """The type a setting's value has (``int | None``: int; ``bool | str``: (bool, str))."""
    return _base(_hints(cls if isinstance(cls, type) else type(cls))[name])


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The class's resolved annotations, once per class: resolving them costs ~1 ms a field, and every evaluation
    and episode batch checks its settings."""
    return typing.get_type_hints(cls)


def _base(hint: Any) -> type | tuple[type, ...]:
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        kinds = tuple(typing.get_origin(a) or a for a in typing.get_args(hint) if a is not type(None))
        return kinds[0] if len(kinds) == 1 else kinds
    return typing.get_origin(hint) or hint  # tuple[int, ...]: a tuple


def flag_of(cls: type, name: str) -> str:
    """How the command line (or, without a flag, a batch file) names the setting ``name`` of ``cls``."""
    declared = declarations(cls).get(name)
    return declared[1].label(name) if declared else name


def check_settings(config: Any) -> None:
    """ValueError, one line naming the flag, for the first declared setting of ``config`` whose value is of the
    wrong type, out of its range or not one of its choices, or that its own check refuses."""
    for name, (f, declared) in declarations(config).items():
        _check_one(config, name, getattr(config, name), f, declared, declared.label(name))


def check_value(config: Any, name: str, value: Any, label: str | None = None) -> None:
    """ValueError, one line naming the setting (its flag, or ``label``), if ``value`` is not what the setting
    ``name`` of the config class (or instance) ``config`` takes: its type, a finite number, in its range, one of its
    choices, passing its own check (:func:`check_settings`, one setting)."""
    f, declared = declarations(config)[name]
    _check_one(config, name, value, f, declared, label or declared.label(name))


def _check_one(config: Any, name: str, value: Any, f: dataclasses.Field, declared: Setting, label: str) -> None:
    if value is None and f.default is None:
        return
    _check_type(label, value, value_type(config, name))
    if isinstance(value, str) and not value.strip() and value != f.default:  # `--model "$UNSET"`: it is not
        # the setting left out (the offline model ran)
        raise ValueError(f"{label} is empty: give a value, or leave {label} out for its default")
    if isinstance(value, float) and not math.isfinite(value):  # nan passes every bound; neither goes in JSON
        raise ValueError(f"{label} must be a finite number, got {value:g}")
    if declared.choices is not None and value not in declared.choices:
        raise ValueError(f"{label} must be one of {', '.join(map(str, declared.choices))}, not {reprlib.repr(value)}")
    problem = range_problem(declared, value)
    if problem is not None:
        raise ValueError(f"{label} {problem}")
    if declared.check is not None:
        declared.check(value)


def recorded_problem(cls: type, recorded: Any) -> str | None:
    """What makes ``recorded`` (a run's settings as its store holds them: anyone's file) not settings of the config
    class ``cls``: no settings at all (``store.recorded.shape_problem``: not a JSON object, nested deeper than
    settings are), or a setting of it that :func:`check_value` refuses (named by its key); None when they read. Keys
    that are no setting of ``cls`` are left to their readers."""
    from store.recorded import shape_problem  # here: the game host and the policy process import this module,
    # and the store's package imports DuckDB

    problem = shape_problem(recorded)
    if problem is not None:
        return problem
    for name in declarations(cls):
        if name not in recorded:
            continue
        value = recorded[name]
        if isinstance(value, list) and value_type(cls, name) is tuple:  # JSON has no tuples: each item checked
            items = [typing.get_args(a) for a in typing.get_args(_hints(cls)[name]) if typing.get_origin(a) is tuple]
            kind = items[0][0] if items and items[0] else object
            wrong = [item for item in value if not isinstance(item, kind) or isinstance(item, bool)]
            if wrong:
                names = {int: "whole numbers", float: "numbers", str: "texts"}.get(kind, str(kind))
                return f"{name} must list {names}, not {reprlib.repr(wrong[0])}"
            value = tuple(value)
        try:
            check_value(cls, name, value, label=name)
        except ValueError as exc:
            return str(exc)
    return None


def recorded_settings(cls: type, text: str | None, run_id: str, names: tuple[str, ...]) -> dict[str, Any]:
    """Run ``run_id``'s recorded settings (``store.recorded.read_recorded``) with those of ``names`` (settings of
    the config class ``cls``) checked as :func:`recorded_problem` checks them: what a reader that uses only these
    needs, the others left to their own readers (``doctor --replay`` reads the one-life setting, ``compare`` the
    settings that change what a score is)."""
    from store.recorded import read_recorded, unreadable_settings  # here: see recorded_problem

    recorded = read_recorded(text, run_id)
    problem = recorded_problem(cls, {name: recorded[name] for name in names if name in recorded})
    if problem is not None:
        raise unreadable_settings(run_id, problem)
    return recorded


def range_problem(declared: Setting, value: float) -> str | None:
    """What is wrong with ``value`` against ``declared``'s bounds (``must be within [0, 2], got 3``), or None: the
    one wording of a setting out of its range, as a batch key and as a flag (``pipeline/cli/common.py`` types)."""
    low, high = declared.minimum, declared.maximum
    if low is not None and high is not None and not low <= value <= high:
        return f"must be within [{_shown(low)}, {_shown(high)}], got {_shown(value)}"
    if low is not None and value < low:
        return f"must be {'0 or more' if low == 0 else f'at least {_shown(low)}'}, got {_shown(value)}"
    if high is not None and value > high:
        return f"must be at most {_shown(high)}, got {_shown(value)}"
    if declared.above is not None and value <= declared.above:
        return f"must be above {_shown(declared.above)}, got {_shown(value)}"
    return None


def _shown(number: float) -> str:
    """A bound or a value in a message: an int in full (a seed's bound is 2**62), else as ``:g`` writes it."""
    return str(number) if isinstance(number, int) else f"{number:g}"


def _check_type(label: str, value: Any, kind: type | tuple[type, ...]) -> None:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if isinstance(value, bool) and bool not in kinds:  # True is an int to Python, not to a person
        ok = False
    else:
        ok = isinstance(value, kinds) or (float in kinds and isinstance(value, int))
    if not ok:
        names = " or ".join({int: "a whole number", float: "a number", str: "a text", bool: "true or false"}
                            .get(k, k.__name__) for k in kinds)
        raise ValueError(f"{label} must be {names}, not {reprlib.repr(value)}")  # a stored value may be any size


def resumable(cls: type) -> tuple[str, ...]:
    """The settings ``--resume`` may change: the resumable ones and the budgets."""
    return tuple(n for n, (_, s) in declarations(cls).items() if s.resumable or s.budget)


def budgets(cls: type) -> tuple[str, ...]:
    return tuple(n for n, (_, s) in declarations(cls).items() if s.budget)


def before_recorded(cls: type) -> dict[str, Any]:
    """The values that reproduce what runs stored before a setting existed did (where not the default)."""
    return {n: s.before_recorded for n, (_, s) in declarations(cls).items() if s.before_recorded is not UNSET}


# ------------------------------------------------------------------------------------------------ episode limits


MAX_STEPS = 2**31 - 1
"""The most steps any episode may be capped at (``--max-steps``, ``--rollout-steps``, ``--eval-max-steps``,
``--screen-steps``): the store's episode length is an INTEGER. ``optimize --rollout-steps 4611686018427387904`` was
taken, played its whole game and ended in a DuckDB conversion error (a traceback) when the episode was stored."""

MAX_TIME_LIMIT_S = 7 * 86_400
"""The longest time limit of a policy call or an episode (a week; the paper's episode limit is 900 s): the policy
channel waits with ``poll()``, which takes milliseconds as a C int (~24.8 days at most). ``--call-time-limit`` or
``--episode-time-limit`` of 4611686018427387904, 1e308 or 30 days was taken and crashed every episode at step 0
(``OverflowError``), a forfeit each; 2,147,000 s ran."""

MAX_MEMORY_MB = 2**30
"""The most address space a worker may be given beyond its start, in MB (a PiB: no machine has it; ``RLIMIT_AS``
takes less than 2**63 bytes: a larger cap raises ``OverflowError``, measured)."""


@dataclass(frozen=True)
class EpisodeLimits:
    """The limits an episode is played under; their defaults are written here and nowhere else."""

    max_steps: int = setting(4000, "cut an episode off after this many steps, reported as truncated (default: "
                             "%(default)s, the paper's)", minimum=1,
                             maximum=MAX_STEPS)
    """Steps after which an episode is cut off (reported as ``truncated``); the paper's cap is 4000."""
    call_time_limit_s: float = setting(1.0, "time limit of one policy call, 0 for none (default: %(default)s)",
                                       flag="--call-time-limit", metavar="SECONDS", minimum=0,
                                       maximum=MAX_TIME_LIMIT_S)
    """Limit for one policy call, ``policy(obs)``, including every bundled method it calls (0: none)."""
    episode_time_limit_s: float = setting(900.0, "wall-clock limit of one episode (default: %(default)s)",
                                          flag="--episode-time-limit", metavar="SECONDS", above=0,
                                          maximum=MAX_TIME_LIMIT_S)
    """Wall-clock limit of one whole episode."""
    memory_limit_mb: int | None = setting(4096, "address space a worker may take beyond what it had at start, in "
                                          "MB (default: %(default)s)", cli=False,
                                          maximum=MAX_MEMORY_MB)
    """Extra address space a worker process may take beyond what it had at start (None: unlimited)."""

    @classmethod
    def of(cls, config: Any) -> "EpisodeLimits":
        """The limits a config (any object with some of these fields) sets; the defaults for the others."""
        return cls(**{f.name: getattr(config, f.name) for f in dataclasses.fields(cls) if hasattr(config, f.name)})


def same_as(cls: type, name: str, **changes: Any) -> Any:
    """A config's field declared as ``cls``'s field ``name`` is (default, help, flag, checks), with ``changes`` to
    its setting (``resumable=True``, ``cli=False``, ...) or its default (``default``): one declaration for a setting
    that several verbs take."""
    f = cls.__dataclass_fields__[name]
    default = changes.pop("default", f.default)
    return dataclasses.field(default=default, metadata={"setting": dataclasses.replace(f.metadata["setting"], **changes)})


def limit(name: str, **changes: Any) -> Any:
    """A config's field for the episode limit ``name``: :class:`EpisodeLimits`'s declaration (see :func:`same_as`)."""
    return same_as(EpisodeLimits, name, **changes)
