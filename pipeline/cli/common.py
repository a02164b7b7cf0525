"""What the verbs of the command line share: exit codes, the one-line user error, :func:`show`, through which every
verb prints, the parser every verb uses (a typo'd flag or verb answered with the nearest one), ``--store`` (found
by ``store/locate.py``) and ``--rerun``, argument types, and run references: resolving them and printing ids by
their shortest unique prefix.
"""

from __future__ import annotations

import argparse
import difflib
import errno
import json
import math
import os
import re
import sys
import time
from typing import IO, Any, Callable, Iterable, Sequence

from viewers.safe_text import terminal_json, terminal_text

EXIT_OK, EXIT_EPISODE_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
FAILED_END_REASONS = ("policy_error", "timeout", "crashed", "tampered")


class CliError(Exception):
    """A user error with a one-line message; exits with code 2."""


def show(text: object, *, multiline: bool = False, file: IO[str] | None = None, flush: bool = False) -> None:
    """Print ``text`` made terminal-safe (``viewers/safe_text.py``: no escape sequence, control character or
    bidirectional override; one line unless ``multiline``). Every line a verb prints passes here: any of it may
    hold text from policy code, an LLM's reply or the store. (``--json`` output goes through :func:`show_json`.)"""
    print(terminal_text(text, multiline), file=file if file is not None else sys.stdout, flush=flush)


def show_json(value: Any, *, default: Callable[[Any], Any] | None = None, ensure_ascii: bool = True) -> None:
    """Print ``value`` as indented JSON (``--json``): every character of it kept, none raw that a terminal acts on
    (JSON escapes C0 controls; ``terminal_json`` the rest)."""
    print(terminal_json(json.dumps(value, indent=2, default=default, ensure_ascii=ensure_ascii)))


QUIET_LINE_S = 60.0
"""Off a terminal, the longest an episode-playing command goes without a progress line while it plays."""


class EpisodeProgress:
    """Progress of a command that plays episodes, on stderr: a tqdm bar on a terminal (finished episodes, steps
    played so far: episodes end at unknown lengths, so a bar over ``episodes x max_steps`` would jump); off a
    terminal (a CI log, ``| tee``), where a bar would be silent, a line when the first episode starts playing, as
    each tenth of the episodes finishes and whenever :data:`QUIET_LINE_S` passed without one (a tenth of 100,000
    short episodes took 5 minutes, one long episode as long), so that a long wait is never silent (and a bad
    input, refused before anything plays, is the only line). ``update`` is the executor's progress callback
    (episode index, steps played), ``finished`` the per-episode one (index, length)."""

    def __init__(self, episodes: int, description: str, stream: IO[str] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        from tqdm import tqdm

        self.clock = clock
        self.said_at = clock()
        self.episodes, self.description = episodes, terminal_text(description)
        self.stream = stream if stream is not None else sys.stderr
        self.steps: dict[int, int] = {}
        self.done = 0
        self.bar = None
        self.announced = False
        if self.stream.isatty():
            tqdm.monitor_interval = 0  # no monitor thread: episode workers are forked from this process
            self.bar = tqdm(total=episodes, desc=self.description, unit="episode", dynamic_ncols=True, leave=False,
                            file=self.stream)

    def _announce(self) -> None:
        if self.bar is None and not self.announced:
            self.announced = True
            print(f"{self.description}: {self.episodes} episode{'s' * (self.episodes != 1)} to play",
                  file=self.stream, flush=True)
            self.said_at = self.clock()

    def update(self, index: int, played: int) -> None:
        self.steps[index] = played
        self._announce()
        if self.bar is not None:
            self.bar.set_postfix_str(f"{sum(self.steps.values()):,} steps", refresh=True)
        elif self.clock() - self.said_at >= QUIET_LINE_S:
            self._line()

    def finished(self, index: int, length: int) -> None:
        self.steps[index] = length
        self.done += 1
        self._announce()
        if self.bar is not None:
            self.bar.update(1)
            self.update(index, length)
        elif (self.done * 10 // self.episodes != (self.done - 1) * 10 // self.episodes or self.done == self.episodes
              or self.clock() - self.said_at >= QUIET_LINE_S):
            self._line()

    def _line(self) -> None:
        print(f"{self.description}: {self.done} of {self.episodes} episodes played, "
              f"{sum(self.steps.values()):,} steps", file=self.stream, flush=True)
        self.said_at = self.clock()

    def write(self, line: str) -> None:
        """A line for people above the bar (or just a line, off a terminal), made terminal-safe."""
        if self.bar is not None:
            self.bar.write(terminal_text(line), file=sys.stdout)
        else:
            show(line)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# --------------------------------------------------------------------------------------------------- parsing


_NOT_UTF8 = re.compile("[\udc80-\udcff]")
"""What a command line's byte that is not UTF-8 becomes in Python (``surrogateescape``)."""


_ARGPARSE_TYPE_ERROR = re.compile(r"invalid (float|int) value: ('.*')$", re.S)
"""argparse's own words for a value its type refused (``invalid float value: 'abc'``), said as the project's
types say it (``give a whole number, got 'abc'``): one wording for the same mistake, whatever the flag's type."""
_TYPE_WORDS = {"float": "a number", "int": "a whole number"}


class CodearcadeParser(argparse.ArgumentParser):
    """The parser of ``codearcade`` and of every verb (``add_subparsers`` makes each verb's parser of its parent's
    class): a mistake on the command line is one line on stderr, ``codearcade eval: unknown flag --epsiodes; did
    you mean --episodes?``, with the nearest flag, verb or choice (``difflib``) where there is one, and exit 2."""

    def parse_known_args(self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None):
        # kept for error(): argparse reports a missing argument before the flags it did not know
        self._given = list(sys.argv[1:] if args is None else args)
        for given in self._given:  # bytes that are not UTF-8 (Python keeps them as lone surrogates): the store,
            # the printed lines and the file names codearcade writes hold text, and failed on them with tracebacks
            if isinstance(given, str) and _NOT_UTF8.search(given):
                shown = given.encode("utf-8", "surrogateescape").decode("ascii", "backslashreplace")
                self.error(f"argument '{terminal_text(shown)}' is not UTF-8 text: give it in UTF-8 (a file of that "
                           "name: rename it)")
        return super().parse_known_args(args, namespace)

    def parse_args(self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None):
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:  # left over by the verb's parser (argparse hands them up to this one)
            verb = self._verb_parser(parsed)
            (verb or self).error((verb or self).unknown_message(extras))
        return parsed

    def _verb_parser(self, parsed: argparse.Namespace) -> "CodearcadeParser | None":
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                chosen = action.choices.get(getattr(parsed, action.dest, None) or "")
                return chosen if isinstance(chosen, CodearcadeParser) else None
        return None

    def _long_flags(self) -> list[str]:
        return [s for s in self._option_string_actions if s.startswith("--")]

    def _is_known(self, token: str) -> bool:
        flag = token.split("=", 1)[0]
        if flag in self._option_string_actions:
            return True
        # argparse takes an unambiguous start of a long flag (--epi for --episodes)
        return flag.startswith("--") and len([s for s in self._long_flags() if s.startswith(flag)]) == 1

    def _unknown_flags(self, tokens: Iterable[str]) -> list[str]:
        unknown = []
        for token in tokens:
            if token == "--":
                break
            if token.startswith("--") and len(token) > 2 and not self._is_known(token):
                unknown.append(token.split("=", 1)[0])
        return unknown

    def unknown_message(self, extras: Sequence[str]) -> str:
        """What to say of arguments this parser did not take: the first unknown flag and its nearest known one."""
        flags = self._unknown_flags(extras) or [t.split("=", 1)[0] for t in extras
                                                if t.startswith("-") and not _is_number(t)]
        if not flags:
            return f"unexpected argument{'s' * (len(extras) != 1)} {' '.join(extras)}; `{self.prog} --help` " \
                   "shows the usage"
        return self._flag_message(flags[0])

    def _flag_message(self, flag: str) -> str:
        # the names are compared without their dashes: the two every long flag shares made `--lsat` look like
        # `--store` and `games --store` like `--json`
        known = {s.lstrip("-"): s for s in (self._long_flags() if flag.startswith("--")
                                            else self._option_string_actions)}
        close = difflib.get_close_matches(flag.lstrip("-"), list(known), n=1, cutoff=0.6)
        if close:
            return f"unknown flag {flag}; did you mean {known[close[0]]}?"
        return f"unknown flag {flag}; `{self.prog} --help` lists the flags"

    def error(self, message: str):  # noqa: D102 (argparse's hook)
        typo = self._unknown_flags(getattr(self, "_given", ()))
        if typo and "required" in message:  # `report --lsat`: the typo, not the RUN it kept from being read
            message = self._flag_message(typo[0])
        else:
            message = _ARGPARSE_TYPE_ERROR.sub(lambda m: f"give {_TYPE_WORDS[m[1]]}, got {m[2]}",
                                               self._nearest_choice(message))
        if not message.startswith(("unknown flag", "unknown verb", "unexpected argument")) and \
                "did you mean" not in message and "choose from" not in message:
            message += f" (`{self.prog} --help` shows the usage)"
        self.exit(2, f"{self.prog}: {message}\n")

    def _nearest_choice(self, message: str) -> str:
        """argparse's "invalid choice" with the nearest choice named; an unknown verb said so."""
        match = re.match(r"argument (\S+): invalid choice: '(.*)' \(choose from (.*)\)$", message, re.S)
        if match is None:
            return message
        name, value, listed = match.groups()
        choices = re.findall(r"'([^']*)'", listed)
        close = difflib.get_close_matches(value, choices, n=1, cutoff=0.5)
        hint = f"; did you mean {close[0]}?" if close else ""
        if name == "VERB":
            return f"unknown verb {value!r}{hint or '; `codearcade --help` lists the verbs'}"
        return f"argument {name}: invalid choice {value!r}{hint} (choose from {', '.join(choices)})"


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


# ----------------------------------------------------------------------------------------------------- store


STORE_HELP = ("the DuckDB store; without it: $CODEARCADE_STORE, else the nearest codearcade.duckdb in this "
              "directory or a parent (as git finds .git), else the per-user "
              "~/.local/share/codearcade/codearcade.duckdb")
"""``--store``'s help: the rule of ``store/locate.py``."""


def add_store(p: argparse.ArgumentParser) -> None:
    p.add_argument("--store", default=None, type=_store_path, metavar="PATH", help=STORE_HELP)


def _store_path(text: str) -> str:
    """--store's value: an empty one (``--store "$UNSET"``) is refused, not taken for no --store (the run went to
    the per-user store)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path: give the store's file, or leave --store out for the store "
                                         "found from here")
    return text


def add_rerun(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rerun", default="off", metavar="DIR|spawn|off",
                   help="live Rerun recordings: DIR writes DIR/<episode_id>.rrd per episode (and DIR/<run_id>.rrd "
                   "for optimize), spawn streams to a Rerun viewer on 127.0.0.1 (started if none runs), "
                   "a rerun+http://HOST:PORT/proxy url streams there; off (default) records nothing")


def check_output(path: str | os.PathLike, directory: bool = False) -> None:
    """OSError (with the path: the command's one-line error) unless a command could write ``path`` later: a file,
    or with ``directory`` a folder it makes if need be. Said before the work, not after it; nothing is made."""
    path = os.path.abspath(path)
    if os.path.isdir(path) and not directory:
        raise OSError(errno.EISDIR, os.strerror(errno.EISDIR), path)
    if os.path.lexists(path) and directory and not os.path.isdir(path):
        raise OSError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), path)
    existing = path if os.path.lexists(path) and directory else os.path.dirname(path)
    while not os.path.lexists(existing):  # the nearest existing folder above: it must be one, and writable
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise OSError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), path)
    if not os.access(existing, os.W_OK | os.X_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        raise OSError(errno.EACCES, os.strerror(errno.EACCES), path)


def open_store(args: argparse.Namespace, announce: bool = True):
    """The store the command uses (``store/locate.py``: ``--store``, ``$CODEARCADE_STORE``, the nearest
    ``codearcade.duckdb`` here or in a parent directory, the per-user store). Where the choice may surprise (a
    parent directory's store, or the per-user one), one line on stderr says which it is, unless ``announce`` is
    off (a verb that names the store itself) or there is no such file yet (the verb's error says so, or its start
    line names the store it makes)."""
    from store import Store, locate_store

    location = locate_store(getattr(args, "store", None))
    if announce and location.surprising and location.path.exists():  # a missing one: the error or start line says
        show(f"codearcade: {location.describe()}", file=sys.stderr, flush=True)
    return Store(location)


def store_flag(store) -> list[str]:
    """The ``--store`` words a command printed for the person to run must carry: none when the store is found
    again from here without one (the environment, this directory, a parent, the per-user store)."""
    import os

    return ["--store", os.path.abspath(store.path)] if store.location.rule == "option" else []


def command_text(store, *words: str) -> str:
    """A command for the person to run, as a shell takes it, with the ``--store`` it needs (:func:`store_flag`):
    ``codearcade serve --resume 01M9 --store /abs/s.duckdb`` (without it, one printed after ``--store`` was given
    looked in another store: "no run 01M9")."""
    import shlex

    return shlex.join(["codearcade", *words, *store_flag(store)])


# ------------------------------------------------------------------------------------------------------ runs


RUN_HELP = ("the run: last (the newest), last~N (the N-th before it), -N (the N-th newest), its label, its id or a "
            "unique prefix of one (`codearcade runs` lists them)")
"""What a RUN argument takes (``store/runs.py``), said the same in every verb."""


def add_run(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_id", metavar="RUN", help=RUN_HELP)


def resolve_run(store, text: str, kinds: tuple[str, ...] | None = None, verb: str | None = None,
                unsubmitted: bool = False) -> str:
    """The run ``text`` names (``store/runs.py``: a whole id, ``last``, ``last~N``, ``-N``, a label or a unique
    prefix), the same in every verb. ``kinds``: the verb acts only on these kinds of run, so ``last`` and its kin
    count only those; ``unsubmitted``: they count served runs that hold no submission too (``serve --resume``),
    which they pass over otherwise (nothing to report, blame, view or audit). When that passes over a newer run,
    one line on stderr says which it took and what it passed over."""
    from store.readers import get_run
    from store.runs import RECENT_FORM, passed_over, resolve_run_id

    passed = None
    with store.read() as con:
        run_id = resolve_run_id(con, text, store, kinds, unsubmitted)
        if RECENT_FORM.fullmatch(text.strip()):
            passed = passed_over(con, run_id, kinds, unsubmitted)
            kind = get_run(con, run_id)["kind"]
    if passed:
        short = short_ids(store)
        others = ", ".join(f"{kind} run {short.get(other, other)}{' (no submission)' if empty else ''}"
                           for other, kind, empty in passed[:3])
        more = f" and {len(passed) - 3} more" if len(passed) > 3 else ""
        show(f"codearcade{' ' + verb if verb else ''}: {text.strip()} is {kind} run {short.get(run_id, run_id)}, "
             f"passing over the newer {others}{more}", file=sys.stderr)
    return run_id


def short_ids(store) -> dict[str, str]:
    """Every run id of the store -> its shortest unique prefix (as git abbreviates commits)."""
    from store.runs import short_run_ids

    with store.read() as con:
        return short_run_ids(con)


def short_id(store, run_id: str) -> str:
    """``run_id``'s shortest unique prefix in ``store`` (the id itself when the store does not have it)."""
    return short_ids(store).get(run_id, run_id)


_RUN_ID = re.compile(r"\b[0-9A-HJKMNP-TV-Z]{26}\b(?!\.[0-9])")
"""A ULID, not one that starts an episode id (``RUN.ITERATION.KIND.INDEX``, which is only ever given whole)."""


def shorten_run_ids(text: str, short: dict[str, str]) -> str:
    """``text`` with every whole run id of ``short`` replaced by its shortest unique prefix."""
    return _RUN_ID.sub(lambda m: short.get(m.group(0), m.group(0)), text)


def shorten_in_message(text: str, args: argparse.Namespace | None) -> str:
    """An error message with its run ids shortened, read from the command's store when it has one and it opens
    at once; the message unchanged otherwise (an error is never lost to this)."""
    if not _RUN_ID.search(text) or args is None:
        return text
    try:
        from store import Store, locate_store

        location = locate_store(getattr(args, "store", None))
        if not location.path.is_file():
            return text
        return shorten_run_ids(text, short_ids(Store(location, lock_timeout_s=1.0)))
    except Exception:  # a locked or damaged store: the whole ids are still right
        return text


def run_name(text: str) -> str:
    """``--name``: a run's label, checked as the store checks it (``store/runs.py``)."""
    from store.runs import check_run_name

    try:
        return check_run_name(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def warn_if_named(store, name: str | None, run_id: str | None = None) -> None:
    """A warning on stderr when runs other than ``run_id`` already carry the label ``name``: a run is made under it
    all the same (a batch's reruns share their labels), but every verb given the label will ask which."""
    if name is None or not store.exists():
        return
    from store.runs import runs_named

    with store.read() as con:
        others = [r for r in runs_named(con, name) if r != run_id]
    if others:
        short = short_ids(store)
        listed = ", ".join(short.get(r, r) for r in others[:3]) + (" ..." if len(others) > 3 else "")
        show(f"codearcade: warning: run {listed} is named {name!r} too; a verb given {name!r} will ask for an id",
             file=sys.stderr)


def add_name(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--name", type=run_name, metavar="LABEL",
                   help=f"a label for the {what}: every verb then takes LABEL for it, as for its id "
                   "(starts with a letter, at most 64 characters)")


# ------------------------------------------------------------------------------------------- argument types


def _whole_number(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"give a whole number, got {text!r}") from None


MAX_COUNT = 2**31 - 1
"""The largest count a verb's own flag takes (``runs -n``, ``sql --max-rows``, ``--iteration``): what a store's
``INTEGER`` holds. ``runs -n 99999999999999999999`` reached DuckDB, which refused it with a traceback."""


def whole_number_within(low: int, high: int = MAX_COUNT) -> Callable[[str], int]:
    """The argparse type of a whole number from ``low`` to ``high``, refused in the words of a setting's range."""
    def typed(text: str) -> int:
        value = _whole_number(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be within [{low}, {high}], got {value}")
        return value

    typed.__name__ = "positive_int" if low >= 1 else "non_negative_int"
    return typed


positive_int = whole_number_within(1)
non_negative_int = whole_number_within(0)


MAX_SECONDS = 86_400.0
"""The longest wait a verb's own flag takes (``export --timeout``): ``--timeout 1e308`` reached the OTLP exporter,
which failed with "timestamp out of range for platform time_t"."""


def positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"give a number of seconds, got {text!r}") from None
    if not 0 < value <= MAX_SECONDS:  # NaN too
        raise argparse.ArgumentTypeError(f"must be a number of seconds above 0 and at most {MAX_SECONDS:g}, got {text}")
    return value


def probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be within [0, 1], got {value}")
    return value


def rerun_target(value: str | None) -> str | None:
    """``--rerun`` as a live target for the episode workers (Rerun itself is never loaded in this process)."""
    from viewers.rerun_sinks import ViewerError, resolve_live_target

    try:
        return resolve_live_target(value)
    except ViewerError as exc:
        raise CliError(str(exc)) from None


def json_default(value: Any) -> str:
    """``json.dumps``'s fallback for the store's timestamps and decimals."""
    return str(value)


# ------------------------------------------------------------------------------------- declared settings


def _argument_type(kind, declared) -> Callable[[str], Any] | None:
    """The argparse type of a setting: its value type, held to its declared range (``settings.range_problem``), so
    that a flag out of range is refused by the parser like any other bad value, in the same words as a batch key.
    Its ``kind`` is the value's type; its name says the range as the project's own types do."""
    from pipeline.settings import range_problem

    if kind not in (int, float):
        return None

    def typed(text: str) -> Any:
        if kind is int:
            value = _whole_number(text)
        else:
            try:
                value = float(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"give a number, got {text!r}") from None
            if not math.isfinite(value):  # nan passes every bound; neither goes in JSON
                raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        problem = range_problem(declared, value)
        if problem is not None:
            raise argparse.ArgumentTypeError(problem)
        return value

    low = declared.minimum if declared.minimum is not None else (
        None if declared.above is None else declared.above + (1 if kind is int else 0))
    if kind is int:
        typed.__name__ = "non_negative_int" if low == 0 else "positive_int" if low is not None and low >= 1 else "int"
    else:
        typed.__name__ = "probability" if (declared.minimum, declared.maximum) == (0, 1) else "float"
    typed.kind = kind
    return typed


def add_settings(p: argparse.ArgumentParser, config: type, groups: dict[str, str] | None = None, *,
                 defaults: bool = False, only: Sequence[str] | None = None, help_prefix: str = "") -> tuple[str, ...]:
    """Add the flags of the declared settings of ``config`` (``pipeline/settings.py``; those named in ``only``, in
    its order) to ``p``: each with its help, type, range and choices, in its group (``groups``: each group's
    title and line). Without ``defaults`` every flag defaults to None, so that the handler sees which were given.
    Returns the names (``dest``) of the settings added."""
    from dataclasses import replace

    from pipeline.settings import UNSET, declarations, value_type

    declared = declarations(config)
    names = list(only) if only is not None else [n for n, (_, s) in declared.items() if s.cli]
    names.sort(key=lambda n: not declared[n][1].positional)  # positionals first, as a verb's usage shows them
    made: dict[str | None, Any] = {None: p}
    # each group's flags together, the verb's own first (argparse lists them in the order they are added)
    order = [None] + [g for g in (groups or {})]
    for group in order:
        for name in names:
            f, s = declared[name]
            if (s.group or ("budgets" if s.budget else None)) != group:
                continue
            if group not in made:
                made[group] = p.add_argument_group(group, groups[group])
            target = made[group]
            default = (f.default if s.flag_default is UNSET else s.flag_default) if defaults else None
            shown = f"{f.default:g}" if isinstance(f.default, float) else str(f.default)
            s = replace(s, help=s.help.replace("%(default)s", shown),
                        switches=tuple(replace(w, help=w.help.replace("%(default)s", shown)) for w in s.switches))
            if s.positional:
                target.add_argument(name, metavar=s.metavar, nargs="?", default=default, help=help_prefix + s.help)
            elif s.switches:
                if len(s.switches) > 1:
                    target = target.add_mutually_exclusive_group()
                for i, switch in enumerate(s.switches):
                    target.add_argument(switch.flag, action="store_const", const=switch.value, dest=name,
                                        help=help_prefix + switch.help, **({"default": default} if i == 0 else {}))
            else:
                kind = value_type(config, name)
                extra = {"choices": s.choices} if s.choices is not None else {"type": _argument_type(kind, s)}
                if s.repeat:
                    extra["action"] = "append"
                target.add_argument(*s.flags(name), dest=name, metavar=s.metavar, default=default,
                                    help=help_prefix + s.help, **{k: v for k, v in extra.items() if v is not None})
    return tuple(names)
