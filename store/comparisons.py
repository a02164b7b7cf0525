"""Readers for ``codearcade compare``: learning curves, best versions, stored versions and where two episodes part.

Each takes an open connection (``with store.read() as con:``) and returns plain Python values, like
``store/readers.py``; the observations and node outputs around a step come from ``readers.episode_steps`` and
``readers.step_nodes``.
"""

from __future__ import annotations

from typing import Any

import duckdb

from store.readers import _rows


def learning_curve(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """A run's iterations in order, with what each one spent (view ``learning_curve``): score, best so far, LLM
    calls and tokens of the iteration, cumulative tokens and elapsed wall seconds."""
    return _rows(con.execute(
        """SELECT iteration, score, best_score, best_iteration, update_status, policy_version_id, best_version_id,
                  llm_calls, total_tokens, cumulative_tokens, wall_s, elapsed_s
           FROM learning_curve WHERE run_id = ? ORDER BY iteration""", [run_id]))


def best_version(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any] | None:
    """The run's best version (view ``run_best``, its one home): ``policy_version_id``, ``iteration`` (where it first
    scored its best), ``score`` and ``best_by``, what picked it and what ``score`` is: ``validation`` for a finalized
    served run (its best by validation, the one its finalize played on the held-out pool,
    ``pipeline/serve/finalize.py``; ``policy_version_id`` None when every submission forfeited a validation game),
    ``training`` for a served run not finalized yet, ``tuning`` for an optimization run. None for a run without
    iterations (an eval run)."""
    rows = _rows(con.execute(
        """SELECT best_version_id AS policy_version_id, best_iteration AS iteration, best_score AS score, best_by,
                  best_training_score AS training_score
           FROM run_best WHERE run_id = ?""", [run_id]))
    return rows[0] if rows else None


def resolve_version(con: duckdb.DuckDBPyConnection, run_id: str, text: str) -> str:
    """The policy version of ``run_id`` whose id is ``text`` or starts with it; ``best`` is the run's best
    version (:func:`best_version`; eval runs: the version they played). ValueError with what exists if none or
    several match."""
    wanted = text.strip()
    if wanted == "best":
        best = best_version(con, run_id)
        if best is not None and best["policy_version_id"] is not None:
            return best["policy_version_id"]
        if best is not None:
            raise ValueError(f"run {run_id} has no best version: every submission forfeited a validation game; give "
                             "a version id")
        rows = con.execute("SELECT DISTINCT policy_version_id FROM episodes WHERE run_id = ?", [run_id]).fetchall()
        if len(rows) == 1:
            return rows[0][0]
        raise ValueError(f"run {run_id} has no best version (no iterations); give a version id")
    matches = [r[0] for r in con.execute(
        "SELECT DISTINCT policy_version_id FROM policy_versions WHERE run_id = ? AND starts_with(policy_version_id, ?) "
        "ORDER BY 1 LIMIT 6", [run_id, wanted]).fetchall()]
    if wanted in matches:
        return wanted
    if len(matches) == 1 and wanted:
        return matches[0]
    if not matches or not wanted:
        known = [r[0] for r in con.execute(
            "SELECT policy_version_id FROM policy_versions WHERE run_id = ? GROUP BY 1 ORDER BY min(iteration) LIMIT 8",
            [run_id]).fetchall()]
        raise ValueError(f"run {run_id} has no policy version {wanted!r}; it has {', '.join(known) or 'none'} "
                         "(or say 'best')")
    raise ValueError(f"version {wanted!r} is ambiguous in run {run_id}: {', '.join(matches[:5])}; give more of the id")


def first_divergent_step(con: duckdb.DuckDBPyConnection, episode_a: str, episode_b: str) -> int | None:
    """The first step at which two episodes' actions differ (a step only one of them has counts as a
    difference, and so does a step where one policy failed: its action is NULL); None if they never do."""
    row = con.execute(
        """SELECT min(step) FROM (SELECT step, action FROM steps WHERE episode_id = ?) a
           FULL OUTER JOIN (SELECT step, action FROM steps WHERE episode_id = ?) b USING (step)
           WHERE a.action IS DISTINCT FROM b.action""", [episode_a, episode_b]).fetchone()
    return row[0] if row else None


def episode_rows(con: duckdb.DuckDBPyConnection, episode_ids: list[str]) -> dict[str, dict[str, Any]]:
    """The ``episodes`` rows of these episodes, by id (seed, return, length, end reason, policy version)."""
    rows = _rows(con.execute(
        """SELECT episode_id, run_id, seed, policy_version_id, return, length, lives_lost, end_reason, error, traced
           FROM episodes WHERE list_contains(?, episode_id)""", [episode_ids]))
    return {r["episode_id"]: r for r in rows}


def best_evaluation(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any] | None:
    """The assessment that picked the run's best (:func:`best_version`): its ``score`` with ``score_low`` and
    ``score_high`` (the 95% interval) and its ``episodes`` (return, length, end reason, error, in order): the
    evaluation episodes (``candidates``), or the robust ones for a run that optimizes the standard protocol's score,
    or a finalized served run's validation games (``audits``). None without iterations or a best."""
    best = best_version(con, run_id)
    if best is None or best["policy_version_id"] is None:
        return None
    if best["best_by"] == "validation":  # validation picked it: its validation games, not its training ones
        rows = _rows(con.execute(
            """SELECT score, score_low, score_high, episode_ids FROM audits
               WHERE run_id = ? AND protocol = 'validation' AND policy_version_id = ?""",
            [run_id, best["policy_version_id"]]))
    else:
        rows = _rows(con.execute(
            """SELECT c.score, c.score_low, c.score_high,
                      CASE WHEN json_extract_string(r.config, '$.optimize_protocol') = 'standard'
                           THEN c.robust_episode_ids ELSE c.eval_episode_ids END AS episode_ids
               FROM candidates c JOIN runs r ON r.run_id = c.run_id
               WHERE c.run_id = ? AND c.iteration = ? AND c.policy_version_id = ?
               ORDER BY c.score DESC NULLS LAST, c.candidate LIMIT 1""",
            [run_id, best["iteration"], best["policy_version_id"]]))
    if not rows:
        return None
    found = rows[0]
    ids = found.pop("episode_ids") or []
    by_id = {e["episode_id"]: e for e in _rows(con.execute(
        """SELECT episode_id, return, length, end_reason, error FROM episodes WHERE list_contains(?, episode_id)""",
        [ids]))}
    found["episodes"] = [by_id[i] for i in ids if i in by_id]
    return found


def held_out_evaluation(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any] | None:
    """The held-out audit of a run's best (``codearcade audit``, ``pipeline/optimizer/audit.py``): its ``audits``
    row of role ``best`` under the standard protocol (``policy_version_id``, ``iteration``, ``seeds``) with its
    ``episodes`` (seed, return, length, end reason, error, in the row's order); None when the run was never
    audited. The caller checks that it played the run's best of now: a run that went on after its audit has a
    newer one."""
    rows = _rows(con.execute(
        """SELECT policy_version_id, iteration, seeds, episode_ids FROM audits
           WHERE run_id = ? AND role = 'best' AND protocol = 'standard'""", [run_id]))
    if not rows:
        return None
    found = rows[0]
    ids = found.pop("episode_ids") or []
    by_id = episode_rows(con, ids)
    found["episodes"] = [by_id[i] for i in ids if i in by_id]
    return found
