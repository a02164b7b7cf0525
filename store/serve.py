"""What ``codearcade serve`` reads from the store: a served run's submissions and spent budget, and the visible part
of the run that the agent's read-only SQL may query.

The visible part is copied into a private in-memory database (:func:`visible_query`) that holds nothing else: the
agent's SQL cannot reach another run, the run's config (its training seeds), any ``seed`` column, or the
validation and held-out episodes and scores (episode kinds other than ``train`` are left out), and it runs with
external access off, so it can read no file either. It runs in a process of its own with its memory capped
(``store/agent_sql.py``), so what a query builds is never the server's.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa

from store import agent_sql
from store.db import Store
from store.readers import _rows
from store.views import QueryError, check_user_sql

_COMMITTED = """(SELECT unnest(eval_episode_ids) FROM candidates WHERE run_id = $run AND iteration >= 1)"""
"""The training episodes of committed submissions (a killed server may leave a submission's episodes without one)."""

VISIBLE_TABLES = {
    "submissions": """SELECT c.iteration AS submission, c.policy_version_id, c.parent_iteration AS parent,
                             c.update_status, len(c.eval_episode_ids) AS episodes, c.score, c.score_low,
                             c.score_high, c.forfeit, c.created_at
                      FROM candidates c WHERE c.run_id = $run AND c.iteration >= 1""",
    "episodes": """SELECT episode_id, iteration AS submission, episode_index AS instance, policy_version_id,
                          "return", length, lives_lost, end_reason, error, max_steps
                   FROM episodes WHERE run_id = $run AND kind = 'train' AND episode_id IN """ + _COMMITTED,
    "steps": """SELECT s.episode_id, s.step, s.action, s.reward, s.score, s.terminated, s.truncated, s.lives,
                       s.player_x, s.player_y, s.ball_x, s.ball_y, s.objects
                FROM steps s WHERE s.episode_id IN """ + _COMMITTED,
    "nodes": """SELECT n.episode_id, n.step, n.call_index, n.function, n.trainable, n.policy_version_id,
                       n.inputs, n.output, n.exc_type, n.exc_message, n.exc_line, n.duration_us, n.parents
                FROM nodes n WHERE n.episode_id IN """ + _COMMITTED,
}
"""The tables the agent's SQL sees, each a slice of its own run's training play (no seed, no other kind)."""


def served_submissions(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """The committed submissions of a served run (iteration >= 1), in order: version, parent, episodes, score,
    interval, forfeit, training episodes' ids."""
    return _rows(con.execute(
        """SELECT iteration, policy_version_id, parent_iteration, parent_version_id, update_status, eval_episode_ids,
                  score, score_low, score_high, forfeit, train_return
           FROM candidates WHERE run_id = ? AND iteration >= 1 ORDER BY iteration""", [run_id]))


def submission_version(con: duckdb.DuckDBPyConnection, run_id: str, iteration: int) -> str | None:
    """The policy version of a served run's submission (0: the starting policy), None if it has none."""
    row = con.execute("SELECT policy_version_id FROM candidates WHERE run_id = ? AND iteration = ?",
                      [run_id, iteration]).fetchone()
    return row[0] if row else None


def submission_feedback(con: duckdb.DuckDBPyConnection, run_id: str, iteration: int) -> str:
    """The feedback text of a served run's submission ("" if it has none)."""
    row = con.execute("SELECT b.text FROM candidates c JOIN blobs b ON b.hash = c.feedback_hash "
                      "WHERE c.run_id = ? AND c.iteration = ?", [run_id, iteration]).fetchone()
    return row[0] if row else ""


def is_finalized(con: duckdb.DuckDBPyConnection, run_id: str, status: str) -> bool:
    """Whether a served run is finalized: finished, or audited (a finalize killed before the run's end)."""
    return status == "finished" or \
        con.execute("SELECT count(*) FROM audits WHERE run_id = ?", [run_id]).fetchone()[0] > 0


def submission_episodes(con: duckdb.DuckDBPyConnection, episode_ids: list[str]) -> list[dict[str, Any]]:
    """The visible summary of training episodes (never their seed), in the order given."""
    rows = {r["episode_id"]: r for r in _rows(con.execute(
        """SELECT episode_id, episode_index AS instance, "return", length, lives_lost, end_reason, error
           FROM episodes WHERE list_contains(?, episode_id)""", [list(episode_ids)]))}
    return [rows[e] for e in episode_ids if e in rows]


QUERY_MEMORY_MB = 512
"""What one query of the agent's may make DuckDB build, beside the tables it reads and the process's own start."""
PROCESS_BASE_MB = 400
"""The query process's data segment before it reads anything: Python, DuckDB and pyarrow loaded, a connection
(~200-340 MB measured here)."""
START_S = 20.0
"""The query process's start and its tables' load, beyond the query's own time limit, before it is killed."""


def visible_query(store: Store, run_id: str, sql: str, max_rows: int, max_bytes: int,
                  time_limit_s: float = 10.0, memory_mb: int = QUERY_MEMORY_MB) -> dict[str, Any]:
    """Run the agent's ``sql`` over the visible part of ``run_id`` (see the module docstring): its columns and the
    first rows, at most ``max_rows`` of them and at most ``max_bytes`` of JSON (``truncated`` says whether rows were
    left out; ``note`` why, when it was their size), every value one standard JSON holds (NaN and the infinities as
    null). :class:`QueryError` for a statement that is not a query, one that runs past ``time_limit_s`` or needs more
    than ``memory_mb`` (beside the tables it reads), and one that DuckDB refuses, with DuckDB's message.

    The query runs in a process of its own (``store/agent_sql.py``), its memory capped: what it makes DuckDB build
    costs that process, not the caller. The tables the query names are copied into it as Arrow files, with the
    store held for the copy only (a query of 10 s does not keep a submission from being stored)."""
    check_user_sql(sql, refuser="sql")  # the copy is the agent's own, but a DELETE that answers "Count: 3" misleads
    with tempfile.TemporaryDirectory(prefix="codearcade-sql-") as directory:
        work = Path(directory)
        held = 0
        with store.read() as con:
            for name in (name for name in VISIBLE_TABLES if re.search(rf"\b{name}\b", sql, re.IGNORECASE)):
                # a run's steps and nodes are big: only the tables the query names are copied
                with warnings.catch_warnings():  # the copy it warns of is the point: the agent's database is its own
                    warnings.simplefilter("ignore", UserWarning)
                    table = con.execute(VISIBLE_TABLES[name], {"run": run_id}).to_arrow_table()
                with pa.OSFile(str(work / f"{name}{agent_sql.TABLE_SUFFIX}"), "wb") as sink, \
                        pa.ipc.new_file(sink, table.schema) as writer:
                    writer.write_table(table)
                held += table.nbytes
                del table
        cap_mb = memory_mb + 2 * held // 2**20 + PROCESS_BASE_MB  # the tables twice: mapped, then DuckDB's copy
        (work / agent_sql.QUERY_FILE).write_text(json.dumps({
            "sql": sql, "max_rows": max_rows, "max_bytes": max_bytes, "time_limit_s": time_limit_s,
            "memory_mb": cap_mb}))
        return _answer_of(work, time_limit_s, cap_mb, max_bytes)


def _answer_of(work: Path, time_limit_s: float, cap_mb: int, max_bytes: int) -> dict[str, Any]:
    """Start the query process on ``work`` and read its answer within a byte bound (it is what DuckDB made of the
    agent's query: read as untrusted, like any reply)."""
    boot = f"import sys; sys.path.insert(0, {str(ROOT)!r}); from store.agent_sql import main; main(sys.argv[1])"
    with open(work / "stderr.txt", "wb") as stderr:
        try:
            done = subprocess.run([sys.executable, "-I", "-c", boot, str(work)], stdin=subprocess.DEVNULL,
                                  stdout=subprocess.DEVNULL, stderr=stderr, timeout=time_limit_s + START_S)
        except subprocess.TimeoutExpired:  # run() has killed it
            raise QueryError(f"the query ran past its limit of {time_limit_s:g} s: ask for less (a LIMIT, fewer rows "
                             "or columns)") from None
    answer = work / agent_sql.ANSWER_FILE
    if not answer.exists():
        with open(work / "stderr.txt", "rb") as said:
            said.seek(max(0, os.path.getsize(work / "stderr.txt") - 600))
            tail = said.read().decode(errors="replace").strip().splitlines()[-1:] or [""]
        how = f"signal {-done.returncode}" if done.returncode < 0 else f"exit status {done.returncode}"
        raise QueryError(f"the query's process ended without an answer ({how}: {tail[0][:200]}); its process may "
                         f"have {cap_mb:,} MB, the tables it reads included: ask for less")
    if answer.stat().st_size > ANSWER_SLACK * max_bytes + 2**16:
        raise QueryError("the query's answer was larger than its bound; ask for less")
    result = json.loads(answer.read_bytes())
    if "answer" in result:
        return result["answer"]
    raise QueryError(str(result.get("refused") or result.get("error"))[:2000])


ANSWER_SLACK = 2
"""The answer file's bytes per byte of ``max_bytes``: its rows are within ``max_bytes`` of JSON, the columns'
names and the escapes of what :func:`json.dumps` writes beside them."""
ROOT = Path(__file__).resolve().parents[1]
