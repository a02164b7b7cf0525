"""``codearcade batch EXPERIMENTS.toml``: a matrix of optimizations, headless and resumable (the file format:
``pipeline/jobs/batch.py``).
"""

from __future__ import annotations

import argparse
import os
import sys

from pipeline.cli.common import EXIT_EPISODE_FAILED, EXIT_OK, add_store, positive_int, show


def add_parser(verbs) -> None:
    """Add ``batch`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "batch",
        help="run a matrix of optimizations headless (resumable)",
        description="Run every optimization an experiment file declares, in parallel, into one store. Running "
        "the same command again skips finished runs and resumes interrupted ones. See pipeline/jobs/batch.py and "
        "examples/ablation.toml for the file format.",
    )
    p.add_argument("experiments", metavar="EXPERIMENTS.toml")
    p.add_argument("--workers", type=positive_int, default=None, help="runs at once (default: cores)")
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="local processes (default) or a Ray cluster")
    p.add_argument("--address", help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--dry-run", action="store_true", help="list what would run, and do nothing")
    p.add_argument("--log", metavar="FILE", help="plain log file (default: <store>.<batch>.log beside the store)")
    add_store(p)
    p.set_defaults(handler=run)


def _batch_display():
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
        table = Table(title="codearcade batch", expand=False)
        for column in ("run", "state", "iteration", "best", "run id"):
            table.add_column(column)
        for p in progress:
            it = "-" if p.iteration is None else f"{p.iteration}/{p.iterations}"
            best = "-" if p.best is None else f"{p.best:g}"
            table.add_row(*(Text(terminal_text(cell)) for cell in (p.label, p.state, it, best, p.run_id or "")))
        counts = {s: sum(1 for p in progress if p.state == s)
                  for s in ("finished", "budget", "running", "failed", "skipped")}
        table.caption = "  ".join(f"{k} {v}" for k, v in counts.items())
        live.update(table)

    return show, live.stop


def run(args: argparse.Namespace) -> int:
    from datetime import datetime
    from pathlib import Path

    from pipeline.jobs.batch import load_experiments, plan, run_local, run_ray
    from store import Store
    from viewers.safe_text import terminal_text

    batch = load_experiments(args.experiments)
    if args.store:
        store = Store(args.store)
    elif batch.store:
        store = Store(Path(batch.store))  # relative to where the user runs it, like --store
    else:
        store = Store()
    planned = plan(batch, store)
    if not args.dry_run:  # a missing key stops the batch before any run starts
        from pipeline.llm.providers import check_credentials

        for item in planned:
            if item.action != "skip" and item.run.config.model:
                check_credentials(item.run.config.model, item.run.config.api_base)
    if args.dry_run:
        show(f"batch {batch.name}: {len(planned)} runs into {store.path}")
        for p in planned:
            show(f"  {p.action:<6} {p.run.label}" + (f"  (run {p.run_id}, {p.status})" if p.run_id else ""))
        return EXIT_OK
    log_path = Path(args.log) if args.log else store.path.with_name(f"{store.path.name}.{batch.name}.log")
    log_file = open(log_path, "a")
    display, stop = _batch_display()
    quiet = sys.stdout.isatty()

    def log(line: str) -> None:
        # the log file is read with cat and tail: it gets the terminal-safe line too (a failure's note quotes
        # the last line a run printed)
        stamped = terminal_text(f"{datetime.now().isoformat(timespec='seconds')} {line}")
        log_file.write(stamped + "\n")
        log_file.flush()
        if not quiet:
            show(stamped, flush=True)

    log(f"batch {batch.name}: {len(planned)} runs ({sum(p.action == 'skip' for p in planned)} finished already), "
        f"executor {args.executor}, store {store.path}")
    try:
        if args.executor == "ray":
            result = run_ray(batch, store, planned, args.address, log, display)
        else:
            workers = args.workers or (os.cpu_count() or 1)
            result = run_local(batch, store, planned, workers, log, display,
                               log_dir=log_path.with_name(log_path.name + ".runs"))
    finally:
        stop()
    failed = result.failed
    log(f"batch {batch.name} done: {sum(p.state == 'finished' for p in result.progress)} finished, "
        f"{sum(p.state == 'skipped' for p in result.progress)} skipped, {len(failed)} failed")
    log_file.close()
    for p in failed:
        show(f"codearcade: {p.label} failed: {p.note}; rerun the same command to resume it", file=sys.stderr)
    return EXIT_EPISODE_FAILED if failed else EXIT_OK
