-- The paper's table from a store: per game, codearcade's best scores in the runs of examples/benchmarks.toml beside
-- the authors' published figures (table published_scores, filled from each game's module, games/<game>.py).
--
--   codearcade batch examples/benchmarks.toml
--   codearcade sql "$(cat examples/benchmarks.sql)" --store benchmarks.duckdb
--
-- Scores are the authors' measure: a run's best evaluation score under their protocol (sticky 0, no no-op starts,
-- their caps and episode counts: the frontier view's deterministic_score, iteration 0 included), averaged over the
-- runs of a game (seeds) with its 95% Student-t interval over the `runs` (`mean_best`: mean_ci and ci_text, which
-- `codearcade sql` provides: docs/schema.md; none for one run or all equal; `no score` when a run has none: its audit
-- forfeited a game, say), and their interquartile
-- mean (`iqm_best`, as rliable recommends), whose bootstrap interval needs 30 runs of a game (below: the IQM alone). `protocol` says what our evaluation episodes were: `lives of one
-- game` (the authors' protocol, `one_life = "continue"`: the follow-up ends an episode at a lost life in Asterix,
-- Breakout, Q*bert and Seaquest and goes on with the same game in the next), `first lives` (`one_life = true`: the
-- first life of each episode's own seeded game), `whole games`, or `mixed` across a game's runs. Beside them, the
-- held-out audit (`audit`: the runs' best versions on seeds the loop never played, under the standard protocol,
-- mean [95% interval] over the runs; `overfit`: how many runs the audit flagged; docs/optimizer.md).
-- `theirs` is their figure at our training horizon; paper, default, h1 and h100 are all of theirs (mean ± se).
WITH batch_runs AS (
    SELECT run_id, game, json_extract(config, '$.rollout_steps')::INTEGER AS horizon,
           CASE json_extract_string(config, '$.one_life') WHEN 'continue' THEN 'lives of one game'
                WHEN 'true' THEN 'first lives' ELSE 'whole games' END AS protocol
    FROM runs WHERE kind = 'optimize' AND json_extract_string(config, '$.batch') = 'eight-games'
), per_run AS (
    SELECT b.game, b.run_id, any_value(b.horizon) AS horizon, any_value(b.protocol) AS protocol,
           max(f.deterministic_score) AS best,
           (SELECT max(i.iteration) FROM iterations i WHERE i.run_id = b.run_id) AS iterations,
           any_value(s.audit_score) AS audit, any_value(s.overfit) AS overfit
    FROM batch_runs b JOIN frontier f USING (run_id) JOIN run_summary s USING (run_id) GROUP BY b.game, b.run_id
), ours AS (
    SELECT game, CASE WHEN count(DISTINCT protocol) > 1 THEN 'mixed' ELSE any_value(protocol) END AS protocol,
           min(horizon) AS horizon, count(*)::INTEGER AS runs, min(iterations) AS iterations,
           max(best) AS best, mean_ci(list(best)) AS m, iqm_ci(list(best)) AS q, mean_ci(list(audit)) AS a,
           (count(*) FILTER (WHERE overfit))::INTEGER AS overfit
    FROM per_run GROUP BY game
), theirs AS (
    SELECT game,
           any_value(CASE WHEN stderr IS NULL THEN printf('%.1f', score)
                          ELSE printf('%.1f ± %.1f', score, stderr) END) FILTER (WHERE setting = 'paper') AS paper,
           any_value(printf('%.1f ± %.1f', score, stderr)) FILTER (WHERE setting = 'default') AS "default",
           any_value(printf('%.1f ± %.1f', score, stderr)) FILTER (WHERE setting = 'h1') AS h1,
           any_value(printf('%.1f ± %.1f', score, stderr)) FILTER (WHERE setting = 'h100') AS h100
    FROM published_scores GROUP BY game
)
SELECT coalesce(o.game, t.game) AS game, o.protocol, o.horizon, o.runs, o.iterations, o.best,
       ci_text(o.m) AS mean_best, ci_text(o.q) AS iqm_best, ci_text(o.a) AS audit, o.overfit,
       (SELECT p.score FROM published_scores p WHERE p.game = o.game AND p.horizon = o.horizon
        AND p.setting <> 'paper' ORDER BY p.setting LIMIT 1) AS theirs,
       (SELECT p.stderr FROM published_scores p WHERE p.game = o.game AND p.horizon = o.horizon
        AND p.setting <> 'paper' ORDER BY p.setting LIMIT 1) AS theirs_se,
       t.paper, t."default", t.h1, t.h100
FROM ours o FULL JOIN theirs t ON t.game = o.game
ORDER BY game;
