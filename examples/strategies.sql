-- Strategies compared at equal LLM budgets. Per strategy (means over the seeds, the scores with their 95% Student-t
-- intervals over the `runs`: mean_ci and ci_text, which `codearcade sql` provides: docs/schema.md; `no score` where a
-- run had none yet: every candidate it had assessed forfeited a game):
-- the best score reached after 5, 10 and 20 LLM calls (the starting policy's score counts from call 0), the tokens and the wall-clock
-- minutes the runs spent, and how many candidates they assessed (and how many reused stored episodes).
WITH runs_of_batch AS (
    SELECT run_id, json_extract_string(config, '$.strategy') AS strategy,
           json_extract(config, '$.seed')::INT AS seed
    FROM runs WHERE json_extract_string(config, '$.batch') = 'pong-strategies'
), calls AS (  -- each call's rank in its run: 1, 2, ...
    SELECT c.run_id, c.call_id, row_number() OVER (PARTITION BY c.run_id ORDER BY c.created_at, c.call_id) AS n
    FROM llm_calls c JOIN runs_of_batch USING (run_id)
), scored AS (  -- each assessed candidate with the number of calls spent when it was made
    SELECT d.run_id, d.score, coalesce(k.n, 0) AS calls_spent, d.evaluation, d.iteration
    FROM candidates d JOIN runs_of_batch USING (run_id) LEFT JOIN calls k ON k.call_id = d.llm_call_id
), per_run AS (
    SELECT b.strategy, b.run_id,
           max(s.score) FILTER (WHERE s.calls_spent <= 5) AS best_at_5,
           max(s.score) FILTER (WHERE s.calls_spent <= 10) AS best_at_10,
           max(s.score) FILTER (WHERE s.calls_spent <= 20) AS best_at_20,
           count(*) FILTER (WHERE s.iteration > 0) AS candidates,
           count(*) FILTER (WHERE s.evaluation = 'cached') AS cached
    FROM runs_of_batch b JOIN scored s USING (run_id) GROUP BY ALL
), per_strategy AS (
    SELECT p.strategy, count(*) AS runs, mean_ci(list(best_at_5)) AS at_5, mean_ci(list(best_at_10)) AS at_10,
           mean_ci(list(best_at_20)) AS at_20, max(best_at_20) AS max_best,
           round(avg(u.calls), 1) AS calls, round(avg(u.total_tokens)) AS tokens,
           round(avg((SELECT sum(wall_s) FROM iterations i WHERE i.run_id = p.run_id)) / 60, 1) AS wall_minutes,
           sum(candidates) AS candidates, sum(cached) AS cached_assessments
    FROM per_run p JOIN llm_usage u USING (run_id)
    GROUP BY p.strategy
)
SELECT strategy, runs, ci_text(at_5) AS best_after_5_calls, ci_text(at_10) AS best_after_10_calls,
       ci_text(at_20) AS best_after_20_calls, max_best, calls, tokens, wall_minutes,
       candidates, cached_assessments
FROM per_strategy ORDER BY at_20.mean DESC NULLS LAST;
