"""Readers of a whole run hold one reply at a time, or a bounded start of each: ``view`` (the run's recording),
``export --otlp`` (its trace) and ``replay``.

An endpoint may answer up to 16 MiB (``pipeline/llm/capped.py``); a reply past 1,000,000 characters is refused by
the reply reader but stored whole, as every reply is. Readers that selected every iteration's reply at once held
one copy per iteration: thirty iterations of a 12.9 million-character reply (a 2.7 MB store: identical texts
compress) held ``view`` at 1.9 GB, the exporter at 1.3 GB and ``replay`` at 1.7 GB. The forged stores here are a
real five-iteration run (``tests/fixtures/greedy_run.duckdb.gz``) whose stored replies are made 16 million characters
long (each, or the first only); every reader runs in a process of its own, its peak RSS (``VmHWM``) against the same
reader on another store.
"""

from __future__ import annotations

import gzip
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import duckdb
import pytest

# each reader runs in a process of its own on a forged store, its peak memory read: not the quick lane's
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "tests" / "fixtures" / "greedy_run.duckdb.gz"
REPLY_CHARS = 16_000_000
"""Each forged reply's length: what the 16 MiB answer cap lets through (a reply of ASCII text)."""
GROWTH_BOUND_MB = 100
"""What the forged replies may add to a reader's peak: before, ~50 MB per iteration (five here: ~250-400 MB)."""

PEAK = """
def peak_kb():
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
"""

READERS = {
    "view": PEAK + """
import json, sys
from pipeline.cli import main
code = main(["view", sys.argv[2], "--store", sys.argv[1], "--save", sys.argv[3]])
print(json.dumps({"peak_kb": peak_kb(), "code": code}))
""",
    "export": PEAK + """
import json, sys
from store import Store
from store.run_trace import run_trace_rows
from viewers.otlp_export import DEFAULT_TEXT_LIMIT, build_spans
with Store(sys.argv[1]).read() as con:  # what export_run reads and builds before it sends
    rows = run_trace_rows(con, sys.argv[2], reply_chars=DEFAULT_TEXT_LIMIT + 1)
spans = build_spans(rows)
print(json.dumps({"peak_kb": peak_kb(), "code": 0 if spans else 1}))
""",
    "replay": PEAK + """
import json, sys
from pipeline.cli import main
code = main(["replay", sys.argv[2], "--store", sys.argv[1], "--json"])
print(json.dumps({"peak_kb": peak_kb(), "code": code}))
""",
}


def _forge(source: Path, path: Path, which: str) -> str:
    """Copy ``source`` to ``path`` with its replies 16 M characters long each (``which``: ``all``, or ``first``: the
    first call's only); the run's id."""
    shutil.copy(source, path)
    con = duckdb.connect(str(path))
    (run_id,) = con.execute("SELECT run_id FROM runs").fetchone()
    hashes = [h for (h,) in con.execute("SELECT reply_hash FROM llm_calls WHERE reply_hash IS NOT NULL "
                                        "ORDER BY created_at").fetchall()]
    assert len(set(hashes)) >= 4, hashes
    for digest in dict.fromkeys(hashes if which == "all" else hashes[:1]):
        # a distinct text each, with no letter of JSON (the reply reader's element count stays low)
        text = (digest + " lorem ipsum dolor sit amet ") * (REPLY_CHARS // (len(digest) + 27))
        con.execute("UPDATE blobs SET text = ?, chars = ? WHERE hash = ?", [text, len(text), digest])
    con.close()
    return run_id


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """(honest store, every reply forged, the first reply forged, run id): the fixture's run, and copies whose
    replies are 16 M characters each."""
    folder = tmp_path_factory.mktemp("run-readers")
    honest = folder / "honest.duckdb"
    with gzip.open(FIXTURE) as packed, open(honest, "wb") as out:
        shutil.copyfileobj(packed, out)
    run_id = _forge(honest, folder / "all.duckdb", "all")
    _forge(honest, folder / "first.duckdb", "first")
    return honest, folder / "all.duckdb", folder / "first.duckdb", run_id


def _run(script: str, *args: str) -> dict:
    env = {**os.environ, "LITELLM_LOCAL_MODEL_COST_MAP": "True", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


@pytest.mark.parametrize("reader", ["view", "export"])
def test_a_run_s_huge_replies_are_read_cut(stores, tmp_path, reader):
    """The run's recording and its trace keep the start of each reply (200,000 and 32,000 characters): their
    readers read that much of each, one reply at a time (DuckDB builds a whole text to cut it)."""
    honest_path, forged_path, _, run_id = stores
    honest = _run(READERS[reader], str(honest_path), run_id, str(tmp_path / "honest.rrd"))
    forged = _run(READERS[reader], str(forged_path), run_id, str(tmp_path / "forged.rrd"))
    assert honest["code"] == forged["code"] == 0, (honest, forged)
    peak, base = forged["peak_kb"] / 1024, honest["peak_kb"] / 1024
    assert peak - base < GROWTH_BOUND_MB, f"{reader}: {peak:,.0f} MB with 16 M-character replies, {base:,.0f} without"


def test_a_replay_reads_each_reply_when_it_answers_with_it(stores, tmp_path):
    """A replay answers each call with the stored reply whole (it must be the same text), so it holds one at a time:
    the replies it has not reached cost it nothing. The first reply forged makes the replay diverge there (the
    reply is refused where the original read it), with or without the later ones forged too; the later ones
    were all read at the start (+72 MB for three of them)."""
    _, every, first, run_id = stores
    only_first = _run(READERS["replay"], str(first), run_id)
    all_of_them = _run(READERS["replay"], str(every), run_id)
    assert only_first["code"] == all_of_them["code"] == 1, "diverged at the first forged reply"
    peak, base = all_of_them["peak_kb"] / 1024, only_first["peak_kb"] / 1024
    assert peak - base < LATER_REPLIES_BOUND_MB, f"{peak:,.0f} MB with every reply forged, {base:,.0f} with the first"


LATER_REPLIES_BOUND_MB = 30
"""What the replies a replay never reaches may add to its peak (three of 16 M characters: 72 MB when read at once)."""
