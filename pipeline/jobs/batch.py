"""Running a batch (``codearcade batch``): the runs of an experiment file (a :class:`~pipeline.jobs.experiments.
Batch`, read by ``pipeline/jobs/experiments.py``) planned against the store by their keys (:func:`plan`), then run by
an executor, with their progress, their logs, and stopping.

Executors: ``local`` runs each run in its own process (``--workers`` at once; the processes die with the
batch, so a killed batch leaves nothing running and nothing locked), all writing the one store in short
transactions. ``ray`` sends each run to a Ray cluster as a task that works on a private store and returns the
run's rows (``store/bundle.py``); the driver alone writes them into the store, one transaction per run.
"""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from pipeline.jobs.experiments import Batch, BatchRun
from pipeline.jobs.worker import BUDGET_EXIT, INTERRUPTED_EXIT, STORE_FULL_EXIT, run_remote
from pipeline.stopping import Terminated, raise_if_stopped
from store import Store
from store.readers import batch_progress, batch_runs
from store.writer import set_run_name


@dataclass
class PlannedRun:
    run: BatchRun
    action: str  # start | resume | skip
    run_id: str | None = None
    status: str | None = None
    stored_name: str | None = None
    """The run's name in the store (a run found there): a finished run whose entry's label changed is renamed."""

    @property
    def renamed(self) -> bool:
        """A finished run whose label in the experiment file is not its name in the store: it is given the label
        without being run again (a run that resumes is given it as it starts)."""
        return self.action == "skip" and self.run.name is not None and self.run.name != self.stored_name


def plan(batch: Batch, store: Store) -> list[PlannedRun]:
    """What running the batch would do now: skip finished runs, resume started ones, start the rest."""
    found: dict[str, tuple[str, str, str | None]] = {}
    if store.exists():
        with store.read() as con:
            rows = batch_runs(con, batch.name)
        for key, run_id, status, name in rows:
            found[key] = (run_id, status, name)  # the latest run of a key wins
    planned = []
    for run in batch.runs:
        key = run.found_as(found)
        if key not in found:
            planned.append(PlannedRun(run, "start"))
        else:
            run_id, status, name = found[key]
            planned.append(PlannedRun(run, "skip" if status == "finished" else "resume", run_id, status, name))
    return planned


def rename_finished(store: Store, planned: list[PlannedRun], log: Callable[[str], None]) -> None:
    """Give the finished runs whose entry's label changed (a ``[[run]]`` name edited) that label, in one
    transaction: they are not run again, so the label reached the store only if one ever resumed."""
    renamed = [p for p in planned if p.renamed]
    if not renamed:
        return
    with store.write() as con:
        for p in renamed:
            set_run_name(con, p.run_id, p.run.name)
    for p in renamed:
        log(f"renamed run {p.run_id} {p.run.name!r}" + (f" (was {p.stored_name!r})" if p.stored_name else ""))


# ------------------------------------------------------------------------------------------- local executor


def worker_command(store: Store, item: PlannedRun, batch: Batch, episode_workers: int) -> list[str]:
    spec = {"store": str(store.path), "config": asdict(item.run.config), "resume": item.run_id,
            "batch": batch.name, "batch_key": item.run.key, "name": item.run.name, "episode_workers": episode_workers}
    return [sys.executable, "-m", "pipeline.jobs.worker", json.dumps(spec)]


@dataclass
class Progress:
    """What the display shows, per run."""

    label: str
    state: str = "pending"  # pending | skipped | running | finished | budget | failed | not started
    run_id: str | None = None
    iteration: int | None = None
    iterations: int = 0
    best: float | None = None
    note: str = ""


@dataclass
class BatchResult:
    progress: list[Progress] = field(default_factory=list)

    @property
    def failed(self) -> list[Progress]:
        return [p for p in self.progress if p.state == "failed"]


def _refresh(store: Store, progress: list[Progress], batch: Batch) -> None:
    """Read each run's latest iteration and best score from the store (read-only, between the writers)."""
    try:
        with store.read() as con:
            rows = batch_progress(con, batch.name)
    except Exception:  # the store may not exist yet; the next refresh will see it
        return
    by_key = {key: (run_id, it, best) for key, run_id, it, best in rows}
    for p, run in zip(progress, batch.runs):
        key = run.found_as(by_key)
        if key in by_key:
            p.run_id, p.iteration, p.best = by_key[key]


def run_local(batch: Batch, store: Store, planned: list[PlannedRun], workers: int, log: Callable[[str], None],
              display: Callable[[list[Progress]], None], log_dir: Path, poll_s: float = 1.0) -> BatchResult:
    """Run the planned runs in at most ``workers`` processes; see the module docstring."""
    from pipeline.boundary.namespaces import die_with_parent

    progress = [Progress(p.run.label, iterations=p.run.config.iterations, run_id=p.run_id) for p in planned]
    queue = []
    for i, p in enumerate(planned):
        if p.action == "skip":
            progress[i].state = "skipped"
            log(f"skipped {p.run.label} (finished already, run {p.run_id})")
        else:
            queue.append(i)
    episode_workers = max(1, (os.cpu_count() or 1) // max(1, workers))
    running: dict[int, tuple[subprocess.Popen, Any]] = {}
    log_dir.mkdir(parents=True, exist_ok=True)
    try:
        _run_queue(queue, running, planned, progress, store, batch, workers, episode_workers, log, display, log_dir,
                   poll_s, die_with_parent)
    except KeyboardInterrupt as stop:
        # each worker marks its run interrupted and ends; wait for that, since a worker dies with this process
        # (PDEATHSIG) and would leave its run half marked. The stop is passed on to them: a terminal's Ctrl-C reached
        # them too (one process group), and one that heard it ignores it again, but a SIGTERM or SIGINT sent to this
        # process alone (`kill PID`, `kill -INT PID`) did not, and the batch waited out the wind-down's limit for
        # runs that went on playing
        sent = signal.SIGTERM if isinstance(stop, Terminated) else signal.SIGINT
        for proc, _ in running.values():
            try:
                proc.send_signal(sent)
            except ProcessLookupError:
                pass
        _wait_for_workers(running, WORKER_WIND_DOWN_S)
        raise
    _refresh(store, progress, batch)
    display(progress)
    return BatchResult(progress)


WORKER_WIND_DOWN_S = 60.0
"""How long a Ctrl-C'd batch waits for its workers to mark their runs interrupted before it ends (and they with it)."""
ABORT_WAIT_S = 5.0
"""How long a worker that outlived the wind-down has to write where it was stuck into its log (SIGABRT) before it
is killed."""


def _wait_for_workers(running: dict, limit_s: float) -> None:
    """Wait for the stopped workers to end, up to ``limit_s`` in all. One still running then is stuck (its run
    stays 'running'): it is sent SIGABRT, on which a run process writes every thread's stack into its log
    (``faulthandler``, enabled in ``pipeline/jobs/worker.py``) and ends, so that its log says where it was stuck; it
    had been sent SIGTERM, which a run that is winding down ignores, and nothing said why."""
    deadline = time.monotonic() + limit_s
    for proc, out in running.values():
        try:
            proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)
            try:
                proc.wait(timeout=ABORT_WAIT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
        except KeyboardInterrupt:  # a second press: stop waiting (the workers die with this process)
            return
        finally:
            out.close()


class RunLog:
    """A run process's output (stdout and stderr, one pipe), copied line by line into its log file by a thread, its
    last lines kept here too. The process wrote into the file itself, and the batch read the file's last line for
    why a run failed: on a full disk the file stayed empty or stopped mid-traceback, and the batch said
    ``failed pong seed=1: exit code 1`` (or a line of ``^^^^``) where the run had said which file it could not
    write. Now the line is the run's own whatever reached the disk, and the note says when the log lost lines."""

    KEPT_LINES = 20

    def __init__(self, path: Path):
        import collections

        self.path = path
        self.file = open(path, "ab")  # before the process starts: a log that cannot be opened starts none
        self.tail: collections.deque[bytes] = collections.deque(maxlen=self.KEPT_LINES)
        self.lost: OSError | None = None
        self.thread = None

    def follow(self, proc: subprocess.Popen) -> "RunLog":
        """Copy ``proc``'s output (its stdout, a pipe) from now on."""
        import threading

        self.thread = threading.Thread(target=self._copy, args=(proc.stdout,), name=f"run log {self.path.name}",
                                       daemon=True)
        self.thread.start()
        return self

    def _copy(self, pipe) -> None:
        for line in pipe:
            if line.strip():
                self.tail.append(line)
            try:
                self.file.write(line)
                self.file.flush()
            except OSError as exc:  # a full disk: the line is kept here, and the note says the log lost it
                self.lost = self.lost or exc
        pipe.close()

    def close(self, wait_s: float = 5.0) -> None:
        """Once the process ended: the rest of its output (a process it started and left may hold the pipe: not
        waited for past ``wait_s``), then the file."""
        if self.thread is not None:
            self.thread.join(wait_s)
        try:
            self.file.close()
        except OSError as exc:  # its last buffered bytes could not be written
            self.lost = self.lost or exc

    def why(self, code: int) -> str:
        """The note of a run that ended with exit code ``code``: its last line, and whether its log is short."""
        last = self.tail[-1].decode(errors="replace").strip()[:200] if self.tail else f"exit code {code}"
        if self.lost is not None:
            last += f" (its log {self.path} lost lines: {self.lost.strerror or self.lost})"
        return last


def _run_queue(queue, running, planned, progress, store, batch, workers, episode_workers, log, display, log_dir,
               poll_s, die_with_parent) -> None:
    """Start the queued runs as worker slots free up, until every run has ended (``run_local``'s loop)."""
    last_refresh = 0.0
    while queue or running:
        # a press Python swallowed (it landed in an at-fork hook as a run's process was started) stops the batch
        # all the same: the signals are ignored from then on, and it would go on starting the queued runs
        raise_if_stopped()
        while queue and len(running) < workers:
            i = queue.pop(0)
            item = planned[i]
            out = RunLog(log_dir / f"{item.run.key}.log")
            proc = subprocess.Popen(worker_command(store, item, batch, episode_workers), stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT,
                                    preexec_fn=functools.partial(die_with_parent, os.getpid()))
            running[i] = (proc, out.follow(proc))
            progress[i].state = "running"
            log(f"{item.action} {item.run.label}" + (f" (run {item.run_id})" if item.run_id else "")
                + f" [pid {proc.pid}]")
        for i, (proc, out) in list(running.items()):
            code = proc.poll()
            if code is None:
                continue
            out.close()
            del running[i]
            progress[i].state = {0: "finished", BUDGET_EXIT: "budget", INTERRUPTED_EXIT: "interrupted"}.get(code,
                                                                                                       "failed")
            if code != 0:
                progress[i].note = out.why(code)
            log(f"{progress[i].state} {planned[i].run.label}" + (f": {progress[i].note}" if progress[i].note else ""))
            if code == STORE_FULL_EXIT and queue:
                _stop_starting(queue, progress, planned[i].run.label, log)
        now = time.monotonic()
        if now - last_refresh >= poll_s:
            _refresh(store, progress, batch)
            display(progress)
            last_refresh = now
        time.sleep(0.2)


NOT_STARTED = "not started"
"""The state of a run a batch did not start: the store's disk was full (:data:`STORE_FULL_EXIT`)."""


def _stop_starting(queue: list[int], progress: list[Progress], label: str, log: Callable[[str], None]) -> None:
    """A run found the store's disk full: every queued run would start, fail at its first write and leave a line
    the same (each a process and its zygotes for nothing); they are not started, said once. The runs still going
    go on: one may end before it writes again."""
    for i in queue:
        progress[i].state, progress[i].note = NOT_STARTED, "the store's disk was full"
    log(f"not starting the {len(queue)} runs left: {label} found the store's disk full; free space and run the "
        "same command again (finished runs are skipped, the others resume or start)")
    queue.clear()


# --------------------------------------------------------------------------------------------- ray executor


def run_ray(batch: Batch, store: Store, planned: list[PlannedRun], address: str | None,
            log: Callable[[str], None], display: Callable[[list[Progress]], None]) -> BatchResult:
    """Run the planned runs as Ray tasks; the driver writes each returned run in one transaction."""
    import ray

    from store.bundle import export_run, import_run

    progress = [Progress(p.run.label, iterations=p.run.config.iterations, run_id=p.run_id) for p in planned]
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False,
                 runtime_env={"env_vars": {"PYTHONPATH": str(Path(__file__).resolve().parents[2])}})
    remote = ray.remote(num_cpus=1, max_retries=1)(run_remote)
    futures = {}
    try:
        for i, item in enumerate(planned):
            if item.action == "skip":
                progress[i].state = "skipped"
                log(f"skipped {item.run.label} (finished already, run {item.run_id})")
                continue
            previous = None
            if item.run_id:
                with store.read() as con:
                    previous = export_run(con, item.run_id)
            spec = {"config": asdict(item.run.config), "resume": item.run_id, "batch": batch.name,
                    "batch_key": item.run.key, "name": item.run.name, "episode_workers": 1}
            futures[remote.remote(spec, previous)] = i
            progress[i].state = "running"
            log(f"{item.action} {item.run.label} on ray")
        display(progress)
        pending = list(futures)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            i = futures[done[0]]
            try:
                bundle, status, error = ray.get(done[0])
            except Exception as exc:  # the task itself failed (a node died, an import error, ...)
                progress[i].state, progress[i].note = "failed", f"{type(exc).__name__}: {str(exc)[:200]}"
                log(f"failed {planned[i].run.label}: {progress[i].note}")
                display(progress)
                continue
            with store.write() as con:
                import_run(con, bundle)
            iterations = bundle["iterations"]
            progress[i].run_id = bundle["runs"].column("run_id")[0].as_py()
            if iterations.num_rows:
                progress[i].iteration = max(iterations.column("iteration").to_pylist())
                progress[i].best = max((b for b in iterations.column("best_score").to_pylist() if b is not None),
                                       default=None)
            progress[i].state = status if status in ("finished", "budget") else "failed"
            progress[i].note = error or ""
            log(f"{progress[i].state} {planned[i].run.label} (run {progress[i].run_id})")
            display(progress)
    finally:
        if started_here:
            ray.shutdown()
    return BatchResult(progress)
