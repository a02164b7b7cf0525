"""Readers for the viewers: the slices of the store that a report, a run recording or an episode recording shows.

Each takes an open connection (``with store.read() as con:``) and returns plain values (rows as dicts) or Arrow
tables; the viewers only draw them. SQL lives here, as everywhere, in ``store/``.
"""

from __future__ import annotations

from typing import Any

import duckdb
import pyarrow as pa

from store.comparisons import best_version
from store.readers import _rows, blob_starts, cut_value_sql
from store.scores import score_episodes
from tracing.bounded import PREVIEW_CHARS


def _query(con: duckdb.DuckDBPyConnection, sql: str, params: list[Any] | None = None) -> list[dict[str, Any]]:
    return _rows(con.execute(sql, params or []))


def report_rows(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any]:
    """What ``codearcade report`` shows of a run: its summary, learning curve, code metrics, LLM usage, rejected
    candidates, lineage, episodes and versions (the views of docs/schema.md)."""
    def q(sql: str) -> list[dict[str, Any]]:
        return _query(con, sql, [run_id])

    rows = {
        "summary": q("SELECT * FROM run_summary WHERE run_id = ?")[0],
        "curve": q("SELECT * FROM learning_curve WHERE run_id = ? ORDER BY iteration"),
        "code": q("SELECT * FROM code_metrics WHERE run_id = ? ORDER BY iteration"),
        "usage": q("SELECT * FROM llm_usage WHERE run_id = ?")[0],
        "models": q("SELECT * FROM model_stats WHERE run_id = ? ORDER BY calls DESC, model"),
        "rejected": q("SELECT * FROM rejected_candidates WHERE run_id = ? ORDER BY iteration"),
        "lineage": q("SELECT * FROM lineage WHERE run_id = ? ORDER BY iteration, candidate"),
        "episodes": q("SELECT episode_id, iteration, kind, episode_index, seed, policy_version_id, return, length, "
                      "lives_lost, end_reason, error, duration_s, max_steps FROM episodes WHERE run_id = ? "
                      "ORDER BY iteration, kind, episode_index"),
        "versions": q("SELECT policy_version_id, iteration, produced_by, validation, loc, sloc, complexity, "
                      "max_if_depth, functions FROM policy_versions WHERE run_id = ? ORDER BY iteration"),
        "audits": q("SELECT role, protocol, iteration, policy_version_id, seeds, episode_ids, score, score_low, "
                    "score_high, forfeit, tuning_score, overfit FROM audits WHERE run_id = ? "
                    "ORDER BY role, protocol DESC"),
        "calls": llm_call_outcomes(con, run_id),
    }
    scored = {r["iteration"]: r["episode_ids"] or [] for r in q(
        """SELECT i.iteration, CASE WHEN json_extract_string(r.config, '$.optimize_protocol') = 'standard'
                                 THEN k.robust_episode_ids ELSE k.eval_episode_ids END AS episode_ids
           FROM iterations i JOIN runs r ON r.run_id = i.run_id
           LEFT JOIN candidates k ON k.run_id = i.run_id AND k.iteration = i.iteration
                AND k.candidate = coalesce(i.candidate, 0)
           WHERE i.run_id = ?""")}
    _rescore(rows["curve"], scored, rows["episodes"])
    _rescore(rows["audits"], {a["role"] + a["protocol"]: a["episode_ids"] for a in rows["audits"]}, rows["episodes"],
             key=lambda a: a["role"] + a["protocol"])
    return rows


def _rescore(rows: list[dict[str, Any]], scored: dict[Any, list[str]], episodes: list[dict[str, Any]],
             key: Any = lambda r: r["iteration"]) -> None:
    """Give each scored row (an iteration of the learning curve, an audit) the interval of ``store/scores.py``,
    computed now from the episodes that scored it, and their number: ``score_low``, ``score_high`` (None: no
    interval) and ``score_n``. A store keeps the interval it was made with, and stores made before issue 37 hold
    percentile-bootstrap ones; what a report prints is today's rule, labelled as such."""
    by_id = {e["episode_id"]: e for e in episodes}
    for row in rows:
        found = [by_id[i] for i in scored.get(key(row)) or [] if i in by_id]
        if row.get("score") is None or not found:
            row["score_n"] = len(found)
            continue
        score = score_episodes(found)
        row["score_low"], row["score_high"], row["score_n"] = score.low, score.high, score.played


def llm_call_outcomes(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """Every LLM call of a run in the order they started, with when it started and ended and what came of it:
    ``outcome`` is the update status of the candidate it made (``accepted``, ``rejected``, ``unchanged``), ``repaired``
    for a reply a repair turn replaced, or ``failed`` for a call without a reply."""
    return _query(con, """
        SELECT c.call_id, c.iteration, c.candidate, c.purpose, c.repair_turn, c.request_model,
               c.created_at - to_microseconds(CAST(coalesce(c.latency_s, 0) * 1e6 AS BIGINT)) AS started_at,
               c.created_at AS ended_at, c.latency_s, c.cost_usd,
               CASE WHEN c.error_type IS NOT NULL THEN 'failed'
                    WHEN k.update_status IS NOT NULL THEN k.update_status
                    WHEN EXISTS (SELECT 1 FROM llm_calls r WHERE r.run_id = c.run_id AND r.repair_of = c.call_id)
                        THEN 'repaired'
                    ELSE 'rejected' END AS outcome
        FROM llm_calls c
        LEFT JOIN candidates k ON k.run_id = c.run_id AND k.llm_call_id = c.call_id
        WHERE c.run_id = ? ORDER BY started_at, c.call_id""", [run_id])


RECORDED_TEXT_CHARS = 200_000
"""Characters of an iteration's reply and feedback a run recording shows (``reply_length`` and
``feedback_length`` say how long the whole is): a reply may be up to 16 MiB, and thirty iterations of a 12.9
million-character one held `view` at 1.9 GB when each was read and shown whole."""


def run_timeline(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any]:
    """A run recording's data: the run row, its iterations (joined with the evaluated version and its code, the
    LLM call with its prompt and the first :data:`RECORDED_TEXT_CHARS` of its reply, the feedback) and its
    lineage, and its ``best`` (``store.comparisons.best_version``: a finalized served run's by validation)."""
    runs = _query(con, "SELECT run_id, kind, game, model, seed, status, config, created_at, error FROM runs "
                      "WHERE run_id = ?", [run_id])
    if not runs:
        raise KeyError(f"no run {run_id}")
    iterations = _query(con, """
        SELECT i.iteration, i.policy_version_id, i.update_status, i.rolled_back, i.score, i.best_score,
               i.best_iteration, i.train_return, i.wall_s,
               v.loc, v.complexity, v.max_if_depth, code.text AS code,
               c.input_tokens, c.output_tokens, c.prompt_tokens_counted, c.cost_usd, c.latency_s, c.error_type,
               c.error_message, c.parse_error, p.text AS prompt, c.reply_hash, left(f.text, $2) AS feedback,
               length(f.text) AS feedback_length, k.forfeit
        FROM iterations i
        LEFT JOIN (SELECT DISTINCT ON (policy_version_id) policy_version_id, loc, complexity, max_if_depth,
                          source_hash FROM policy_versions WHERE run_id = $1) v
               ON v.policy_version_id = i.policy_version_id
        LEFT JOIN blobs code ON code.hash = v.source_hash
        LEFT JOIN llm_calls c ON c.call_id = i.llm_call_id
        LEFT JOIN blobs p ON p.hash = c.prompt_hash
        LEFT JOIN feedback f ON f.run_id = i.run_id AND f.iteration = i.iteration
        LEFT JOIN candidates k ON k.run_id = i.run_id AND k.iteration = i.iteration  -- the chosen candidate
             AND k.candidate = coalesce(i.candidate, 0)
        WHERE i.run_id = $1 ORDER BY i.iteration""", [run_id, RECORDED_TEXT_CHARS])
    replies = blob_starts(con, (it["reply_hash"] for it in iterations), RECORDED_TEXT_CHARS)
    for it in iterations:
        it["reply"], it["reply_length"] = replies.get(it.pop("reply_hash"), (None, None))
    lineage = _query(con, "SELECT iteration, candidate, parent_iteration, parent_candidate, score, decision, "
                         "update_status FROM lineage WHERE run_id = ? ORDER BY iteration, candidate", [run_id])
    return {"run": runs[0], "iterations": iterations, "lineage": lineage, "best": best_version(con, run_id)}


def episode_list(con: duckdb.DuckDBPyConnection, run_id: str) -> list[tuple[str, int, str, int]]:
    """(episode id, iteration, kind, index) of a run's episodes: iterations in order, training rollouts first."""
    return con.execute("SELECT episode_id, iteration, kind, episode_index FROM episodes WHERE run_id = ? "
                       "ORDER BY iteration, kind DESC, episode_index", [run_id]).fetchall()


def episode_tables(con: duckdb.DuckDBPyConnection, episode_id: str) -> tuple[dict[str, Any], pa.Table, pa.Table]:
    """An episode's row, and its steps and node calls as Arrow tables in order, each node value at most
    :data:`RECORDED_VALUE_CHARS` characters (else its marker); KeyError if there is none."""
    rows = _query(con, "SELECT * FROM episodes WHERE episode_id = ?", [episode_id])
    if not rows:
        raise KeyError(f"no episode {episode_id}")
    steps = con.sql("SELECT step, action, reward, score, lives, objects FROM steps WHERE episode_id = $1 "
                    "ORDER BY step", params=[episode_id]).to_arrow_table()
    nodes = con.sql(f"SELECT step, call_index, function, {_shown('inputs')}, {_shown('output')}, exc_type, exc_message, "
                    "exc_line, exc_source, parents, lines_run FROM nodes WHERE episode_id = $1 ORDER BY step, call_index",
                    params=[episode_id]).to_arrow_table()
    return rows[0], steps, nodes


RECORDED_VALUE_CHARS = PREVIEW_CHARS
"""Characters of a node value a rebuilt recording shows (a line of its text log): a longer value comes as the
``$truncated`` marker of ``tracing/bounded.py``, its length and a preview, so the recording never holds more of a
rollout's values than its rows times this, decoded (issue 38: 2,000 values of ``[{},{},…]``)."""


def _shown(column: str) -> str:
    """The SQL of a node value as a rebuilt recording reads it (:data:`RECORDED_VALUE_CHARS`)."""
    return f"{cut_value_sql(column, RECORDED_VALUE_CHARS)} AS {column}"


def lead_in_actions(con: duckdb.DuckDBPyConnection, episode_id: str) -> list[list[int]]:
    """The recorded actions of the episodes that ``episode_id`` continues (the authors' one-life protocol:
    ``episodes.continues``), the game's first episode first: what a replay plays before it; [] for an episode
    that starts from ``reset(seed)``."""
    chain = _query(con, """
        WITH RECURSIVE chain(episode_id, continues, depth) AS (
            SELECT episode_id, continues, 0 FROM episodes WHERE episode_id = ?
            UNION ALL
            SELECT e.episode_id, e.continues, c.depth + 1 FROM episodes e JOIN chain c ON e.episode_id = c.continues
        )
        SELECT c.episode_id, list(s.action ORDER BY s.step) FILTER (WHERE s.action IS NOT NULL) AS actions
        FROM chain c LEFT JOIN steps s USING (episode_id) WHERE c.depth > 0
        GROUP BY c.episode_id, c.depth ORDER BY c.depth DESC""", [episode_id])
    return [row["actions"] or [] for row in chain]


def reused_episodes(con: duckdb.DuckDBPyConnection, run_id: str, iteration: int) -> list[dict[str, Any]]:
    """The candidates of an iteration whose episodes were reused from an earlier assessment of the same version
    (``candidates.evaluation = 'cached'``, the evaluation cache), in order: candidate, version, training rollout and
    evaluation episode ids, and ``played_in``, the iteration that played them."""
    return _query(con, """
        SELECT c.candidate, c.policy_version_id, c.decision, c.train_episode_id, c.eval_episode_ids,
               e.iteration AS played_in
        FROM candidates c
        LEFT JOIN episodes e ON e.episode_id = coalesce(c.train_episode_id, c.eval_episode_ids[1])
        WHERE c.run_id = ? AND c.iteration = ? AND c.evaluation = 'cached'
        ORDER BY c.candidate""", [run_id, iteration])
