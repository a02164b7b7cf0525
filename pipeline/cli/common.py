"""What the verbs of the command line share: exit codes, the one-line user error, ``--store`` and ``--rerun``,
argument types, resolving a run id, and :func:`show`, through which every verb prints.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import IO, Any, Callable

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


def add_store(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--store",
        default=None,
        metavar="PATH",
        help="DuckDB store file (default: $CODEARCADE_STORE or ./codearcade.duckdb)",
    )


def add_rerun(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rerun", default="off", metavar="DIR|spawn|off",
                   help="live Rerun recordings: DIR writes DIR/<episode_id>.rrd per episode (and DIR/<run_id>.rrd "
                   "for optimize), spawn streams to a Rerun viewer on 127.0.0.1 (started if none runs), "
                   "a rerun+http://HOST:PORT/proxy url streams there; off (default) records nothing")


def open_store(args: argparse.Namespace):
    from store import Store

    return Store(args.store) if args.store else Store()


def resolve_run(store, text: str) -> str:
    """The run whose id is ``text`` or starts with it (every verb that takes a run accepts a unique prefix)."""
    from store.views import resolve_run_id

    with store.read() as con:
        return resolve_run_id(con, text, store)


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
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
