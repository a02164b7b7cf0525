"""Readers read slices (issue 38, item 2): what reads policy-produced node values back from the store decodes at
most what it shows.

The attack ("parsed on read"): valid node values ``[{},{},…]`` of 16,000 characters in 2,000 rows. Decoded whole
for the prompt's context, they cost ~24 bytes of Python objects per character stored (an empty dict for every
three), ~2 GB for one rollout, although the prompt shows 300 characters of a value. The store here is forged
through the real writer (``store/writer.write_episode``) over a real run's training rollout, so that the test does
not depend on what the boundary lets through; each reader then runs in a process of its own, and its peak RSS
(``VmHWM``) is measured against a store holding the honest rollout. The prompt of an honest run must not
change: the bounded reader's prompt is compared, character for character, with the prompt built from values
decoded whole, over the real rollout and over a sweep of honest values written by ``tracing/capture.to_json``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow as pa
import pytest

from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer import context
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.context import read_context
from pipeline.optimizer.loop import load_state, run_loop, start_run
from pipeline.optimizer.prompt import build_prompt
from store import Store
from store.held_values import JsonHead
from store.readers import step_nodes
from store.writer import write_episode
from tracing.capture import to_json

# each reader runs in a process of its own on a forged store, its peak memory read: not the quick lane's
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
ROWS, CHARS = 2_000, 16_000
FLOOD = "[" + ",".join(["{}"] * ((CHARS - 1) // 3)) + "]"
"""The attack's value: 16,000 characters of valid JSON that decode to 5,333 dicts."""
PEAK_BOUND_MB = 600
"""The issue's bound for any trusted process; the unbounded reader peaked far above it (docs/sandbox.md)."""
GROWTH_BOUND_MB = 150
"""What the forged rows may add to the reader's peak over the honest store's: 2,000 rows of kilobytes each."""


def _build(path: Path) -> str:
    """A store with iteration 0 of a Pong run (the starter's traced rollout); its run id."""
    store = Store(path)
    config = OptimizeConfig(game="pong", iterations=0, eval_max_steps=120, audit_episodes=0, rng_key="read-slices")
    run_id = start_run(config, store, "openai/gpt-4o")
    run_loop(store, load_state(store, run_id), None)
    return run_id


def _replace_nodes(path: Path, run_id: str, rows: list[dict]) -> None:
    """Write the run's training rollout again through the store's writer, with ``rows`` as its node calls."""
    store = Store(path)
    with store.write() as con:
        (episode_id,) = con.execute("SELECT train_episode_id FROM candidates WHERE run_id = ? AND iteration = 0",
                                    [run_id]).fetchall()[0]
        cursor = con.execute("SELECT * FROM episodes WHERE episode_id = ?", [episode_id])
        episode = dict(zip([d[0] for d in cursor.description], cursor.fetchall()[0]))
        steps = con.sql("SELECT * EXCLUDE (episode_id) FROM steps WHERE episode_id = $1 ORDER BY step",
                        params=[episode_id]).to_arrow_table()
        nodes = pa.table({
            "step": pa.array([r["step"] for r in rows], pa.int32()),
            "call_index": pa.array([r["call_index"] for r in rows], pa.int16()),
            "function": [r.get("function", "predict") for r in rows],
            "trainable": [True] * len(rows),
            "inputs": [r["inputs"] for r in rows],
            "output": pa.array([r["output"] for r in rows], pa.string()),
            **({"exc_type": [r.get("exc_type") for r in rows], "exc_message": [r.get("exc_message") for r in rows]}
               if any("exc_type" in r for r in rows) else {}),
        })
        write_episode(con, episode, steps, nodes, replace=True)


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """(honest store, forged store, run id): the same run, the forged one's rollout with the attack's rows."""
    folder = tmp_path_factory.mktemp("slices")
    honest = folder / "honest.duckdb"
    run_id = _build(honest)
    forged = folder / "forged.duckdb"
    shutil.copy(honest, forged)
    inputs = '{"obs":{"$ref":"obs"},"seen":' + FLOOD + "}"
    steps = 120
    _replace_nodes(forged, run_id, [{"step": i % steps, "call_index": i // steps, "inputs": inputs, "output": FLOOD}
                                    for i in range(ROWS)])
    return honest, forged, run_id


PEAK = """
def peak_kb():
    # VmHWM: the peak RSS of this process's own memory since exec (ru_maxrss would start from the pytest process's
    # size at fork, which a child inherits on Linux)
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
"""

PROMPT_READER = PEAK + """
import json, sys
from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer import context
from pipeline.optimizer.context import read_context
from pipeline.optimizer.prompt import build_prompt
from store import Store
with Store(sys.argv[1]).read() as con:
    ctx = read_context(con, sys.argv[2], 1, memory=5)
prompt = build_prompt(ctx, 8_000, TokenCounter("openai/gpt-4o"))
print(json.dumps({"peak_kb": peak_kb(), "tokens": prompt.tokens,
                  "text": prompt.messages[1]["content"]}))
"""


def _run(script: str, *args: str) -> dict:
    env = {**os.environ, "LITELLM_LOCAL_MODEL_COST_MAP": "True", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, env=env, cwd=ROOT, check=False,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


def test_the_prompt_reads_a_slice_of_a_flooded_rollout(stores):
    """2,000 node rows of 16,000-character ``[{},{},…]`` values: the prompt is built, shows 300 characters of
    each value it shows, and the reader's peak RSS stays under the bound, near the honest store's."""
    honest_path, forged_path, run_id = stores
    honest = _run(PROMPT_READER, str(honest_path), run_id)
    forged = _run(PROMPT_READER, str(forged_path), run_id)
    peak, base = forged["peak_kb"] / 1024, honest["peak_kb"] / 1024
    assert peak < PEAK_BOUND_MB, f"the prompt's reader peaked at {peak:,.0f} MB ({base:,.0f} MB on the honest store)"
    assert peak - base < GROWTH_BOUND_MB, f"{peak:,.0f} MB with the forged rows, {base:,.0f} MB without"
    others = forged["text"].split("#Others")[1].split("#Outputs")[0]
    assert "predict(obs, seen=[{},{}," in others and "-> [{},{}," in others
    assert max(len(part) for line in others.splitlines() for part in line.split(" | ")) < 1_000
    assert forged["tokens"] <= 8_000


def test_an_honest_rollout_gives_the_same_prompt(stores):
    """The real rollout of the run: its prompt from the bounded reader is the prompt from values decoded whole."""
    honest_path, _, run_id = stores
    assert _prompts_agree(Store(honest_path), run_id) > 0


def _prompts_agree(store: Store, run_id: str) -> int:
    """Build the prompt at several budgets from the bounded context and from one whose node values are decoded
    whole; assert they are the same text; return how many of the bounded values were left undecoded."""
    counter = TokenCounter("openai/gpt-4o")
    context._ROLLOUTS.clear()  # the stores share the run's episode ids: read each one's rows
    with store.read() as con:
        bounded = read_context(con, run_id, 1, memory=5)
        whole = step_nodes(con, bounded.train_episode["episode_id"])
    full = dataclasses.replace(bounded, train_nodes=whole)
    heads = sum(isinstance(v, JsonHead) for n in bounded.train_nodes
                for v in [n["output"], *(n["inputs"].values() if isinstance(n["inputs"], dict) else [n["inputs"]])])
    for budget in (4_000, 16_000, 200_000):
        a, b = build_prompt(bounded, budget, counter), build_prompt(full, budget, counter)
        assert a.messages == b.messages and a.steps_shown == b.steps_shown, budget
    return heads + 1


_TEXT = "".join(random.Random(7).choices([chr(c) for c in (*range(32, 127), 0xE9, 0x4E2D, 0x1F600, 10, 34, 92)],
                                          k=100_000))
"""Text with escapes, quotes and astral characters, of which :func:`_honest_value` takes slices."""


def _honest_value(rng: random.Random, depth: int = 0):
    """A value a policy's method could return or take: numbers of every size, text with escapes and astral
    characters, lists of objects (Breakout's bricks), nested containers."""
    kind = rng.randrange(9 if depth < 3 else 5)
    if kind == 0:
        return rng.randrange(-10 ** rng.randrange(1, 400), 10 ** rng.randrange(1, 400))
    if kind == 1:
        return rng.random() * 10 ** rng.randrange(-30, 30)
    if kind == 2:  # a slice of random text at a random place: drawn a character at a time, it was 80% of the test
        length = rng.choice([3, 40, 290, 310, 2_000])
        start = rng.randrange(len(_TEXT) - length)
        return _TEXT[start:start + length]
    if kind == 3:
        return rng.choice([True, False, None, float("nan")])
    if kind == 4:
        return rng.randrange(300)
    if kind in (5, 6):
        return [_honest_value(rng, depth + 1) for _ in range(rng.choice([0, 2, 12, 120]))]
    return {rng.choice(["x", "y", "w", "a\"b", "é", "😀", f"k{i}"]): _honest_value(rng, depth + 1) for i in range(6)}


def test_a_sweep_of_honest_values_gives_the_same_prompt(stores, tmp_path):
    """Values as the policy's process writes them (``to_json``), short and long, in inputs and outputs: the
    prompt from the bounded reader is the same text, at every budget, as from values decoded whole."""
    honest_path, _, run_id = stores
    path = tmp_path / "sweep.duckdb"
    shutil.copy(honest_path, path)
    rng = random.Random(38)
    rows = []
    for step in range(120):
        for call in range(3):
            inputs = {"obs": {"$ref": "obs"}} if rng.random() < 0.7 else {}
            for k in range(rng.choice([0, 1, 3, 8])):
                inputs[rng.choice(["ball", "bricks", "paddle", f"p{k}"])] = _honest_value(rng)
            rows.append({"step": step, "call_index": call, "function": rng.choice(["predict", "aim"]),
                         "inputs": to_json(inputs), "output": to_json(_honest_value(rng))})
    _replace_nodes(path, run_id, rows)
    assert _prompts_agree(Store(path), run_id) > 50  # many values long enough to be left undecoded


VIEW_READER = PEAK + """
import json, sys
from pipeline.cli import main
code = main(["view", sys.argv[2], "--iteration", "0", "--store", sys.argv[1], "--save", sys.argv[3]])
print(json.dumps({"peak_kb": peak_kb(), "code": code}))
"""


def test_a_rebuilt_recording_reads_a_slice_of_a_flooded_rollout(stores, tmp_path):
    """``codearcade view RUN --iteration 0 --save``: the training rollout's recording is rebuilt from the store,
    each node value cut to a line of text (``store/showing.episode_tables``): the same peak RSS give or take
    DuckDB's cache of the rows it read, with the forged rows or without."""
    honest_path, forged_path, run_id = stores
    honest = _run(VIEW_READER, str(honest_path), run_id, str(tmp_path / "honest.rrd"))
    forged = _run(VIEW_READER, str(forged_path), run_id, str(tmp_path / "forged.rrd"))
    assert honest["code"] == forged["code"] == 0 and (tmp_path / "forged.rrd").stat().st_size > 0
    peak, base = forged["peak_kb"] / 1024, honest["peak_kb"] / 1024
    assert peak < PEAK_BOUND_MB and peak - base < 100, f"{peak:,.0f} MB with the forged rows, {base:,.0f} MB without"


EXCEPTION_ROWS, EXCEPTION_CHARS = 32_000, 1_900
"""Caught exceptions of a policy that raises in a helper sixteen times a step, each message near the 2,000
characters a stored message keeps: 61 MB of messages, within an episode's node budget."""


def test_a_rebuilt_recording_logs_a_flood_of_exceptions_a_slice_at_a_time(stores, tmp_path):
    """A rollout whose calls are mostly caught exceptions: the recording logged all of an episode's exception
    messages in one column (a reviewer's Freeway policy: 871 MB against 359 honest); they go a slice of rows at a
    time now, like the outputs."""
    honest_path, _, run_id = stores
    flooded = tmp_path / "exceptions.duckdb"
    shutil.copy(honest_path, flooded)
    steps = 120
    message = ("m " * EXCEPTION_CHARS)[:EXCEPTION_CHARS]
    _replace_nodes(flooded, run_id, [{"step": i % steps, "call_index": i // steps, "inputs": "{}", "output": None,
                                      "exc_type": "ValueError", "exc_message": f"{i} {message}"}
                                     for i in range(EXCEPTION_ROWS)])
    honest = _run(VIEW_READER, str(honest_path), run_id, str(tmp_path / "honest.rrd"))
    forged = _run(VIEW_READER, str(flooded), run_id, str(tmp_path / "forged.rrd"))
    assert honest["code"] == forged["code"] == 0
    peak, base = forged["peak_kb"] / 1024, honest["peak_kb"] / 1024
    assert peak - base < 250, f"{peak:,.0f} MB with {EXCEPTION_ROWS:,} exceptions, {base:,.0f} MB without"


COMPARE_READER = PEAK + """
import json, sys
from store import Store
from store.readers import step_outputs
with Store(sys.argv[1]).read() as con:
    (episode_id,) = con.execute("SELECT train_episode_id FROM candidates WHERE run_id = ? AND iteration = 0",
                                [sys.argv[2]]).fetchall()[0]
    rows = step_outputs(con, episode_id, 0, 120)
print(json.dumps({"peak_kb": peak_kb(), "rows": len(rows), "output": rows[0]["output"]}))
"""


def test_compare_reads_each_methods_last_output_cut(stores):
    """What ``codearcade compare`` shows around a divergence (``store.readers.step_outputs``): one row per method
    and step, each value at most a marker of its length and a preview, however many calls the policy made."""
    honest_path, forged_path, run_id = stores
    honest = _run(COMPARE_READER, str(honest_path), run_id)
    forged = _run(COMPARE_READER, str(forged_path), run_id)
    assert forged["rows"] == 120  # 2,000 calls of one method over 120 steps: its last call in each
    assert forged["output"]["$truncated"] == len(FLOOD) and forged["output"]["preview"].startswith("[{},{},")
    peak, base = forged["peak_kb"] / 1024, honest["peak_kb"] / 1024
    assert peak - base < 100, f"{peak:,.0f} MB with the forged rows, {base:,.0f} MB without"


def _held_bytes(value, seen=None) -> int:
    """The bytes of Python objects ``value`` holds (sys.getsizeof over its lists, dicts and heads, each once)."""
    seen = set() if seen is None else seen
    if id(value) in seen:
        return 0
    seen.add(id(value))
    size = sys.getsizeof(value)
    if isinstance(value, dict):
        size += sum(_held_bytes(k, seen) + _held_bytes(v, seen) for k, v in value.items())
    elif isinstance(value, list):
        size += sum(_held_bytes(v, seen) for v in value)
    elif isinstance(value, JsonHead):
        size += _held_bytes(value.text, seen)
    return size


def _hostile_text(rng: random.Random) -> str:
    """Valid JSON of at most 20,000 characters shaped to cost the most once decoded: empty containers by the
    thousand, objects of many keys of tiny lists, whitespace, astral text, long numbers, deep nesting."""
    empty = rng.choice(["{}", "[]", "[{}]", '""', "0", "{ }", "[ [ ] ]"])
    sep = rng.choice([",", ", ", ",\n  "])
    count = rng.choice([10, 99, 100, 101, 1_000, 4_000])
    kind = rng.randrange(5)
    if kind == 0:
        text = "[" + sep.join([empty] * count) + "]"
    elif kind == 1:
        text = "{" + sep.join(f'"k{i}":{empty}' for i in range(count)) + "}"
    elif kind == 2:
        keys = rng.choice([3, 8, 31, 32, 33])
        text = "{" + ",".join(f'"a{i}":[' + ",".join(["{}"] * rng.choice([5, 10, 100])) + "]" for i in range(keys)) + "}"
    elif kind == 3:
        text = json.dumps("".join(chr(rng.choice([0x1F600, 0x10FFFF, 0x41])) for _ in range(count)), ensure_ascii=False)
    else:
        depth = rng.choice([10, 60, 64, 65, 200])
        text = "[" * depth + "]" * depth
    text = (" " * rng.choice([0, 1]) + text) if kind != 2 else text
    return text[:20_000] if len(text) <= 20_000 else '"cut"'


def test_a_bounded_value_holds_a_few_bytes_per_character_it_shows_whatever_was_stored():
    """A sweep of hostile stored texts (valid JSON, at most 20,000 characters): what the prompt's reader keeps
    of a value, as the call's inputs or as its output, is at most a few kilobytes for the 300 characters it
    shows (9.5 KB at most here; decoded whole, the same texts hold up to 289 KB each); it never raises."""
    from store.held_values import bounded_value

    rng = random.Random(382)
    worst = 0
    for _ in range(600):
        text = _hostile_text(rng)
        for split in (False, True):
            worst = max(worst, _held_bytes(bounded_value(text, len(text), 300, split=split)))
    assert worst < 16_000, worst


def test_the_prompt_s_slice_stops_at_its_byte_bound(stores):
    """``step_nodes(..., max_bytes=)``: the rows stop, in step order, once what they hold passes the bound; the
    estimate (``held_bytes``) is never below what the rows hold (measured with ``sys.getsizeof``)."""
    from store.held_values import held_bytes

    _, forged_path, run_id = stores
    with Store(forged_path).read() as con:
        (episode_id,) = con.execute("SELECT train_episode_id FROM candidates WHERE run_id = ? AND iteration = 0",
                                    [run_id]).fetchall()[0]
        whole = step_nodes(con, episode_id, value_chars=300)
        cut = step_nodes(con, episode_id, value_chars=300, max_bytes=2**20)
        assert con.execute("SELECT 1").fetchall() == [(1,)]  # the connection goes on after the cut
    assert len(whole) == ROWS and 0 < len(cut) < ROWS and cut == whole[:len(cut)]
    assert held_bytes(cut) <= 2**20 < held_bytes(whole[:len(cut) + 1])
    assert held_bytes(whole) >= _held_bytes(whole)
