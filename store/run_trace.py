"""Reader of one whole run as the rows a trace export needs (``codearcade export``): the run, its iterations,
LLM calls (with their prompt and reply texts), episodes and feedback, each with the stored times.

Rows come back as plain dicts, ordered the way the trace shows them; building spans from them is
``viewers/otlp_export.py``'s job.
"""

from __future__ import annotations

from typing import Any

import duckdb

from store.comparisons import best_version
from store.readers import _rows, blob_starts


def run_trace_rows(con: duckdb.DuckDBPyConnection, run_id: str, reply_chars: int = 2**31 - 1) -> dict[str, Any]:
    """``run`` (the runs row), ``iterations``, ``llm_calls``, ``episodes`` and ``feedback`` of ``run_id``, and its
    ``best`` (``store.comparisons.best_version``: a finalized served run's by validation; None for an eval run).

    KeyError if the run does not exist. ``llm_calls`` rows carry ``prompt_text`` (the stored JSON of the
    messages), ``reply_text`` (NULL when the call failed), its first ``reply_chars`` characters, and
    ``reply_length``, the whole reply's: a run's replies together may be far larger than what a trace keeps of them
    (up to 16 MiB each; thirty of 12.9 million characters held the exporter at 1.3 GB when read whole);
    ``iterations`` rows carry ``rejection`` (the reason from the ``rejected_candidates`` view, NULL unless the
    update was rejected).
    """
    runs = _rows(con.execute(
        """SELECT run_id, created_at, finished_at, kind, game, model, seed, status, error, starter_version_id,
                  package_versions->>'codearcade' AS codearcade_version
           FROM runs WHERE run_id = ?""", [run_id]))
    if not runs:
        raise KeyError(run_id)
    iterations = _rows(con.execute(
        """SELECT i.iteration, i.policy_version_id, i.base_version_id, i.update_status, i.rolled_back, i.llm_call_id,
                  i.train_episode_id, i.train_return, i.score, i.best_score, i.best_version_id, i.best_iteration,
                  i.started_at, i.finished_at, i.llm_s, i.train_s, i.eval_s, i.wall_s,
                  (SELECT any_value(r.reason) FROM rejected_candidates r
                   WHERE r.run_id = i.run_id AND r.iteration = i.iteration) AS rejection,
                  (SELECT count(*) FROM candidates c WHERE c.run_id = i.run_id AND c.iteration = i.iteration)
                      AS candidates,
                  (SELECT any_value(c.evaluation) FROM candidates c WHERE c.run_id = i.run_id
                   AND c.iteration = i.iteration AND c.candidate = coalesce(i.candidate, 0)) AS evaluation,
                  (SELECT e.iteration FROM episodes e WHERE e.episode_id = i.train_episode_id) AS episodes_iteration,
                  (SELECT any_value(c.forfeit) FROM candidates c WHERE c.run_id = i.run_id
                   AND c.iteration = i.iteration AND c.candidate = coalesce(i.candidate, 0)) AS forfeit
           FROM iterations i WHERE i.run_id = ? ORDER BY i.iteration""", [run_id]))
    llm_calls = _rows(con.execute(
        """SELECT c.call_id, c.iteration, c.purpose, c.created_at, c.latency_s, c.operation_name, c.provider_name,
                  c.request_model, c.response_model, c.request_temperature, c.request_max_tokens, c.request_seed,
                  c.response_id, c.finish_reasons, c.input_tokens, c.output_tokens, c.cached_input_tokens,
                  c.cache_creation_input_tokens, c.prompt_tokens_counted, c.cost_usd, c.attempts, c.error_type,
                  c.error_message, c.parse_error, c.replayed, c.prompt_hash, c.repair_of, c.repair_turn,
                  p.text AS prompt_text, c.reply_hash
           FROM llm_calls c LEFT JOIN blobs p ON p.hash = c.prompt_hash
           WHERE c.run_id = ? ORDER BY c.iteration, c.created_at, c.call_id""", [run_id]))
    replies = blob_starts(con, (call["reply_hash"] for call in llm_calls), reply_chars)
    for call in llm_calls:
        call["reply_text"], call["reply_length"] = replies.get(call.pop("reply_hash"), (None, None))
    episodes = _rows(con.execute(
        """SELECT episode_id, iteration, kind, episode_index, seed, policy_version_id, return, length, lives_lost,
                  end_reason, error, max_steps, traced, verified, started_at, duration_s, env_s, policy_s
           FROM episodes WHERE run_id = ?
           ORDER BY iteration, CASE kind WHEN 'train' THEN 0 ELSE 1 END, episode_index""", [run_id]))
    feedback = _rows(con.execute(
        "SELECT iteration, mode, stage, score, text FROM feedback WHERE run_id = ? ORDER BY iteration", [run_id]))
    return {"run": runs[0], "iterations": iterations, "llm_calls": llm_calls, "episodes": episodes,
            "feedback": feedback, "best": best_version(con, run_id)}
