-- The ablation's comparison table: per feedback mode, the best and final scores over the seeds: their means with
-- 95% Student-t intervals over the `runs` (mean_ci and ci_text, which `codearcade sql` provides: docs/schema.md; the
-- mean alone when the runs' scores are all equal; `no score` when a run has none: every version it assessed, or its
-- final one, forfeited a game; final_score is the last iteration's, NULL when it forfeited: arg_max_null);
-- then the held-out audit of the runs' best versions (standard protocol, seeds the loop never played) and how many
-- runs it flagged overfit (docs/optimizer.md).
--
--   codearcade sql "$(cat examples/ablation.sql)" --store ablation.duckdb
WITH runs_of_batch AS (
    SELECT run_id, json_extract_string(config, '$.feedback') AS feedback,
           json_extract(config, '$.seed')::INT AS seed
    FROM runs WHERE json_extract_string(config, '$.batch') = 'pong-ablation'
), per_run AS (
    SELECT b.feedback, b.seed, max(i.score) AS best_score, arg_max_null(i.score, i.iteration) AS final_score,
           count(*) - 1 AS iterations, any_value(s.audit_score) AS audit, any_value(s.overfit) AS overfit
    FROM runs_of_batch b JOIN iterations i USING (run_id) JOIN run_summary s USING (run_id)
    GROUP BY b.feedback, b.seed
), per_mode AS (
    SELECT feedback, count(*) AS runs, mean_ci(list(best_score)) AS best, max(best_score) AS max_best,
           mean_ci(list(final_score)) AS final, min(iterations) AS iterations, mean_ci(list(audit)) AS audit,
           (count(*) FILTER (WHERE overfit))::INTEGER AS overfit
    FROM per_run GROUP BY feedback
)
SELECT feedback, runs, ci_text(best) AS mean_best, max_best, ci_text(final) AS mean_final, iterations,
       ci_text(audit) AS mean_audit, overfit
FROM per_mode ORDER BY feedback;
