-- The ablation's comparison table: per feedback mode, the best and final scores over the seeds: their means with
-- 95% bootstrap intervals (mean [low, high]: mean_ci and ci_text, which `codearcade sql` provides: docs/schema.md).
--
--   codearcade sql "$(cat examples/ablation.sql)" --store ablation.duckdb
WITH runs_of_batch AS (
    SELECT run_id, json_extract_string(config, '$.feedback') AS feedback,
           json_extract(config, '$.seed')::INT AS seed
    FROM runs WHERE json_extract_string(config, '$.batch') = 'pong-ablation'
), per_run AS (
    SELECT b.feedback, b.seed, max(i.score) AS best_score, arg_max(i.score, i.iteration) AS final_score,
           count(*) - 1 AS iterations
    FROM runs_of_batch b JOIN iterations i USING (run_id) GROUP BY ALL
), per_mode AS (
    SELECT feedback, count(*) AS runs, mean_ci(list(best_score)) AS best, max(best_score) AS max_best,
           mean_ci(list(final_score)) AS final, min(iterations) AS iterations
    FROM per_run GROUP BY feedback
)
SELECT feedback, runs, ci_text(best.mean, best.low, best.high) AS mean_best, max_best,
       ci_text(final.mean, final.low, final.high) AS mean_final, iterations
FROM per_mode ORDER BY feedback;
