"""``codearcade batch EXPERIMENTS.toml``: a matrix of optimization runs, headless, into one store.

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

Executors: ``local`` runs each run in its own process (``--workers`` at once; the processes die with the
batch, so a killed batch leaves nothing running and nothing locked), all writing the one store in short
transactions. ``ray`` sends each run to a Ray cluster as a task that works on a private store and returns the
run's rows (``store/bundle.py``); the driver alone writes them into the store, one transaction per run.
"""

from __future__ import annotations

import difflib
import functools
import hashlib
import itertools
import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from games import get_game
from games.base import one_life_setting
from pipeline.jobs.worker import BUDGET_EXIT, INTERRUPTED_EXIT, STORE_FULL_EXIT, run_remote
from pipeline.optimizer.config import OptimizeConfig, model_defaults, validate_config
from pipeline.optimizer.ensemble import split_model_flags
from pipeline.settings import declarations
from pipeline.stopping import Terminated
from store import Store
from store.readers import batch_progress, batch_runs
from store.runs import check_run_name
from store.writer import set_run_name

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
        # Ctrl-C reached the workers too (one process group): each marks its run interrupted and ends; wait for
        # that, since a worker dies with this process (PDEATHSIG) and would leave its run half marked. A SIGTERM
        # may have reached this process alone: the workers are told (one that heard it already ignores it)
        if isinstance(stop, Terminated):
            for proc, _ in running.values():
                try:
                    proc.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        _wait_for_workers(running, WORKER_WIND_DOWN_S)
        raise
    _refresh(store, progress, batch)
    display(progress)
    return BatchResult(progress)


WORKER_WIND_DOWN_S = 60.0
"""How long a Ctrl-C'd batch waits for its workers to mark their runs interrupted before it ends (and they with it)."""


def _wait_for_workers(running: dict, limit_s: float) -> None:
    deadline = time.monotonic() + limit_s
    for proc, out in running.values():
        try:
            proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.terminate()
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
