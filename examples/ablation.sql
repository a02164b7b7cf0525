-- The ablation's comparison table: per feedback mode, the best and final scores over the seeds.
WITH runs_of_batch AS (
    SELECT run_id, json_extract_string(config, '$.feedback') AS feedback,
           json_extract(config, '$.seed')::INT AS seed
    FROM runs WHERE json_extract_string(config, '$.batch') = 'pong-ablation'
), per_run AS (
    SELECT b.feedback, b.seed, max(i.score) AS best_score, arg_max(i.score, i.iteration) AS final_score,
           count(*) - 1 AS iterations
    FROM runs_of_batch b JOIN iterations i USING (run_id) GROUP BY ALL
)
SELECT feedback, count(*) AS runs, round(avg(best_score), 1) AS mean_best, max(best_score) AS max_best,
       round(avg(final_score), 1) AS mean_final, min(iterations) AS iterations
FROM per_run GROUP BY feedback ORDER BY feedback;
