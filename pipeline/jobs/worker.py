"""One run of a batch: ``python -m pipeline.jobs.worker SPEC_JSON`` (local executor) or a Ray task.

The spec carries the run's :class:`~pipeline.optimizer.config.OptimizeConfig`, the batch name and run key (stored in
the run's config so a later ``codearcade batch`` finds it), the run's label (``runs.name``) and the run id to
resume, if any. Locally the process works on the shared store directly; on Ray, :func:`run_remote` works on a
private store seeded with the run's earlier rows and returns all of them for the driver to write.
"""

from __future__ import annotations

import sys

from pipeline.stopping import end_process, quiet_swallowed_interrupts, stop_on_signals

INTERRUPTED_EXIT = 130
"""Exit code of a batch run process stopped by a Ctrl-C (its run is interrupted, resumable)."""


if __name__ == "__main__":
    import faulthandler

    # a run that a stopped batch found stuck past its wind-down is sent SIGABRT: every thread's stack goes into
    # the run's log (its stderr), which then says where it was stuck (pipeline/jobs/batch.py); a crash says so too
    faulthandler.enable()
    # a press that lands in an exit handler or a finalizer as the run ends is the one it answers with its line
    # `interrupted`: no "Exception ignored" and traceback in the run's log
    quiet_swallowed_interrupts()
    # a Ctrl-C, or SIGTERM (to the batch's process group, or from the batch itself when a SIGTERM stopped it
    # alone), once: the run is marked interrupted, and another while it winds down is ignored
    stop_on_signals()

try:  # a Ctrl-C to the batch's process group reaches its runs too, also while they import (the standard
    # library's modules too: a press landed in `import tempfile`, and the run's log held a traceback)
    import json
    import tempfile
    from contextlib import contextmanager
    from pathlib import Path
    from typing import Any

    from pipeline.boundary.preload import lists_are_not_dataframes
    from pipeline.boundary.zygotes import keep_hosts
    from pipeline.llm.client import open_client
    from pipeline.optimizer.config import OptimizeConfig, fit_to_model
    from pipeline.optimizer.loop import OptimizeResult, new_run, optimize
    from store import Store
    from store.db import StoreError, StoreFull
    from store.writer import set_run_name
    from viewers.safe_text import make_python_reports_terminal_safe, terminal_text

    if __name__ == "__main__":  # the run's log is read with cat and tail: a traceback or warning Python prints
        # there itself may quote a reply or a stored text, so it is made safe and cut short too
        make_python_reports_terminal_safe()
        lists_are_not_dataframes()
        quiet_swallowed_interrupts()  # again, over the terminal-safe reports
except KeyboardInterrupt:
    if __name__ != "__main__":
        raise
    sys.stderr.write("interrupted\n")  # the run's log says so in a line, as the batch's terminal does
    raise SystemExit(INTERRUPTED_EXIT) from None

BUDGET_EXIT = 3
"""Exit code of a batch run process whose run stopped at its budget (not a failure)."""
STORE_FULL_EXIT = 4
"""Exit code of a batch run process that found the store's disk full: the batch starts no more runs, which would
each fail alike."""


def _say(line: str) -> None:
    """One line of the run's log (its stdout, a file the batch's log quotes): terminal-safe, as a line may quote
    a rejected candidate's exception (``viewers/safe_text.py``)."""
    print(terminal_text(line), flush=True)


@contextmanager
def _waiting(iteration: int, model: str):
    _say(f"iteration {iteration}: waiting for {model}")
    yield


def _run(spec: dict[str, Any], store: Store) -> OptimizeResult:
    with keep_hosts():  # the run's assessments reuse their game hosts; they exit when it is done
        return _optimize(spec, store)


def _optimize(spec: dict[str, Any], store: Store) -> OptimizeResult:
    config = OptimizeConfig(**spec["config"])
    config.workers = spec.get("episode_workers", config.workers)
    client, server, cap = open_client(config.model, config.api_base, config.temperature, config.max_tokens,
                                      config.seed, models=config.models, notice=_say)
    fit_to_model(config, cap)
    try:
        with new_run(store, client) as made:
            run_id = spec.get("resume") or made.start(config, client.label, extra={
                "batch": spec["batch"], "batch_key": spec["batch_key"]})
            if spec.get("name"):  # the entry's label (pipeline/jobs/experiments.py), given again as the run resumes
                with store.write() as con:
                    set_run_name(con, run_id, spec["name"])
            return optimize(config, store, client, resume=run_id, waiting=_waiting, log=_say,
                            on_iteration=lambda item: _say(f"iteration {item.iteration}: score "
                                                           f"{_shown(item.score)} best {_shown(item.best_score)} "
                                                           f"{item.update_status}"))
    finally:
        if server is not None:
            server.stop()


def run_remote(spec: dict[str, Any], previous: dict | None):
    """The Ray task: (the run's rows as a bundle, status, error)."""
    from store.bundle import export_run, import_run

    with tempfile.TemporaryDirectory(prefix="codearcade-ray-") as tmp:
        store = Store(Path(tmp) / "run.duckdb")
        if previous is not None:
            with store.write() as con:
                import_run(con, previous)
        result = _run(spec, store)
        with store.read() as con:
            return export_run(con, result.run_id), result.status, result.error


def _shown(score: float | None) -> str:
    """A score in a log line; None is a forfeit (``store/scores.py``)."""
    return f"{score:g}" if score is not None else "forfeit"


def main(argv: list[str] | None = None) -> int:
    spec = json.loads((argv if argv is not None else sys.argv[1:])[0])
    result = _run(spec, Store(spec["store"]))
    _say(f"run {result.run_id} {result.status}" + (f": {result.error}" if result.error else ""))
    return {"finished": 0, "budget": BUDGET_EXIT}.get(result.status, 1)


if __name__ == "__main__":  # each end is end_process's: the batch waits for this process's end
    try:
        code = main()
        end_process(code)
    except KeyboardInterrupt:  # the run is marked interrupted already (the loop did); a line, not a traceback
        _say("interrupted")
        end_process(INTERRUPTED_EXIT)
    except StoreError as exc:  # the store says what happened and what to do: its line, not a traceback
        _say(f"error: {exc}")
        end_process(STORE_FULL_EXIT if isinstance(exc, StoreFull) else 1)
    except Exception as exc:
        from pipeline.stopping import stop_pending
        from store.db import is_ctrl_c

        # DuckDB's word for a press that reached it outside the store's conversion; or the error of something the
        # press itself broke while it was held (a zygote it killed as the run started: "did not start")
        if not (is_ctrl_c(exc) or stop_pending()):
            raise
        _say("interrupted")
        end_process(INTERRUPTED_EXIT)
