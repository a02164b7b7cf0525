"""``codearcade batch EXPERIMENTS.toml``: a matrix of optimizations, headless and resumable (the file format:
``pipeline/jobs/experiments.py``).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
from contextlib import ExitStack, contextmanager
from typing import Iterator

from pipeline.cli.common import EXIT_EPISODE_FAILED, EXIT_OK, CliError, add_store, positive_int, short_ids, show
from store.scores import score_text


def add_parser(verbs) -> None:
    """Add ``batch`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "batch",
        help="run a matrix of optimizations headless (resumable)",
        description="Run every optimization an experiment file declares, in parallel, into one store. Running "
        "the same command again skips finished runs and resumes interrupted ones. See pipeline/jobs/experiments.py "
        "and examples/ablation.toml for the file format.",
    )
    p.add_argument("experiments", metavar="EXPERIMENTS.toml")
    p.add_argument("--workers", type=positive_int, default=None, help="runs at once (default: cores)")
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="local processes (default) or a Ray cluster")
    p.add_argument("--address", help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--dry-run", action="store_true",
                   help="list what would run (each run's label in the store), warn of unset API keys and servers "
                   "that do not answer, and do nothing")
    p.add_argument("--log", metavar="FILE", help="plain log file (default: <store>.<batch>.log beside the store)")
    add_store(p)
    p.set_defaults(handler=run)


def _batch_display(store):
    """A live table on a terminal (rich), nothing otherwise (the log lines tell the story). Its cells are plain
    ``Text``, never rich markup (a label or a failure's note is anyone's text: ``[link=...]`` stays as written),
    and terminal-safe (``viewers/safe_text.py``)."""
    if not sys.stdout.isatty():
        return (lambda progress: None), (lambda: None)
    from rich.live import Live
    from rich.table import Table
    from rich.text import Text

    from viewers.safe_text import terminal_text

    live = Live(refresh_per_second=2, transient=False)
    live.start()

    def show(progress) -> None:
        try:
            short = short_ids(store)
        except Exception:  # the store is made by the first run; until then there is nothing to shorten
            short = {}
        table = Table(title="codearcade batch", expand=False)
        for column in ("run", "state", "iteration", "best", "run id"):
            table.add_column(column)
        for p in progress:
            it = "-" if p.iteration is None else f"{p.iteration}/{p.iterations}"
            best = best_cell(p)
            table.add_row(*(Text(terminal_text(cell)) for cell in (p.label, p.state, it, best,
                                                                    short.get(p.run_id, p.run_id) or "")))
        counts = {s: sum(1 for p in progress if p.state == s)
                  for s in ("finished", "budget", "running", "failed", "skipped", "not started")}
        table.caption = "  ".join(f"{k} {v}" for k, v in counts.items())
        live.update(table)

    return show, live.stop


def best_cell(progress) -> str:
    """A run's best score in the live table: ``-`` before it assessed anything, ``no score`` once every version it
    assessed forfeited a game (its starter's iteration 0 included: a forfeit is never scored, ``store/scores.py``),
    where it showed ``-`` as if nothing had been played."""
    if progress.best is not None:
        return score_text(progress.best)
    return "-" if progress.iteration is None else "no score"


def _endpoint_problems(planned) -> list[str]:
    """One line per model whose key is unset, and per ``api_base`` that does not answer, among the runs that
    would start or resume (``pipeline/llm/providers.py``), with how many runs each would stop."""
    from functools import partial

    from pipeline.llm.providers import FIX_IN_BATCH_FILE, check_credentials, check_reachable

    found: dict[tuple, str | None] = {}  # each model and each server checked once
    problems: dict[str, int] = {}
    for item in planned:
        config = item.run.config
        if item.action == "skip":
            continue
        entries = config.models or ([{"model": config.model, "api_base": config.api_base}] if config.model else [])
        checks = [(partial(check_credentials, other_fixes=FIX_IN_BATCH_FILE), e["model"], e["api_base"])
                  for e in entries] + \
            [(check_reachable, base) for base in dict.fromkeys([e["api_base"] for e in entries] + [config.api_base])
             if base]
        for check, *values in checks:
            key = (getattr(check, "func", check).__name__, *values)
            if key not in found:
                try:
                    check(*values)
                    found[key] = None
                except ValueError as exc:  # MissingCredentialsError, UnreachableEndpointError
                    found[key] = str(exc)
            if found[key] is not None:
                problems[found[key]] = problems.get(found[key], 0) + 1
    return [f"{text} ({n} run{'s' * (n != 1)})" for text, n in problems.items()]


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from pipeline.jobs.batch import plan
    from pipeline.jobs.experiments import load_experiments
    from store import Store, StoreLocation, locate_store

    if args.address is not None and args.executor != "ray":  # it ran locally, the address left unused
        raise CliError("--address is a Ray cluster's: it goes with --executor ray")

    batch = load_experiments(args.experiments)
    if args.store or not batch.store:
        location = locate_store(args.store)
    else:  # relative to where the user runs it, like --store
        location = StoreLocation(Path(batch.store), "experiment")
    if location.surprising:
        show(f"codearcade: {location.describe()}", file=sys.stderr, flush=True)
    store = Store(location)
    if not store.path.parent.is_dir():  # said first, for --dry-run too (the log file beside it failed to open)
        where = "experiment file's store" if location.rule == "experiment" else "store"
        raise CliError(f"the {where} {store.path}: directory {store.path.parent} does not exist; create it or "
                       "choose another store")
    planned = plan(batch, store)
    problems = _endpoint_problems(planned)
    if args.dry_run:
        short = short_ids(store) if store.exists() else {}
        show(f"batch {batch.name}: {len(planned)} runs into {store.path}")
        for p in planned:
            name = f"  [{p.run.name}]" if p.run.name else ""
            renamed = f", named {p.stored_name!r} now" if p.renamed and p.stored_name else \
                (", unnamed now" if p.renamed else "")
            show(f"  {p.action:<6} {p.run.label}{name}"
                 + (f"  (run {short.get(p.run_id, p.run_id)}, {p.status}{renamed})" if p.run_id else ""))
        for line in problems:  # what would stop the batch: said now, before it is run for real
            show(f"codearcade: warning: {line}", file=sys.stderr)
        return EXIT_OK
    if problems:  # a missing key or a server that does not answer stops the batch before any run starts
        raise CliError(problems[0] + (f"; and {len(problems) - 1} more problem(s): `codearcade batch "
                                      f"{args.experiments} --dry-run` lists them" if len(problems) > 1 else ""))
    with _only_runner(store, batch.name):
        return _run(args, batch, store, plan(batch, store))  # planned again, now that no one else runs it


@contextmanager
def _only_runner(store, name: str) -> Iterator[None]:
    """Hold the batch's lock beside the store for the block (``store/locks.py``), or say who holds it: two
    commands running one batch at once both planned its runs, and each started them all (two runs per entry)."""
    from store.locks import RunBusyError, run_lock

    with ExitStack() as held:
        try:
            held.enter_context(run_lock(store.path, "batch-" + hashlib.sha256(name.encode()).hexdigest()[:16]))
        except RunBusyError as exc:
            raise CliError(f"batch {name} is being run on {store.path} by process {exc.holder}; wait for it to end "
                           "(or stop it), then run the same command again to go on") from None
        yield


def _close_quietly(file) -> None:
    """Close ``file``: a flush that fails (the bytes a full disk refused, written again at close) loses nothing more
    than the log lines already said on the terminal, and the file is closed all the same."""
    try:
        file.close()
    except OSError:
        pass


def _run(args: argparse.Namespace, batch, store, planned) -> int:
    """The batch run for real (``run``, once it holds the batch's lock)."""
    from datetime import datetime
    from pathlib import Path

    from pipeline.jobs.batch import NOT_STARTED, rename_finished, run_local, run_ray
    from viewers.safe_text import terminal_text

    log_path = Path(args.log) if args.log else store.path.with_name(f"{store.path.name}.{batch.name}.log")
    try:
        log_file = open(log_path, "a")
    except OSError as exc:  # past check_output: a file that takes no appending (/proc/...) says EINVAL, unnamed
        raise CliError(f"--log {log_path}: {exc.strerror or exc}; give another path") from None
    display, stop = _batch_display(store)
    quiet = sys.stdout.isatty()

    lost: list[OSError] = []

    def log(line: str) -> None:
        # the log file is read with cat and tail: it gets the terminal-safe line too (a failure's note quotes
        # the last line a run printed)
        stamped = terminal_text(f"{datetime.now().isoformat(timespec='seconds')} {line}")
        if not lost:
            try:
                log_file.write(stamped + "\n")
                log_file.flush()
            except OSError as exc:
                # a full disk: the batch died with a traceback at this line, and its runs with it (they die with
                # the batch), each cut off in its iteration; the log is not the work, so the batch goes on
                lost.append(exc)
                _close_quietly(log_file)
                show(f"codearcade: warning: cannot write the batch's log {log_path}: {exc.strerror or exc}; the "
                     "batch goes on without it", file=sys.stderr, flush=True)
        if not quiet:
            show(stamped, flush=True)

    log(f"batch {batch.name}: {len(planned)} runs ({sum(p.action == 'skip' for p in planned)} finished already), "
        f"executor {args.executor}, store {store.path}")
    try:
        rename_finished(store, planned, log)
        if args.executor == "ray":
            result = run_ray(batch, store, planned, args.address, log, display)
        else:
            workers = args.workers or (os.cpu_count() or 1)
            result = run_local(batch, store, planned, workers, log, display,
                               log_dir=log_path.with_name(log_path.name + ".runs"))
    except KeyboardInterrupt:  # the command's own handler then says "interrupted" and exits 130
        stop()  # the live table first, so that the lines below print under it (stopping twice is a no-op)
        log(f"batch {batch.name} interrupted")
        show("codearcade: interrupted: the runs are stored up to their last whole iterations; rerun the same command "
             "to resume them", file=sys.stderr, flush=True)
        raise
    finally:
        stop()
    failed = result.failed
    budget = sum(p.state == "budget" for p in result.progress)
    not_started = sum(p.state == NOT_STARTED for p in result.progress)
    log(f"batch {batch.name} done: {sum(p.state == 'finished' for p in result.progress)} finished, "
        + (f"{budget} stopped by a budget (rerun with a larger one to resume), " if budget else "")
        + f"{sum(p.state == 'skipped' for p in result.progress)} skipped, {len(failed)} failed"
        + (f", {not_started} not started (the store's disk is full)" if not_started else ""))
    _close_quietly(log_file)
    for p in failed:
        show(f"codearcade: {p.label} failed: {p.note}; rerun the same command to resume it", file=sys.stderr)
    return EXIT_EPISODE_FAILED if failed or not_started else EXIT_OK
