"""Readers that return slices of the store as plain Python values, for the optimizer and the viewers.

Each takes an open connection (``with store.read() as con:``) so a caller can read several slices in one
open. Step slices come back with the observation dict rebuilt exactly as the policy saw it.
"""

from __future__ import annotations

import json
from typing import Any, Callable, Mapping

import duckdb

from tracing.steps import objects_to_obs


def _rows(cursor: duckdb.DuckDBPyConnection) -> list[dict[str, Any]]:
    names = [d[0] for d in cursor.description]
    return [dict(zip(names, row)) for row in cursor.fetchall()]


def episode_steps(
    con: duckdb.DuckDBPyConnection,
    episode_id: str,
    start: int = 0,
    stop: int | None = None,
    list_widths: Mapping[str, int] | None = None,
    derive: Callable[[dict, int], None] | None = None,
) -> list[dict[str, Any]]:
    """Steps ``start <= step < stop`` of an episode, in order; each with ``obs`` rebuilt as the policy saw it
    (see tracing/steps.py): ``list_widths`` and ``derive`` are the game's (``games.Game``), which adds the
    fields it computes from the objects and the step's lives."""
    rows = _rows(
        con.execute(
            """SELECT step, action, reward, score, terminated, truncated, lives, objects
               FROM steps WHERE episode_id = ? AND step >= ? AND step < ? ORDER BY step""",
            [episode_id, start, stop if stop is not None else 2**31 - 1],
        )
    )
    for row in rows:
        row["obs"] = objects_to_obs(row.pop("objects"), list_widths)
        if derive is not None:
            derive(row["obs"], row["lives"])
    return rows


def step_nodes(
    con: duckdb.DuckDBPyConnection, episode_id: str, start: int = 0, stop: int | None = None
) -> list[dict[str, Any]]:
    """Node calls of steps ``start <= step < stop``, ordered by step and call index; JSON decoded."""
    rows = _rows(
        con.execute(
            """SELECT step, call_index, function, trainable, policy_version_id, inputs, output, exc_type,
                      exc_message, exc_line, exc_source, duration_us, parents
               FROM nodes WHERE episode_id = ? AND step >= ? AND step < ? ORDER BY step, call_index""",
            [episode_id, start, stop if stop is not None else 2**31 - 1],
        )
    )
    for row in rows:
        row["inputs"] = json.loads(row["inputs"]) if row["inputs"] is not None else None
        row["output"] = json.loads(row["output"]) if row["output"] is not None else None
    return rows


def run_episodes(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """Every episode of a run with its return, length and end reason, in (iteration, kind, index) order."""
    return _rows(
        con.execute(
            """SELECT episode_id, iteration, kind, episode_index, seed, policy_version_id, return, length,
                      lives_lost, end_reason, error, duration_s
               FROM episodes WHERE run_id = ? ORDER BY iteration, kind, episode_index""",
            [run_id],
        )
    )


def get_run(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any] | None:
    rows = _rows(con.execute("SELECT * FROM runs WHERE run_id = ?", [run_id]))
    return rows[0] if rows else None


def blob_text(con: duckdb.DuckDBPyConnection, digest: str) -> str | None:
    row = con.execute("SELECT text FROM blobs WHERE hash = ?", [digest]).fetchone()
    return row[0] if row else None


def policy_text(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str) -> str:
    """The whole policy file of a version used or considered in a run."""
    row = con.execute(
        "SELECT b.text FROM policy_versions v JOIN blobs b ON b.hash = v.source_hash "
        "WHERE v.run_id = ? AND v.policy_version_id = ? LIMIT 1", [run_id, version_id]).fetchone()
    if row is None:
        raise KeyError(f"run {run_id} has no policy version {version_id}")
    return row[0]


def run_spending(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, float]:
    """What a run has used so far: LLM cost (USD, calls with a known price), tokens, and iteration wall time."""
    cost, tokens = con.execute(
        "SELECT coalesce(sum(cost_usd), 0), coalesce(sum(coalesce(input_tokens, 0) + coalesce(output_tokens, 0)), 0) "
        "FROM llm_calls WHERE run_id = ? AND NOT replayed", [run_id]).fetchone()
    wall, last_wall = con.execute(
        "SELECT coalesce(sum(wall_s), 0), coalesce(arg_max(wall_s, iteration), 0) FROM iterations WHERE run_id = ?",
        [run_id]).fetchone()
    return {"cost_usd": float(cost), "tokens": int(tokens), "wall_s": float(wall), "last_wall_s": float(last_wall)}


def stored_reply(con: duckdb.DuckDBPyConnection, run_id: str, iteration: int, prompt_hash: str) -> tuple[str, str] | None:
    """(call id, reply text) of a successful call already made for this prompt in this iteration, if any."""
    row = con.execute(
        "SELECT c.call_id, b.text FROM llm_calls c JOIN blobs b ON b.hash = c.reply_hash "
        "WHERE c.run_id = ? AND c.iteration = ? AND c.prompt_hash = ? AND c.error_type IS NULL "
        "ORDER BY c.created_at LIMIT 1", [run_id, iteration, prompt_hash]).fetchone()
    return (row[0], row[1]) if row else None
