"""The ``codearcade`` command line: one verb per job, each with ``--store`` and ``--help``.

:func:`main` parses the command line with the top-level parser that :func:`build_parser` assembles from the
verbs' modules (``pipeline/cli/<verb>.py``: each adds its own arguments, beside the handler that reads them);
``common.py`` holds what they share. A verb's module imports what its handler needs only when it runs, so
``codearcade --help`` stays quick.

Every verb's parser is :class:`~pipeline.cli.common.CodearcadeParser`: a typo'd flag or verb is answered in one
line with the nearest one. Run ids in error messages are printed by their shortest unique prefix.

Exit codes: 0 success; 1 the job ran but an episode ended in a policy error, time-out, crash or score tampering;
2 bad input (unknown game, missing or broken policy file, unusable or damaged store), with a one-line message on
stderr; 130 interrupted. Everything a verb prints goes through ``common.show``, which makes text from policy code,
an LLM's reply or the store safe for a terminal (``viewers/safe_text.py``); so does what Python prints by itself
in the command's process (an uncaught exception's traceback, a warning).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import IO, Any, Callable, Sequence

try:  # Ctrl-C while the command starts (its imports take a second or more on a busy machine): nothing has
    # started that needs stopping or rolling back, so it ends as an interrupted command does, without a traceback
    from pipeline.cli import (audit, batch, blame, compare, doctor, export, games, new, optimize, replay, report, runs,
                                serve, sql, view)
    from pipeline.cli import eval as eval_  # the verb's module (the builtin is not used here)
    from pipeline.cli.common import (EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_OK, CliError, CodearcadeParser,
                                     shorten_in_message, show)
    from pipeline.stopping import end_process, exit_now, quiet_swallowed_interrupts, stop_on_signals, stop_once
except KeyboardInterrupt:
    sys.stderr.write("codearcade: interrupted\n")
    raise SystemExit(130) from None


VERBS = (eval_, optimize, serve, audit, batch, doctor, replay, sql, runs, report, blame, games, new, view, export,
         compare)
"""The verbs' modules, in the order ``codearcade --help`` lists them; each adds its parser (``add_parser``), whose
handler is its ``run(args)``."""


def build_parser() -> argparse.ArgumentParser:
    parser = CodearcadeParser(
        prog="codearcade",
        description="Game-playing agents whose policies are Python programs, improved by an LLM; "
        "every step and call in a DuckDB store.",
        epilog="Run `codearcade VERB --help` for a verb's options.",
    )
    parser.add_argument("--version", action="version", version=f"codearcade {_version()}")
    verbs = parser.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True
    for verb in VERBS:
        verb.add_parser(verbs)
    return parser


def _version() -> str:
    """The installed codearcade's version (what a run records in ``runs.package_versions``)."""
    from importlib import metadata

    try:
        return metadata.version("codearcade")
    except metadata.PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def _user_errors() -> tuple[type[BaseException], ...]:
    from games import UnknownGameError
    from pipeline.llm.local import LocalModelError
    from store import StoreError
    from store.locks import RunBusyError
    from tracing.policy_file import PolicyLoadError

    return (CliError, PolicyLoadError, UnknownGameError, StoreError, RunBusyError, LocalModelError, ValueError)


def _interrupted_once(signum: int, frame: object) -> None:
    """Ctrl-C, or SIGTERM (``pipeline/stopping.py``): raise KeyboardInterrupt once, then ignore both while the
    command winds down (the run is marked interrupted, the zygotes and their processes are stopped)."""
    PRESSED.set()
    stop_once(signum, frame)


class _StderrThatMayClose:
    """The command's stderr, whose reader may go away (``codearcade eval ... 2>&1 | head -1``): progress lines and
    notices are for people, so one it cannot take is dropped and the job goes on. A progress line's BrokenPipeError
    had ended a good run as failed (raised in the episodes' message loop, it was taken for a worker's malformed
    message). Once the reader is gone, fd 2 points at /dev/null, for the processes this one starts too."""

    def __init__(self, stream: IO[str]) -> None:
        self._stream = stream
        self._gone = False

    def _went(self) -> None:
        self._gone = True
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())
        os.close(devnull)

    def write(self, text: str) -> int:
        if not self._gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._went()
        return len(text)

    def flush(self) -> None:
        if not self._gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._went()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


PRESSED = threading.Event()
"""Set by a Ctrl-C. A library may wrap the KeyboardInterrupt it raised in an error of its own (DuckDB's "Query
interrupted" or its error of a Python function in a query, pydantic's SchemaError while litellm builds a model):
whatever error then ends the command is the Ctrl-C's, and the command ends as interrupted (130), not with it."""


def _interrupted() -> int:
    show("codearcade: interrupted", file=sys.stderr)
    return EXIT_INTERRUPTED


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: ``argv`` (``sys.argv[1:]`` when None); returns its exit code. With no ``argv`` this is the
    command line's own process, which ends here once the command is done (:func:`pipeline.stopping.end_process`); a
    caller in the same process gives ``argv`` and goes on as it was."""
    code = _main(argv)
    if argv is None:
        _end_now_past_a_stuck_sink(code)
        end_process(code)
    return code


def _end_now_past_a_stuck_sink(code: int) -> None:
    """End the process at once, its own streams flushed, when a Rerun sink in it did not answer within its time
    (``viewers.rerun_recording.wedged``): its Rust thread is stuck in a write for good, and the interpreter's exit
    waited on it (the recording flushed as it was dropped), so `view --save` onto a full disk or a pipe nobody
    read said its one line and never exited, past SIGTERM. Nothing is left to do: the command has ended."""
    recording = sys.modules.get("viewers.rerun_recording")  # only a command that recorded has it
    if recording is None or not getattr(recording, "wedged", False):
        return
    exit_now(code)


def _main(argv: Sequence[str] | None) -> int:
    PRESSED.clear()  # this command's presses only (tests run many commands in one process)
    if argv is None:  # the command line's own process: a traceback or warning Python prints may quote anyone's text
        from pipeline.boundary.preload import lists_are_not_dataframes
        from viewers.safe_text import make_python_reports_terminal_safe

        make_python_reports_terminal_safe()
        quiet_swallowed_interrupts()  # a press Python swallowed is said once, as `interrupted` (pipeline/stopping.py)
        lists_are_not_dataframes()
    given = list(sys.argv[1:] if argv is None else argv)
    if given[:1] == ["help"] and len(given) <= 2:  # `codearcade help [VERB]`, as git and pip take it
        given = [*given[1:], "--help"]
    try:
        args = build_parser().parse_args(given)
    except KeyboardInterrupt:  # Ctrl-C before the verb started anything
        show("codearcade: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    handler: Callable[[argparse.Namespace], int] = args.handler
    if argv is None and not isinstance(sys.stderr, _StderrThatMayClose) and sys.stderr is not None:
        sys.stderr = _StderrThatMayClose(sys.stderr)  # the command line's own process
    installed = stop_on_signals(_interrupted_once)
    try:
        from pipeline.boundary.zygotes import keep_hosts

        with keep_hosts():  # a verb that plays several times reuses its game hosts; they exit with the verb
            return handler(args)
    except BrokenPipeError:  # `codearcade sql ... | head`: the reader has what it wanted; say nothing more
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so the interpreter's final flush does not fail again
        return EXIT_OK
    except KeyboardInterrupt:
        return _interrupted()
    except _user_errors() as exc:  # the message may quote a policy file, a stored text or an LLM's reply
        from pipeline.llm.local import LocalModelError

        if PRESSED.is_set():
            return _interrupted()

        # one line (but the offline model's failure ends with its server's log), its run ids as the person types
        # them: shortest unique prefixes
        show(f"codearcade: error: {shorten_in_message(str(exc), args)}", multiline=isinstance(exc, LocalModelError),
             file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        if PRESSED.is_set():
            return _interrupted()
        if exc.filename is None:  # not a path the person gave (a socket, a pipe): not theirs to fix
            raise
        # a path that cannot be made or written: report --out, view --save, new, a batch's log, ...
        show(f"codearcade: error: {exc.filename}: {exc.strerror or exc}; give another path", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:
        if PRESSED.is_set():
            return _interrupted()
        missing = _columns_gone(exc, args)
        if missing:
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            show(f"codearcade: error: the store lacks columns its schema made ({', '.join(missing[:3])}{more}): it was "
                 "changed by hand or is damaged; `codearcade doctor` reports what is left", file=sys.stderr)
            return EXIT_BAD_INPUT
        if not _store_damage(exc):
            raise
        from store.views import one_line

        # a store damaged beyond what the checks on opening see
        show(f"codearcade: error: cannot use the store ({one_line(exc)[:300]}); it may be damaged: "
             "`codearcade doctor` reports what is left", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        for signum in installed:
            if argv is None:  # the command line's own process, about to exit: a Ctrl-C now (the zygotes are
                # stopped at exit) would only end it by the signal, past the exit status it has
                signal.signal(signum, signal.SIG_IGN)
            else:  # a caller in this process (a test, a script): the signal as it was
                signal.signal(signum, signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL)


def _columns_gone(exc: BaseException, args: argparse.Namespace) -> list[str]:
    """For DuckDB's error on a name it cannot bind: the columns of the command's store that its schema made and
    that are gone (``store.doctor.missing_columns``: a column dropped by hand fails whichever query reads it, with
    DuckDB's binder error); empty when none is, or when the store cannot be looked at, so the error stays as it is.
    Looked at only on this failure: knowing the columns to expect costs ~70 ms."""
    import duckdb

    if not isinstance(exc, (duckdb.BinderException, duckdb.CatalogException)) or not hasattr(args, "store"):
        return []
    from pipeline.cli.common import open_store
    from store.doctor import missing_columns
    from store.migrations import LATEST

    try:
        store = open_store(args, announce=False)
        with store.read(check=False) as con:
            version = con.execute("SELECT coalesce(max(version), 0) FROM schema_migrations").fetchone()[0]
            return missing_columns(con, min(version, LATEST))
    except Exception:  # noqa: BLE001 - no store, or one that cannot be read: the original error is the one to show
        return []


def _store_damage(exc: BaseException) -> bool:
    """Whether DuckDB raised ``exc`` on reading a damaged store file: an IO, serialization or internal error, or a
    block whose checksum does not match (a plain ``duckdb.Error``)."""
    import duckdb

    from store.db import is_corrupt_block

    return isinstance(exc, (duckdb.IOException, duckdb.SerializationException, duckdb.InternalException)) or \
        is_corrupt_block(exc)
