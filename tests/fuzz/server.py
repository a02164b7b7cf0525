"""The trusted side under fuzzing: a process that decodes what a policy process sent, one forked child per input,
and says what each cost.

Run as a script (``python tests/fuzz/server.py``) so that ``PYTHONPATH`` alone chooses the tree under test (a
worktree of an older commit, for the fuzzers' run against the code before a fix). It imports the trusted modules
once, then reads requests, one JSON line each on stdin: ``{"target", "path", "steps"}`` (``path``: a file holding
the bytes a policy process sent). For each, a forked child resets its peak RSS (``/proc/self/clear_refs``, 5),
decodes the bytes as the target's trusted code does, and reports one JSON line on stdout: ``outcome``
(``accepted``, ``refused``: the episode's recorded policy error or a refused message, ``error``: an exception in
the trusted process, ``killed``), ``detail``, ``growth_kb`` (peak RSS over the RSS before decoding, from
``getrusage``'s ``ru_maxrss``) and, for ``nodes``, ``store_bytes`` (what the store file grew by). The child's
address space is capped at :data:`CAP_BYTES`, so an attack that works ends that child (a MemoryError, an
``error``), not the machine.

Targets (each the code that receives the bytes in a run):

- ``frame``: ``wire.parse_arrow`` of a node stream (the frame decoder);
- ``nodes``: the parent's path: ``episodes.episode_from_worker`` (node rows read within bounds, every field
  checked), ``verify.checked_outcome`` (node values cleaned) and ``store.writer.EpisodeWriter`` into a real
  DuckDB store;
- ``rerun``: the game host's ``--rerun`` path: ``nodes.read_nodes`` then ``viewers.rerun_live``'s recorder
  logging the rows into an ``.rrd`` file;
- ``failure``: the host's reading of a policy process's failure frame (``channels.RemotePolicy._failure``).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import tempfile
import traceback
from types import SimpleNamespace

CAP_BYTES = 6 * 2**30
"""Address space of a child: far above any bound the oracle allows, far below what would hurt the machine."""


def _rss_kb() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _steps_table(n: int):
    import pyarrow as pa

    from tracing.steps import STEP_SCHEMA

    columns = []
    for field in STEP_SCHEMA:
        if field.name == "step":
            columns.append(pa.array(range(n), pa.int32()))
        elif field.name == "objects":
            columns.append(pa.array([[]] * n, field.type))
        else:
            columns.append(pa.array([0] * n).cast(field.type))
    return pa.table(columns, schema=STEP_SCHEMA)


class Targets:
    def __init__(self, policy_text: str, workdir: str):
        from pipeline.play.spec import EpisodeSpec
        from store.db import Store

        self.workdir = workdir
        self.spec = EpisodeSpec("fuzz.0.eval.0", "fuzz", "pong", policy_text, "v", max_steps=64, trace=True,
                                trace_lines=True)
        self.template = os.path.join(workdir, "template.duckdb")
        with Store(self.template).write():  # made and migrated once; each child writes into a copy
            pass

    def frame(self, payload: bytes, steps: int) -> tuple[str, str]:
        from pipeline.boundary import wire
        from tracing.capture import NODE_SCHEMA

        try:
            table = wire.parse_arrow(payload, NODE_SCHEMA, max_rows=2_000_000)
        except wire.BadMessage as exc:
            return "refused", str(exc)
        return "accepted", f"{table.num_rows} rows"

    def nodes(self, payload: bytes, steps: int) -> tuple[str, str]:
        from pipeline.boundary import wire
        from pipeline.play import episodes
        from pipeline.play.verify import checked_outcome
        from store.db import Store
        from store.writer import EpisodeWriter

        row = {"episode_id": self.spec.episode_id, "game": "pong", "started_at": None, "duration_s": 1.0,
               "env_s": 0.1, "policy_s": 0.1, "length": steps, "lives_lost": 0, "end_reason": "truncated",
               "error": None, "return": 0.0}
        try:
            outcome = episodes.episode_from_worker(self.spec, row, _steps_table(steps), payload)
        except wire.BadMessage as exc:
            return "refused", str(exc)
        outcome = checked_outcome(self.spec, outcome)
        path = os.path.join(self.workdir, f"store-{os.getpid()}.duckdb")
        shutil.copy(self.template, path)
        before = os.path.getsize(path)
        with EpisodeWriter(Store(path), every_s=3600) as writer:
            writer.add(outcome.episode, outcome.steps, outcome.nodes)
        self.store_bytes = os.path.getsize(path) - before
        end = outcome.episode["end_reason"]
        if end == "policy_error":
            return "refused", outcome.episode["error"]
        return "accepted", f"{end}, {0 if outcome.nodes is None else outcome.nodes.num_rows} node rows stored"

    def rerun(self, payload: bytes, steps: int) -> tuple[str, str]:
        from pipeline.boundary.nodes import MalformedTrace, read_nodes
        from tracing.steps import StepLog
        from viewers.rerun_live import finish_recorder, open_recorder

        spec = self.spec
        spec.rerun, spec.rerun_frames_every = self.workdir, 0
        log = StepLog()
        recorder = open_recorder(spec, SimpleNamespace(unwrapped=SimpleNamespace(ale=None)), log)  # no screen
        try:
            table = read_nodes(payload, spec, steps, 1.0)
        except MalformedTrace as exc:
            return "refused", str(exc)
        finally:
            spec.rerun = None
        finish_recorder(recorder, {"episode_id": spec.episode_id}, table)
        return "accepted", f"{table.num_rows} rows recorded"

    def failure(self, payload: bytes, steps: int) -> tuple[str, str]:
        from pipeline.play.channels import RemotePolicy

        failed = RemotePolicy._failure(None, payload, "at this step")
        outcome = "refused" if failed.end_reason == "crashed" else "accepted"
        return outcome, f"{failed.end_reason}: {len(failed.error)} characters"


def child(targets: Targets, request: dict) -> dict:
    with open(request["path"], "rb") as f:
        payload = f.read()
    resource.setrlimit(resource.RLIMIT_AS, (CAP_BYTES, CAP_BYTES))
    _reset_peak()
    before = _rss_kb()
    targets.store_bytes = None
    try:
        outcome, detail = getattr(targets, request["target"])(payload, request["steps"])
    except BaseException as exc:  # noqa: BLE001 - what the oracle looks for
        outcome, detail = "error", f"{type(exc).__name__}: {exc}"[:500] + "\n" + traceback.format_exc()[-1500:]
    return {"outcome": outcome, "detail": str(detail)[:2000], "growth_kb": _rss_kb() - before,
            "store_bytes": targets.store_bytes}


def main() -> None:
    config = json.loads(sys.stdin.readline())
    workdir = tempfile.mkdtemp(prefix="fuzz-")
    targets = Targets(config["policy_text"], workdir)
    # every target warmed once on an honest input (imports, first calls, caches), so that a child pays only for
    # its input; Rerun is imported, not started: a child forked after its threads start could hang on their locks
    import viewers.rerun_live  # noqa: F401

    with open(config["honest"], "rb") as f:
        honest = f.read()
    for target in ("frame", "nodes", "failure"):
        getattr(targets, target)(honest, config["honest_steps"])
    for name in os.listdir(workdir):
        if name.startswith("store-"):
            os.unlink(os.path.join(workdir, name))
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        out_path = os.path.join(workdir, "answer.json")
        pid = os.fork()
        if pid == 0:
            try:
                answer = child(targets, request)
                with open(out_path, "w") as f:
                    json.dump(answer, f)
            finally:
                os._exit(0)
        _, status = os.waitpid(pid, 0)
        if os.WIFEXITED(status) and os.path.exists(out_path):
            with open(out_path) as f:
                answer = json.load(f)
            os.unlink(out_path)
        else:
            answer = {"outcome": "killed", "detail": f"wait status {status}", "growth_kb": None,
                      "store_bytes": None}
        for name in os.listdir(workdir):
            if name.startswith("store-") or name.endswith(".rrd"):
                os.unlink(os.path.join(workdir, name))
        print(json.dumps(answer), flush=True)
    shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
