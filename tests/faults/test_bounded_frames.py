"""Nothing the policy process sends is believed (issue #31): frames are bounded before they are parsed, and every
field of a node row is checked, asserted by effect on ``codearcade eval`` and ``optimize`` in processes of their own.

The policy reaches its own process's objects (``typing.sys.modules``: ``pipeline.boundary.wire``, the
``PolicySide`` and its channel) and sends, at the end of its episode or at a step:

- a decompression bomb: node rows as a zstd-compressed Arrow stream, a few KB that inflate to 768 MiB (the parent
  peaked at 3.4 GB, the game host with ``--rerun DIR`` at 6.3 GB, for 1 GiB strings), also for an episode that is
  not traced;
- node rows whose ``output`` is not JSON (it reached the store's JSON column: the run failed, 0 episodes stored);
- 10,000 forged node rows for a 5-step episode (step 2^31-1, invented functions, parents, durations: the store
  grew by 156 MB);
- a 300 MiB failure frame (the host decoded it: 2.8 GB).

Each must leave the parent and the game host under 600 MB (peaks measured: the parent's own ``VmHWM``, the
hosts' sampled from ``/proc``), the episode a recorded policy error (never a crash of a trusted
process, never a failed run), and the store without its rows.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from store import Store
from tests.conftest import ROOT, json_reply, pong_policy
from tests.faults.test_read_slices import PEAK

LIMIT_MB = 600

# A traced episode's recorder may be swapped; an untraced one is given a recorder, so that a node frame is sent.
SEND_NODES = """
import typing
mods = typing.sys.modules
wire = mods['pipeline.boundary.wire']
if not getattr(wire, 'forged', False):
    gc = mods['importlib'].import_module('gc')
    pa = mods['pyarrow']
    real_frame = wire.arrow_frame
    for side in gc.get_objects():
        if type(side).__name__ == 'PolicySide' and side.recorder is None:
            side.recorder = mods['tracing.capture'].NodeRecorder()
    FORGE
    wire.arrow_frame = forged
    wire.forged = True
return 0
"""

BOMB = """
def forged(table, pa=pa, wire=wire):
    n = 2**28  # 256 MiB of 'x', three columns of it: a few KB as zstd
    data = pa.py_buffer(b'x' * n)
    text = pa.StringArray.from_buffers(1, pa.array([0, n], pa.int32()).buffers()[1], data)
    columns = {f.name: pa.nulls(1, f.type) for f in table.schema}
    columns.update(step=pa.array([0], pa.int32()), call_index=pa.array([0], pa.int16()),
                   function=pa.array(['select_action']), trainable=pa.array([True]), inputs=text, output=text,
                   exc_message=text, duration_us=pa.array([1], pa.int64()),
                   parents=pa.array([[]], pa.list_(pa.int16())))
    bomb = pa.table(columns, schema=table.schema)
    sink = pa.BufferOutputStream()
    options = pa.ipc.IpcWriteOptions(compression='zstd', use_threads=False)  # no threads in the sandbox
    with pa.ipc.new_stream(sink, bomb.schema, options=options) as writer:
        writer.write_table(bomb)
    payload = sink.getvalue().to_pybytes()
    return wire.HEADER.pack(b'A', len(payload)) + payload
"""

NOT_JSON = """
def forged(table, pa=pa, real_frame=real_frame):
    column = table.schema.get_field_index('output')
    return real_frame(table.set_column(column, 'output', pa.array(['{not json'] * table.num_rows, pa.string())))
"""

FORGED_ROWS = """
def forged(table, pa=pa, real_frame=real_frame):
    n = 10_000
    columns = {f.name: pa.nulls(n, f.type) for f in table.schema}
    columns.update(step=pa.array([2**31 - 1] * n, pa.int32()), call_index=pa.array([i % 32_000 for i in range(n)],
                   pa.int16()), function=pa.array([f'invented_{i % 2_001}' for i in range(n)]),
                   trainable=pa.array([True] * n), inputs=pa.array(['{"x": 1}'] * n),  # within the budget
                   output=pa.array(['1'] * n), duration_us=pa.array([2**62] * n, pa.int64()),
                   parents=pa.array([[32767]] * n, pa.list_(pa.int16())))
    return real_frame(pa.concat_tables([table, pa.table(columns, schema=table.schema)]))
"""

FLOOD = """
import typing
mods = typing.sys.modules
gc = mods['importlib'].import_module('gc')
for side in gc.get_objects():
    if type(side).__name__ == 'PolicySide':
        channel = side.channel
        text = b'{"kind":"failed","end_reason":"policy_error","error":"' + b'x' * (300 * 2**20) + b'"}'
        channel.write_all(mods['struct'].pack('>cI', b'J', len(text)) + text)
return 0
"""


def attack(forge: str) -> str:
    lines = "\n".join("    " + line for line in forge.strip("\n").splitlines())
    return pong_policy(SEND_NODES.replace("    FORGE", lines), prelude="")


def attack_method(forge: str) -> str:
    """The attack as the ``select_action`` of an LLM's reply."""
    body = SEND_NODES.replace("    FORGE", "\n".join("    " + line for line in forge.strip("\n").splitlines()))
    return "def select_action(self, predicted_ball_y, obs):\n" + "\n".join(
        "    " + line for line in body.strip("\n").splitlines()) + "\n"


DRIVER = PEAK + """
import sys
from pipeline.cli import main
try:
    code = main(sys.argv[1:])
finally:
    print('PEAK_KB', peak_kb(), file=sys.stderr)  # its own peak (ru_maxrss read 631 MB: the pytest worker's)
sys.exit(code)
"""


class HostPeaks:
    """The highest ``VmHWM`` of the game hosts (forks of the ``game`` zygote) under one process, sampled from
    ``/proc`` while it runs (a host stays until its run ends: its high-water mark is read before it goes)."""

    def __init__(self) -> None:
        self.root: int | None = None
        self.peak_kb = 0
        self.seen = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _scan(self) -> None:
        parents, marks = {}, {}
        for name in os.listdir("/proc"):
            if not name.isdigit():
                continue
            try:
                status = Path(f"/proc/{name}/status").read_text()
                cmdline = Path(f"/proc/{name}/cmdline").read_bytes()
            except OSError:
                continue
            fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
            parents[int(name)] = int(fields.get("PPid", "0"))
            if b"pipeline.boundary.zygote\x00game" in cmdline and "VmHWM" in fields:
                marks[int(name)] = int(fields["VmHWM"].split()[0])
        for pid, mark in marks.items():
            up = pid
            while up > 1 and up != self.root:
                up = parents.get(up, 0)
            if up == self.root:
                self.seen += 1
                self.peak_kb = max(self.peak_kb, mark)

    def _sample(self) -> None:
        while not self._stop.is_set():
            self._scan()
            time.sleep(0.02)

    def start(self, root: int) -> None:
        self.root = root
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def run_measured(args: list[str], cwd: Path = ROOT, env: dict | None = None) -> tuple[int, str, str, float, float]:
    """``codearcade ARGS`` in a process of its own: (exit code, stdout, stderr, its peak RSS in MB, the highest peak
    of its game hosts in MB)."""
    peaks = HostPeaks()
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    peaks.start(proc.pid)
    try:
        out, err = proc.communicate(timeout=600)
    finally:
        peaks.stop()
    parent_kb = [int(line.split()[1]) for line in err.splitlines() if line.startswith("PEAK_KB")]
    assert parent_kb, err[-3000:]
    assert peaks.seen, "no game host was sampled"
    return proc.returncode, out, err, parent_kb[-1] / 1024, peaks.peak_kb / 1024


def _eval(path: Path, store: Store, *extra: str):
    return run_measured(["eval", str(path), "--max-steps", "5", "--store", str(store.path), "--json", *extra])


@pytest.fixture(scope="module")
def honest_store(tmp_path_factory) -> int:
    """The store's size after an honest traced 5-step episode of the same policy text but its attack."""
    path = tmp_path_factory.mktemp("honest") / "honest.py"
    path.write_text(pong_policy("return 0"))
    store = Store(path.parent / "honest.duckdb")
    code, out, err, _, _ = _eval(path, store, "--trace")
    assert code == 0, err[-2000:]
    return store.path.stat().st_size


def _episode(store: Store) -> dict:
    rows = store.query("SELECT end_reason, error, length FROM episodes")
    assert len(rows) == 1, rows
    return dict(zip(("end_reason", "error", "length"), rows[0]))


@pytest.mark.slow
@pytest.mark.parametrize("flags", [["--trace"], ["--trace", "--rerun", "RRD"], ["--rerun", "RRD"]],
                         ids=["traced", "traced, --rerun DIR", "untraced, --rerun DIR"])
def test_a_decompression_bomb_is_refused_unread(flags, store, write_policy, tmp_path):
    path = write_policy(attack(BOMB))
    flags = [str(tmp_path / "rrd") if flag == "RRD" else flag for flag in flags]
    code, out, err, parent_mb, host_mb = _eval(path, store, *flags)
    assert code == 1 and "Traceback" not in err, err[-3000:]  # as for any episode its policy failed
    assert parent_mb < LIMIT_MB and host_mb < LIMIT_MB, (parent_mb, host_mb)
    episode = _episode(store)
    assert episode["end_reason"] == "policy_error" and episode["error"].startswith("malformed trace"), episode
    reason = "not traced" if "--trace" not in flags else "compressed"
    assert reason in episode["error"], episode
    assert store.query("SELECT count(*) FROM nodes") == [(0,)]
    assert json.loads(out)["episodes"][0]["end_reason"] == "policy_error"


@pytest.mark.slow
@pytest.mark.parametrize("forge, reason", [(NOT_JSON, "is not JSON"), (FORGED_ROWS, "more than 1,280 rows")],
                         ids=["output not JSON", "10,000 forged rows"])
def test_forged_node_rows_are_the_episodes_error_and_never_stored(forge, reason, store, write_policy, honest_store):
    path = write_policy(attack(forge))
    code, out, err, parent_mb, host_mb = _eval(path, store, "--trace")
    assert code == 1 and "Traceback" not in err, err[-3000:]  # as for any episode its policy failed
    episode = _episode(store)
    assert episode["end_reason"] == "policy_error" and episode["error"].startswith("malformed trace"), episode
    assert reason in episode["error"] and episode["length"] == 5, episode
    assert store.query("SELECT count(*) FROM nodes") == [(0,)]
    assert store.query("SELECT count(*) FROM steps") == [(5,)]  # the host's steps are kept
    assert store.path.stat().st_size <= honest_store, (store.path.stat().st_size, honest_store)
    assert store.query("SELECT status FROM runs") == [("finished",)]


@pytest.mark.slow
def test_a_300_mib_failure_frame_is_refused_at_its_header(store, write_policy):
    path = write_policy(pong_policy(FLOOD, prelude=""))
    code, out, err, parent_mb, host_mb = _eval(path, store, "--call-time-limit", "30")  # 600 MB to write first
    assert code == 1 and "Traceback" not in err, err[-3000:]
    assert host_mb < LIMIT_MB and parent_mb < LIMIT_MB, (parent_mb, host_mb)
    episode = _episode(store)
    assert episode["end_reason"] == "crashed" and "over the limit" in episode["error"], episode
    assert len(episode["error"]) < 300


def optimize_with_forged_candidate(forge, store, scripted, tmp_path):
    """`codearcade optimize --rerun` whose one candidate (the scripted model's reply) sends ``forge`` in its traced
    rollout, with the peak RSS of the parent and the game hosts: (exit code, stdout, stderr, parent MB, host MB)."""
    model = scripted([json_reply({"select_action": attack_method(forge)})])
    return run_measured(
        ["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base, "--iterations", "1",
         "--rollout-steps", "5", "--eval-max-steps", "5", "--workers", "1", "--store", str(store.path), "--json",
         "--rerun", str(tmp_path / "rrd"), "--audit-episodes", "0"], cwd=tmp_path,  # the audit plays no candidate
        env={"LITELLM_LOCAL_MODEL_COST_MAP": "True", "OPENAI_API_KEY": "sk-test"})


@pytest.mark.slow
@pytest.mark.parametrize("forge", [NOT_JSON, BOMB], ids=["output not JSON", "decompression bomb"])
def test_optimize_goes_on_past_a_candidates_forged_trace(forge, store, scripted, tmp_path):
    """A candidate (an LLM's reply) whose traced rollout sends forged node rows: that rollout is its policy error,
    the run finishes, its other episodes are stored, and the parent and hosts stay small."""
    code, out, err, parent_mb, host_mb = optimize_with_forged_candidate(forge, store, scripted, tmp_path)
    assert code == 0 and json.loads(out)["status"] == "finished", err[-3000:]
    assert parent_mb < LIMIT_MB and host_mb < LIMIT_MB, (parent_mb, host_mb)
    refused = store.query("SELECT e.episode_id, e.error FROM episodes e WHERE e.traced AND e.iteration = 1")
    assert refused and all(error.startswith("malformed trace") for _, error in refused), refused
    assert store.query("SELECT count(*) FROM nodes WHERE episode_id IN (SELECT episode_id FROM episodes "
                       "WHERE iteration = 1)") == [(0,)]
    assert store.query("SELECT count(*) FROM episodes WHERE iteration = 0")[0][0] >= 1  # the starter's, kept
