"""The store's schema, as ordered migrations recorded in the database itself.

Each migration is a (version, name, SQL) triple applied once, in order, inside a transaction, and recorded in
``schema_migrations``. Never edit a released migration: add a new one. A store whose highest recorded
version is above :data:`LATEST` was written by a newer codearcade and is refused (see ``store/db.py``).
The tables and their columns are documented in docs/schema.md; tests check that the two agree.

Over ~600 lines because it is the schema's whole history, append-only: a released migration is never edited, so
it cannot be shortened, and one file keeps the order plain.
"""

from __future__ import annotations

MIGRATIONS: list[tuple[int, str, str]] = [
    (
        1,
        "foundation: runs, blobs, policy versions, episodes, steps, nodes",
        """
        CREATE TABLE blobs (
            hash        VARCHAR PRIMARY KEY,   -- sha256 hex of text
            kind        VARCHAR NOT NULL,      -- policy | prompt | reply | source | ...
            text        VARCHAR NOT NULL,
            chars       INTEGER NOT NULL
        );
        CREATE TABLE runs (
            run_id              VARCHAR PRIMARY KEY,   -- ULID
            created_at          TIMESTAMP NOT NULL,
            kind                VARCHAR NOT NULL,      -- eval | optimize
            game                VARCHAR NOT NULL,
            config              JSON NOT NULL,
            model               VARCHAR,
            seed                BIGINT,
            status              VARCHAR NOT NULL,      -- running | finished | failed | interrupted
            package_versions    JSON,
            starter_policy_hash VARCHAR,               -- blobs.hash of the starting policy file
            starter_version_id  VARCHAR,
            finished_at         TIMESTAMP,
            error               VARCHAR
        );
        CREATE TABLE policy_versions (
            policy_version_id VARCHAR NOT NULL,        -- content hash of the policy text
            run_id            VARCHAR NOT NULL,
            iteration         INTEGER NOT NULL,
            parent_id         VARCHAR,
            source_hash       VARCHAR NOT NULL,        -- blobs.hash of the whole policy text
            produced_by       VARCHAR NOT NULL,        -- file | initial | llm | rollback
            validation        VARCHAR NOT NULL,        -- accepted | rejected | unvalidated
            validation_error  VARCHAR,
            loc               INTEGER,
            sloc              INTEGER,
            complexity        INTEGER,
            max_if_depth      INTEGER,
            functions         STRUCT(name VARCHAR, source_hash VARCHAR, trainable BOOLEAN, loc INTEGER,
                                     sloc INTEGER, complexity INTEGER, max_if_depth INTEGER)[],
            created_at        TIMESTAMP NOT NULL,
            PRIMARY KEY (run_id, iteration, policy_version_id)
        );
        CREATE TABLE episodes (
            episode_id        VARCHAR PRIMARY KEY,     -- {run_id}.{iteration}.{kind}.{index}
            run_id            VARCHAR NOT NULL,
            iteration         INTEGER NOT NULL,
            kind              VARCHAR NOT NULL,        -- eval | train
            episode_index     INTEGER NOT NULL,
            game              VARCHAR NOT NULL,
            seed              BIGINT,
            policy_version_id VARCHAR NOT NULL,
            return            DOUBLE NOT NULL,
            length            INTEGER NOT NULL,        -- environment steps taken
            lives_lost        INTEGER NOT NULL,        -- lives lost; points conceded in games without lives
            end_reason        VARCHAR NOT NULL,        -- terminated | truncated | policy_error | timeout | crashed
            error             VARCHAR,
            max_steps         INTEGER,
            traced            BOOLEAN NOT NULL,
            sticky            DOUBLE,
            noop_max          INTEGER,
            started_at        TIMESTAMP,
            duration_s        DOUBLE NOT NULL,
            env_s             DOUBLE,                  -- time inside env.step
            policy_s          DOUBLE                   -- time inside the policy
        );
        CREATE TABLE steps (
            episode_id  VARCHAR NOT NULL,
            step        INTEGER NOT NULL,
            action      SMALLINT,                      -- NULL on the step where the policy failed
            reward      DOUBLE NOT NULL,
            score       DOUBLE NOT NULL,               -- cumulative reward after this step
            terminated  BOOLEAN NOT NULL,
            truncated   BOOLEAN NOT NULL,
            lives       SMALLINT,
            player_x    SMALLINT,
            player_y    SMALLINT,
            ball_x      SMALLINT,
            ball_y      SMALLINT,
            objects     STRUCT(key VARCHAR, idx SMALLINT, category VARCHAR, x SMALLINT, y SMALLINT,
                               w SMALLINT, h SMALLINT, dx SMALLINT, dy SMALLINT)[]
        );
        CREATE TABLE nodes (
            episode_id        VARCHAR NOT NULL,
            step              INTEGER NOT NULL,
            call_index        SMALLINT NOT NULL,
            function          VARCHAR NOT NULL,
            trainable         BOOLEAN NOT NULL,
            policy_version_id VARCHAR NOT NULL,
            inputs            JSON,
            output            JSON,
            exc_type          VARCHAR,
            exc_message       VARCHAR,
            exc_line          INTEGER,
            exc_source        VARCHAR,
            duration_us       BIGINT,
            parents           SMALLINT[]               -- call_index of the calls whose outputs it consumed
        );
        """,
    ),
]

MIGRATIONS.append(
    (
        2,
        "optimizer: iterations, llm_calls, feedback",
        """
        CREATE TABLE iterations (
            run_id              VARCHAR NOT NULL,
            iteration           INTEGER NOT NULL,       -- 0: the starting policy; k >= 1: after the k-th update
            policy_version_id   VARCHAR NOT NULL,       -- version evaluated in this iteration
            base_version_id     VARCHAR,                -- version the update started from
            update_status       VARCHAR NOT NULL,       -- initial | accepted | rejected | unchanged | llm_error
            rolled_back         BOOLEAN NOT NULL,       -- the next iteration starts from the best version
            llm_call_id         VARCHAR,
            train_episode_id    VARCHAR,
            eval_episode_ids    VARCHAR[],
            train_return        DOUBLE,
            score               DOUBLE,                 -- mean return of the evaluation episodes
            best_score          DOUBLE,                 -- best score so far in the run
            best_version_id     VARCHAR,
            best_iteration      INTEGER,
            started_at          TIMESTAMP,
            finished_at         TIMESTAMP,
            llm_s               DOUBLE,
            train_s             DOUBLE,
            eval_s              DOUBLE,
            wall_s              DOUBLE,
            PRIMARY KEY (run_id, iteration)
        );
        CREATE TABLE feedback (
            run_id      VARCHAR NOT NULL,
            iteration   INTEGER NOT NULL,
            mode        VARCHAR NOT NULL,               -- staged | rollout
            stage       VARCHAR NOT NULL,               -- high | medium | low
            score       DOUBLE,
            text        VARCHAR NOT NULL,
            PRIMARY KEY (run_id, iteration)
        );
        CREATE TABLE llm_calls (
            call_id             VARCHAR PRIMARY KEY,    -- ULID
            run_id              VARCHAR NOT NULL,
            iteration           INTEGER NOT NULL,
            purpose             VARCHAR NOT NULL,       -- update (repair: migration 14)
            created_at          TIMESTAMP NOT NULL,
            operation_name      VARCHAR NOT NULL,       -- gen_ai.operation.name (chat)
            provider_name       VARCHAR,                -- gen_ai.provider.name (openai, anthropic, local, replay)
            request_model       VARCHAR NOT NULL,       -- gen_ai.request.model
            response_model      VARCHAR,                -- gen_ai.response.model
            request_temperature DOUBLE,                 -- gen_ai.request.temperature
            request_max_tokens  INTEGER,                -- gen_ai.request.max_tokens
            request_seed        BIGINT,                 -- gen_ai.request.seed
            request_params      JSON,                   -- every parameter sent (api_base, timeout, ...)
            prompt_hash         VARCHAR NOT NULL,       -- blobs.hash of the canonical JSON of the messages
            reply_hash          VARCHAR,                -- blobs.hash of the reply text
            suggestion_hash     VARCHAR,                -- blobs.hash of the parsed suggestion (JSON)
            parse_error         VARCHAR,
            response_id         VARCHAR,                -- gen_ai.response.id
            finish_reasons      VARCHAR[],              -- gen_ai.response.finish_reasons
            input_tokens        INTEGER,                -- gen_ai.usage.input_tokens
            output_tokens       INTEGER,                -- gen_ai.usage.output_tokens
            prompt_tokens_counted INTEGER,              -- our own count of the prompt, against the budget
            cost_usd            DOUBLE,
            latency_s           DOUBLE,
            attempts            INTEGER NOT NULL,
            error_type          VARCHAR,                -- error.type
            error_message       VARCHAR,
            replayed            BOOLEAN NOT NULL        -- the reply came from the store, not a model
        );
        """,
    )
)

# Views for people (``codearcade sql``, ``runs``, ``report``, any DuckDB client); documented in docs/schema.md.
# A view is stored SQL: a later change is a new migration with CREATE OR REPLACE VIEW, never an edit here.
MIGRATIONS.append(
    (
        3,
        "views: learning_curve, code_metrics, llm_usage, rejected_candidates, run_summary",
        r"""
        CREATE VIEW learning_curve AS
        WITH calls AS (
            SELECT run_id, iteration, count(*) AS llm_calls,
                   coalesce(sum(input_tokens), 0) AS input_tokens,
                   coalesce(sum(output_tokens), 0) AS output_tokens
            FROM llm_calls GROUP BY run_id, iteration
        )
        SELECT i.run_id, i.iteration, i.score, i.best_score, i.best_iteration, i.train_return, i.update_status,
               i.rolled_back, i.policy_version_id, i.best_version_id,
               coalesce(c.llm_calls, 0)::INTEGER AS llm_calls,
               coalesce(c.input_tokens, 0)::BIGINT AS input_tokens,
               coalesce(c.output_tokens, 0)::BIGINT AS output_tokens,
               (coalesce(c.input_tokens, 0) + coalesce(c.output_tokens, 0))::BIGINT AS total_tokens,
               sum(coalesce(c.input_tokens, 0) + coalesce(c.output_tokens, 0))
                   OVER (PARTITION BY i.run_id ORDER BY i.iteration)::BIGINT AS cumulative_tokens,
               i.llm_s, i.train_s, i.eval_s, i.wall_s,
               sum(i.wall_s) OVER (PARTITION BY i.run_id ORDER BY i.iteration) AS elapsed_s,
               i.started_at, i.finished_at
        FROM iterations i
        LEFT JOIN calls c ON c.run_id = i.run_id AND c.iteration = i.iteration;

        CREATE VIEW code_metrics AS
        WITH versions AS (  -- one row per (run, accepted version): a version can recur (rollback, unchanged)
            SELECT run_id, policy_version_id, min(iteration) AS version_iteration,
                   any_value(loc) AS loc, any_value(sloc) AS sloc, any_value(complexity) AS complexity,
                   any_value(max_if_depth) AS max_if_depth,
                   any_value(list_sum(list_transform(list_filter(functions, lambda f: f.trainable),
                                                     lambda f: f.sloc))) AS trainable_sloc,
                   any_value(list_sum(list_transform(list_filter(functions, lambda f: f.trainable),
                                                     lambda f: f.complexity))) AS trainable_complexity
            FROM policy_versions WHERE validation = 'accepted'
            GROUP BY run_id, policy_version_id
        )
        SELECT i.run_id, i.iteration, i.policy_version_id, v.version_iteration, i.update_status, i.score,
               v.loc, v.sloc, v.complexity, v.max_if_depth,
               v.trainable_sloc::INTEGER AS trainable_sloc, v.trainable_complexity::INTEGER AS trainable_complexity
        FROM iterations i
        LEFT JOIN versions v ON v.run_id = i.run_id AND v.policy_version_id = i.policy_version_id;

        CREATE VIEW llm_usage AS
        SELECT r.run_id, r.kind, r.model,
               count(c.call_id)::INTEGER AS calls,
               count(c.error_type)::INTEGER AS errors,
               count(c.parse_error)::INTEGER AS parse_errors,
               (count(c.call_id) FILTER (WHERE c.replayed))::INTEGER AS replayed,
               coalesce(sum(c.input_tokens), 0)::BIGINT AS input_tokens,
               coalesce(sum(c.output_tokens), 0)::BIGINT AS output_tokens,
               (coalesce(sum(c.input_tokens), 0) + coalesce(sum(c.output_tokens), 0))::BIGINT AS total_tokens,
               sum(c.cost_usd) AS cost_usd,
               coalesce(sum(c.latency_s), 0) AS latency_s,
               avg(c.latency_s) AS mean_latency_s,
               max(c.latency_s) AS max_latency_s,
               coalesce(sum(c.attempts), 0)::INTEGER AS attempts,
               (coalesce(sum(c.attempts), 0) - count(c.call_id))::INTEGER AS retries,
               string_agg(DISTINCT c.request_model, ', ' ORDER BY c.request_model) AS request_models
        FROM runs r
        LEFT JOIN llm_calls c ON c.run_id = r.run_id
        GROUP BY r.run_id, r.kind, r.model;

        CREATE VIEW rejected_candidates AS
        SELECT v.run_id, v.iteration,
               coalesce(i.llm_call_id, (SELECT max(c.call_id) FROM llm_calls c WHERE c.run_id = v.run_id
                                        AND c.iteration = v.iteration AND c.error_type IS NULL)) AS llm_call_id,
               v.policy_version_id, 'runtime' AS stage, v.validation_error AS reason
        FROM policy_versions v
        LEFT JOIN iterations i ON i.run_id = v.run_id AND i.iteration = v.iteration
        WHERE v.validation = 'rejected'
        UNION ALL
        SELECT i.run_id, i.iteration, i.llm_call_id, NULL AS policy_version_id,
               CASE WHEN c.parse_error IS NOT NULL THEN 'parse' ELSE 'static' END AS stage,
               coalesce(c.parse_error,
                        nullif(regexp_extract(f.text, 'Your last suggestion was rejected: ([^\n]*)', 1), ''),
                        f.text) AS reason
        FROM iterations i
        LEFT JOIN llm_calls c ON c.call_id = i.llm_call_id
        LEFT JOIN feedback f ON f.run_id = i.run_id AND f.iteration = i.iteration
        WHERE i.update_status = 'rejected'
          AND NOT EXISTS (SELECT 1 FROM policy_versions v WHERE v.run_id = i.run_id AND v.iteration = i.iteration
                          AND v.validation = 'rejected');

        CREATE VIEW run_summary AS
        WITH it AS (
            SELECT run_id, (count(*) FILTER (WHERE iteration >= 1))::INTEGER AS iterations_done,
                   max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max(score, iteration) AS last_score
            FROM iterations GROUP BY run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval') AS mean_eval_return
            FROM episodes GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        )
        SELECT r.run_id, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind = 'eval' THEN ep.mean_eval_return ELSE it.best_score END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id;
        """,
    )
)

# The untrusted-code boundary (issue 13): each episode's score is checked by replaying its actions in the parent
# (pipeline/play/verify.py). Rows written before this migration keep verified NULL (never checked).
MIGRATIONS.append(
    (
        4,
        "episodes: verified, verify_error (score verification by replay)",
        """
        ALTER TABLE episodes ADD COLUMN verified BOOLEAN;
        ALTER TABLE episodes ADD COLUMN verify_error VARCHAR;
        """,
    )
)

MIGRATIONS.append(
    (
        5,
        "prompt caching in llm_calls; llm_usage counts cached tokens and the runs stopped by a budget",
        r"""
        ALTER TABLE llm_calls ADD COLUMN cached_input_tokens INTEGER;   -- gen_ai.usage.cache_read.input_tokens
        ALTER TABLE llm_calls ADD COLUMN cache_creation_input_tokens INTEGER;  -- gen_ai.usage.cache_creation.input_tokens
        CREATE OR REPLACE VIEW llm_usage AS
        SELECT r.run_id, r.kind, r.model,
               count(c.call_id)::INTEGER AS calls,
               count(c.error_type)::INTEGER AS errors,
               count(c.parse_error)::INTEGER AS parse_errors,
               (count(c.call_id) FILTER (WHERE c.replayed))::INTEGER AS replayed,
               coalesce(sum(c.input_tokens), 0)::BIGINT AS input_tokens,
               coalesce(sum(c.output_tokens), 0)::BIGINT AS output_tokens,
               (coalesce(sum(c.input_tokens), 0) + coalesce(sum(c.output_tokens), 0))::BIGINT AS total_tokens,
               coalesce(sum(c.cached_input_tokens), 0)::BIGINT AS cached_input_tokens,
               coalesce(sum(c.cache_creation_input_tokens), 0)::BIGINT AS cache_creation_input_tokens,
               sum(c.cost_usd) AS cost_usd,
               coalesce(sum(c.latency_s), 0) AS latency_s,
               avg(c.latency_s) AS mean_latency_s,
               max(c.latency_s) AS max_latency_s,
               coalesce(sum(c.attempts), 0)::INTEGER AS attempts,
               (coalesce(sum(c.attempts), 0) - count(c.call_id))::INTEGER AS retries,
               string_agg(DISTINCT c.request_model, ', ' ORDER BY c.request_model) AS request_models
        FROM runs r
        LEFT JOIN llm_calls c ON c.run_id = r.run_id
        GROUP BY r.run_id, r.kind, r.model;
        """,
    )
)

# Search strategies (issue 15): an iteration may assess several candidates. Each is a ``candidates`` row: the
# version it improved (its parent), the LLM call that made it, the version it proposed and the one assessed for it
# (its parent again when the proposal was rejected or unchanged), where its episodes came from (played, or
# reused from an earlier assessment of the same version: the evaluation cache), its score, and the strategy's
# decision. ``iterations`` keeps one row per iteration: the candidate the strategy chose. Runs made before this
# migration had one candidate per iteration: they are copied in as candidate 0, so every run has its lineage.
MIGRATIONS.append(
    (
        6,
        "candidates (several per iteration, with parents and the strategy's decision); lineage and frontier views",
        r"""
        ALTER TABLE llm_calls ADD COLUMN candidate INTEGER DEFAULT 0;  -- which of an iteration's proposals
        ALTER TABLE iterations ADD COLUMN candidate INTEGER DEFAULT 0; -- the candidate the strategy chose
        ALTER TABLE policy_versions ADD COLUMN llm_call_id VARCHAR;     -- the call whose reply it is (produced_by llm)
        UPDATE policy_versions v SET llm_call_id = i.llm_call_id
        FROM iterations i
        WHERE v.produced_by = 'llm' AND i.run_id = v.run_id AND i.iteration = v.iteration;
        CREATE TABLE candidates (
            run_id              VARCHAR NOT NULL,
            iteration           INTEGER NOT NULL,
            candidate           INTEGER NOT NULL,       -- 0, 1, ... within the iteration
            strategy            VARCHAR NOT NULL,       -- greedy | best-of-n | beam
            parent_iteration    INTEGER,                -- the candidate it improved: (parent_iteration, parent_candidate)
            parent_candidate    INTEGER,
            parent_version_id   VARCHAR,
            proposed_version_id VARCHAR,                -- the code the reply proposed (NULL: no usable code)
            policy_version_id   VARCHAR NOT NULL,       -- the version assessed for it
            llm_call_id         VARCHAR,
            update_status       VARCHAR NOT NULL,       -- initial | accepted | rejected | unchanged | llm_error
            evaluation          VARCHAR NOT NULL,       -- played | cached (an earlier assessment's episodes) | screened
            train_episode_id    VARCHAR,
            eval_episode_ids    VARCHAR[],
            train_return        DOUBLE,
            score               DOUBLE,                 -- the score the run optimizes (one of the two below)
            deterministic_score DOUBLE,                 -- mean return under the paper's protocol (sticky 0)
            standard_score      DOUBLE,                 -- mean return under the standard one (sticky 0.25, no-op starts)
            robust_episode_ids  VARCHAR[],              -- the standard-protocol evaluation episodes (kind robust)
            screen_episode_id   VARCHAR,                -- cascade: its short screening game (kind screen)
            screen_score        DOUBLE,                 -- its return in that game
            screen_bar          DOUBLE,                 -- what it had to reach: the parent's score at that step
            decision            VARCHAR NOT NULL,       -- best | kept | discarded | rolled_back | rejected
            feedback_hash       VARCHAR,                -- blobs.hash of the feedback text shown when it is improved
            created_at          TIMESTAMP NOT NULL,
            PRIMARY KEY (run_id, iteration, candidate)
        );
        INSERT INTO blobs (hash, kind, text, chars)
        SELECT DISTINCT sha256(text), 'feedback', text, length(text) FROM feedback
        ON CONFLICT DO NOTHING;
        INSERT INTO candidates BY NAME
        SELECT i.run_id, i.iteration, 0 AS candidate, 'greedy' AS strategy,
               p.iteration AS parent_iteration, CASE WHEN p.iteration IS NULL THEN NULL ELSE 0 END AS parent_candidate,
               i.base_version_id AS parent_version_id,
               CASE WHEN i.update_status IN ('accepted', 'initial') THEN i.policy_version_id END AS proposed_version_id,
               i.policy_version_id, i.llm_call_id, i.update_status, 'played' AS evaluation,
               i.train_episode_id, i.eval_episode_ids, i.train_return, i.score, i.score AS deterministic_score,
               CASE WHEN i.update_status = 'rejected' THEN 'rejected'
                    WHEN i.rolled_back THEN 'rolled_back'
                    WHEN i.best_iteration = i.iteration THEN 'best' ELSE 'kept' END AS decision,
               sha256(f.text) AS feedback_hash, coalesce(i.finished_at, now()) AS created_at
        FROM iterations i
        LEFT JOIN feedback f ON f.run_id = i.run_id AND f.iteration = i.iteration
        LEFT JOIN iterations prev ON prev.run_id = i.run_id AND prev.iteration = i.iteration - 1
        LEFT JOIN iterations p ON p.run_id = i.run_id
             AND p.iteration = CASE WHEN prev.rolled_back THEN prev.best_iteration ELSE prev.iteration END;

        CREATE OR REPLACE VIEW lineage AS  -- one row per candidate: an edge to the candidate it improved
        SELECT c.run_id, c.iteration, c.candidate, c.strategy, c.policy_version_id, c.proposed_version_id,
               c.parent_iteration, c.parent_candidate, c.parent_version_id, c.update_status, c.evaluation,
               c.score, c.deterministic_score, c.standard_score, p.score AS parent_score, c.score - p.score AS gain, c.decision, c.llm_call_id,
               v.loc, v.complexity
        FROM candidates c
        LEFT JOIN candidates p ON p.run_id = c.run_id AND p.iteration = c.parent_iteration
             AND p.candidate = c.parent_candidate
        LEFT JOIN policy_versions v ON v.run_id = c.run_id AND v.iteration = c.iteration
             AND v.policy_version_id = c.policy_version_id;

        CREATE OR REPLACE VIEW frontier AS  -- each distinct assessed version once, with its score and rank in the run
        WITH versions AS (
            SELECT run_id, policy_version_id, max(score) AS score, max(deterministic_score) AS deterministic_score,
                   max(standard_score) AS standard_score, min(iteration) AS first_iteration,
                   count(*) AS assessments, count(*) FILTER (WHERE evaluation = 'cached') AS cached
            FROM candidates  -- not a version caught tampering (assessed, then rejected)
            WHERE NOT (decision = 'rejected' AND policy_version_id IS NOT DISTINCT FROM proposed_version_id)
            GROUP BY run_id, policy_version_id
        )
        SELECT v.*, rank() OVER (PARTITION BY v.run_id ORDER BY v.score DESC NULLS LAST) AS rank,
               m.loc, m.complexity
        FROM versions v
        LEFT JOIN (SELECT run_id, policy_version_id, any_value(loc) AS loc, any_value(complexity) AS complexity
                   FROM policy_versions GROUP BY ALL) m
               ON m.run_id = v.run_id AND m.policy_version_id = v.policy_version_id;
        """,
    )
)

# Line provenance (issue 16, items 1-2): blame per line of every version's trainable methods, and the lines each
# traced call ran.
MIGRATIONS.append(
    (
        7,
        "line provenance: policy_lines (blame), nodes.lines_run; views line_blame, node_lines, line_coverage, "
        "unrun_lines",
        r"""
        ALTER TABLE nodes ADD COLUMN lines_run SMALLINT[];  -- lines of the method's source that ran in the call
        CREATE TABLE policy_lines (
            run_id              VARCHAR NOT NULL,
            policy_version_id   VARCHAR NOT NULL,
            function            VARCHAR NOT NULL,       -- a trainable method of the version
            line_no             INTEGER NOT NULL,       -- 1-based within the method's source (its def line is 1)
            text                VARCHAR NOT NULL,
            executable          BOOLEAN NOT NULL,       -- holds code (not blank, comment, docstring, the def line)
            origin_version_id   VARCHAR NOT NULL,       -- the version that introduced the line
            origin_iteration    INTEGER NOT NULL,       -- the iteration that first stored that version
            origin_produced_by  VARCHAR NOT NULL,       -- how that version was made: file | initial | llm | rollback
            PRIMARY KEY (run_id, policy_version_id, function, line_no)
        );

        CREATE VIEW line_blame AS
        WITH calls AS (  -- the call whose reply a version is (policy_versions.llm_call_id, migration 6)
            SELECT run_id, iteration, policy_version_id, any_value(llm_call_id) AS call_id FROM policy_versions
            WHERE produced_by = 'llm' GROUP BY ALL
        )
        SELECT l.run_id, l.policy_version_id, l.function, l.line_no, l.text, l.executable,
               l.origin_version_id, l.origin_iteration, l.origin_produced_by,
               CASE WHEN l.origin_produced_by = 'llm' THEN c.call_id END AS origin_call_id
        FROM policy_lines l
        LEFT JOIN calls c ON c.run_id = l.run_id AND c.iteration = l.origin_iteration
                          AND c.policy_version_id = l.origin_version_id;

        CREATE VIEW node_lines AS
        SELECT e.run_id, e.iteration, e.kind, n.episode_id, n.step, n.call_index, n.function, n.policy_version_id,
               r.line_no::INTEGER AS line_no, l.text
        FROM nodes n
        JOIN episodes e ON e.episode_id = n.episode_id
        CROSS JOIN unnest(n.lines_run) AS r(line_no)
        LEFT JOIN policy_lines l ON l.run_id = e.run_id AND l.policy_version_id = n.policy_version_id
                                 AND l.function = n.function AND l.line_no = r.line_no;

        CREATE VIEW line_coverage AS
        WITH traced AS (
            SELECT episode_id, function, count(*)::INTEGER AS calls FROM nodes
            WHERE lines_run IS NOT NULL GROUP BY episode_id, function
        ), ran AS (
            SELECT episode_id, function, line_no::INTEGER AS line_no, count(*)::INTEGER AS times_ran
            FROM (SELECT episode_id, function, unnest(lines_run) AS line_no FROM nodes WHERE lines_run IS NOT NULL)
            GROUP BY episode_id, function, line_no
        )
        SELECT e.run_id, e.iteration, e.kind, e.episode_id, e.policy_version_id, l.function, l.line_no, l.text,
               l.executable, t.calls, coalesce(r.times_ran, 0) AS times_ran
        FROM episodes e
        JOIN traced t ON t.episode_id = e.episode_id
        JOIN policy_lines l ON l.run_id = e.run_id AND l.policy_version_id = e.policy_version_id
                            AND l.function = t.function
        LEFT JOIN ran r ON r.episode_id = e.episode_id AND r.function = l.function AND r.line_no = l.line_no;

        CREATE VIEW unrun_lines AS
        SELECT run_id, policy_version_id, function, line_no, any_value(text) AS text,
               count(DISTINCT episode_id)::INTEGER AS episodes, sum(calls)::BIGINT AS calls
        FROM line_coverage WHERE executable
        GROUP BY run_id, policy_version_id, function, line_no
        HAVING sum(times_ran) = 0;
        """,
    )
)

# How each reply was read (issue 25, item 5): the parser (pipeline/optimizer/reply.py) recovers near-misses and says so.
# Rows written before keep NULL, except replies the parser of the day refused (parse_error set), which were
# 'unusable' then whatever a re-read would give now: the column records what the run did with the reply.
MIGRATIONS.append(
    (
        8,
        "llm_calls: reply_reading (structured | parsed | repaired | unusable), reply_repairs",
        """
        ALTER TABLE llm_calls ADD COLUMN reply_reading VARCHAR;    -- structured | parsed | repaired | unusable
        ALTER TABLE llm_calls ADD COLUMN reply_repairs VARCHAR[];  -- the near-misses recovered (repaired replies)
        UPDATE llm_calls SET reply_reading = 'unusable' WHERE parse_error IS NOT NULL AND reply_hash IS NOT NULL;
        """,
    )
)

# The authors' published scores (issue 25, item 6): facts of each game, kept in its module (games/<game>.py,
# Task.published). This table holds a copy for SQL, refilled from the game modules whenever a process first
# writes to the store (store/published.py), so it follows the code that wrote the store.
MIGRATIONS.append(
    (
        9,
        "published_scores: the authors' published figures, per game, from the game modules",
        """
        CREATE TABLE published_scores (
            game        VARCHAR NOT NULL,
            source      VARCHAR NOT NULL,   -- paper (Kuang et al. 2025, Table 1) | follow-up (arXiv 2603.23994)
            setting     VARCHAR NOT NULL,   -- paper | default | h1 | h100 (training horizon 1 or 100 steps)
            horizon     INTEGER,            -- training rollout steps of that setting
            trials      INTEGER NOT NULL,   -- runs the figure is the mean of
            score       DOUBLE NOT NULL,    -- best-so-far evaluation return (mean over the trials)
            stderr      DOUBLE,             -- its standard error over the trials (NULL: one trial)
            PRIMARY KEY (game, setting)
        );
        """,
    )
)

# Runs as people address and tell them apart (issue 24): a label per run, a mark on the runs a command made for
# its own use (compare's evaluations of two versions), run_summary with the settings that tell runs apart, and a
# one-line description of every table and view (DuckDB comments: `codearcade sql --schema` lists them, and so does
# any DuckDB client: SELECT table_name, comment FROM duckdb_tables()). Eval runs that compare made before this
# migration are found by the temporary policy file it played them from.
MIGRATIONS.append(
    (
        10,
        "runs: name (a label), made_by (compare's own eval runs); run_summary tells runs apart; comments on every "
        "table and view",
        r"""
        ALTER TABLE runs ADD COLUMN name VARCHAR;     -- a label: --name, or a batch entry's
        ALTER TABLE runs ADD COLUMN made_by VARCHAR;  -- NULL: a person's command; compare: played by codearcade compare
        UPDATE runs SET made_by = 'compare'
        WHERE kind = 'eval' AND json_extract_string(config, '$.policy') LIKE '%codearcade-compare-%';

        CREATE OR REPLACE VIEW run_summary AS
        WITH it AS (
            SELECT run_id, (count(*) FILTER (WHERE iteration >= 1))::INTEGER AS iterations_done,
                   max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max(score, iteration) AS last_score
            FROM iterations GROUP BY run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval') AS mean_eval_return
            FROM episodes GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        )
        SELECT r.run_id, r.name, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               json_extract_string(r.config, '$.policy') AS policy,
               CASE WHEN r.kind <> 'eval' THEN coalesce(json_extract_string(r.config, '$.strategy'), 'greedy')
               END AS strategy,
               CASE WHEN r.kind <> 'eval' THEN json_extract_string(r.config, '$.feedback') END AS feedback,
               json_extract_string(r.config, '$.batch') AS batch,
               r.made_by,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind = 'eval' THEN ep.mean_eval_return ELSE it.best_score END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id;

        COMMENT ON TABLE schema_migrations IS 'the migrations applied to this store, in order: version, name, when';
        COMMENT ON TABLE blobs IS 'texts stored once by their SHA-256: policy files, method sources, prompts, replies, feedback';
        COMMENT ON TABLE runs IS 'one row per run (eval, optimize, replay): game, settings (config JSON), model, status, label (name)';
        COMMENT ON TABLE policy_versions IS 'every policy version a run used or considered: how it was made, its validation, code metrics';
        COMMENT ON TABLE episodes IS 'one row per played episode: return, length, lives lost, end reason, verification by replay';
        COMMENT ON TABLE steps IS 'one row per environment step: action, reward, score, lives and the whole object observation';
        COMMENT ON TABLE nodes IS 'one row per call of a bundled policy method in traced episodes: inputs, output, exception, lines run';
        COMMENT ON TABLE iterations IS 'one row per optimizer iteration: the chosen candidate, its score, the best so far, times';
        COMMENT ON TABLE feedback IS 'the feedback text of each iteration, as the next prompt shows it';
        COMMENT ON TABLE llm_calls IS 'every LLM call (OpenTelemetry gen_ai names): model, prompt and reply hashes, tokens, cost, latency, error';
        COMMENT ON TABLE candidates IS 'every candidate of every iteration: its parent, its evaluation (played, cached, screened), score, decision';
        COMMENT ON TABLE published_scores IS 'the authors'' published scores per game and setting, refilled from the game modules';
        COMMENT ON TABLE policy_lines IS 'every line of every version of the trainable methods, with the version that introduced it (blame)';
        COMMENT ON VIEW learning_curve IS 'one row per iteration: score, best so far, LLM calls and tokens, times';
        COMMENT ON VIEW code_metrics IS 'one row per iteration: lines, complexity and if depth of the version it evaluated (the paper Table 3)';
        COMMENT ON VIEW llm_usage IS 'one row per run: LLM calls, errors, retries, tokens (cached too), cost, latency';
        COMMENT ON VIEW rejected_candidates IS 'one row per rejected update: the stage (parse, static, runtime) and the reason';
        COMMENT ON VIEW run_summary IS 'one row per run, what codearcade runs prints: label, settings, status, best score, episodes, tokens';
        COMMENT ON VIEW lineage IS 'one row per candidate, with its edge to the candidate it improved and the score gained';
        COMMENT ON VIEW frontier IS 'each distinct version a run assessed, once, ranked by score';
        COMMENT ON VIEW line_blame IS 'policy_lines with the LLM call that wrote each line';
        COMMENT ON VIEW node_lines IS 'one row per line that ran in a traced call, with its text';
        COMMENT ON VIEW line_coverage IS 'one row per line of a trainable method per traced episode: in how many calls it ran';
        COMMENT ON VIEW unrun_lines IS 'the executable lines of a version that none of its traced calls in the run ran';
        """,
    )
)

# The authors' one-life protocol exactly (issue 25, item 3; `one_life = "continue"`): the evaluation episodes of a
# run are the lives of one game, each going on from where the one before ended. What makes such an episode
# reproducible is the episode it continues (replayed first, in the same environment) and where in the game it
# starts; an episode of any other run starts from reset(seed): continues NULL, start_step 0.
MIGRATIONS.append(
    (
        11,
        "episodes: continues, start_step (an episode that goes on with the game of another)",
        """
        ALTER TABLE episodes ADD COLUMN continues VARCHAR;              -- the episode whose game it goes on with
        ALTER TABLE episodes ADD COLUMN start_step INTEGER DEFAULT 0;   -- steps of its game played before it
        """,
    )
)


# Scores that mean what they say (issue 33): an episode the policy ended (policy_error, timeout, crashed, tampered)
# is a forfeit, and an assessment with a forfeit has no score to rank (store/scores.py is the rule): its ``score``
# (and the protocol's own score) is NULL, ``forfeit`` names what ended it and ``forfeit_score`` keeps the mean of
# the partial returns. ``score_low``/``score_high`` are the 95% bootstrap interval of ``score`` over its episodes.
# Runs stored before keep the scores they were recorded with; their forfeited candidates are named here.
MIGRATIONS.append(
    (
        12,
        "candidates: forfeit, forfeit_score, score_low, score_high; forfeits and intervals in learning_curve, "
        "lineage, frontier and run_summary",
        r"""
        ALTER TABLE candidates ADD COLUMN forfeit VARCHAR;        -- NULL: every episode played out; else what ended one
        ALTER TABLE candidates ADD COLUMN forfeit_score DOUBLE;   -- mean return with forfeits at their partial return
        ALTER TABLE candidates ADD COLUMN score_low DOUBLE;       -- 95% bootstrap interval of score over its episodes
        ALTER TABLE candidates ADD COLUMN score_high DOUBLE;
        UPDATE candidates c SET forfeit = f.forfeit, forfeit_score = c.score
        FROM (SELECT c2.run_id, c2.iteration, c2.candidate,
                     count(*)::VARCHAR || ' of ' || any_value(len(c2.eval_episode_ids))::VARCHAR
                         || ' episodes forfeited: ' || arg_min(e.end_reason, e.episode_id) || ' at step '
                         || arg_min(e.length, e.episode_id)::VARCHAR AS forfeit
              FROM candidates c2, unnest(c2.eval_episode_ids) AS u(episode_id)
              JOIN episodes e ON e.episode_id = u.episode_id
              WHERE e.end_reason NOT IN ('terminated', 'truncated')
              GROUP BY c2.run_id, c2.iteration, c2.candidate) f
        WHERE f.run_id = c.run_id AND f.iteration = c.iteration AND f.candidate = c.candidate
          AND c.evaluation <> 'screened';

        CREATE OR REPLACE VIEW learning_curve AS
        WITH calls AS (
            SELECT run_id, iteration, count(*) AS llm_calls,
                   coalesce(sum(input_tokens), 0) AS input_tokens,
                   coalesce(sum(output_tokens), 0) AS output_tokens
            FROM llm_calls GROUP BY run_id, iteration
        )
        SELECT i.run_id, i.iteration, i.score, i.best_score, i.best_iteration, i.train_return, i.update_status,
               i.rolled_back, i.policy_version_id, i.best_version_id,
               coalesce(c.llm_calls, 0)::INTEGER AS llm_calls,
               coalesce(c.input_tokens, 0)::BIGINT AS input_tokens,
               coalesce(c.output_tokens, 0)::BIGINT AS output_tokens,
               (coalesce(c.input_tokens, 0) + coalesce(c.output_tokens, 0))::BIGINT AS total_tokens,
               sum(coalesce(c.input_tokens, 0) + coalesce(c.output_tokens, 0))
                   OVER (PARTITION BY i.run_id ORDER BY i.iteration)::BIGINT AS cumulative_tokens,
               i.llm_s, i.train_s, i.eval_s, i.wall_s,
               sum(i.wall_s) OVER (PARTITION BY i.run_id ORDER BY i.iteration) AS elapsed_s,
               i.started_at, i.finished_at,
               k.score_low, k.score_high, k.forfeit, k.forfeit_score
        FROM iterations i
        LEFT JOIN calls c ON c.run_id = i.run_id AND c.iteration = i.iteration
        LEFT JOIN candidates k ON k.run_id = i.run_id AND k.iteration = i.iteration
             AND k.candidate = coalesce(i.candidate, 0);

        CREATE OR REPLACE VIEW lineage AS  -- one row per candidate: an edge to the candidate it improved
        SELECT c.run_id, c.iteration, c.candidate, c.strategy, c.policy_version_id, c.proposed_version_id,
               c.parent_iteration, c.parent_candidate, c.parent_version_id, c.update_status, c.evaluation,
               c.score, c.deterministic_score, c.standard_score, p.score AS parent_score, c.score - p.score AS gain, c.decision, c.llm_call_id,
               v.loc, v.complexity, c.score_low, c.score_high, c.forfeit, c.forfeit_score
        FROM candidates c
        LEFT JOIN candidates p ON p.run_id = c.run_id AND p.iteration = c.parent_iteration
             AND p.candidate = c.parent_candidate
        LEFT JOIN policy_versions v ON v.run_id = c.run_id AND v.iteration = c.iteration
             AND v.policy_version_id = c.policy_version_id;

        CREATE OR REPLACE VIEW frontier AS  -- each distinct assessed version once, with its score and rank in the run
        WITH versions AS (
            SELECT run_id, policy_version_id, max(score) AS score, max(deterministic_score) AS deterministic_score,
                   max(standard_score) AS standard_score, min(iteration) AS first_iteration,
                   count(*) AS assessments, count(*) FILTER (WHERE evaluation = 'cached') AS cached,
                   count(*) FILTER (WHERE forfeit IS NOT NULL) AS forfeited, any_value(forfeit) AS forfeit
            FROM candidates  -- not a version caught tampering (assessed, then rejected)
            WHERE NOT (decision = 'rejected' AND policy_version_id IS NOT DISTINCT FROM proposed_version_id)
            GROUP BY run_id, policy_version_id
        )
        SELECT v.* EXCLUDE (forfeited, forfeit),
               rank() OVER (PARTITION BY v.run_id ORDER BY v.forfeited > 0, v.score DESC NULLS LAST) AS rank,
               m.loc, m.complexity, v.forfeited, v.forfeit
        FROM versions v
        LEFT JOIN (SELECT run_id, policy_version_id, any_value(loc) AS loc, any_value(complexity) AS complexity
                   FROM policy_versions GROUP BY ALL) m
               ON m.run_id = v.run_id AND m.policy_version_id = v.policy_version_id;

        CREATE OR REPLACE VIEW run_summary AS
        WITH it AS (
            SELECT run_id, (count(*) FILTER (WHERE iteration >= 1))::INTEGER AS iterations_done,
                   max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max(score, iteration) AS last_score
            FROM iterations GROUP BY run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval' AND end_reason IN ('terminated', 'truncated'))
                       AS mean_eval_return,
                   (count(*) FILTER (WHERE kind = 'eval' AND end_reason NOT IN ('terminated', 'truncated')))::INTEGER
                       AS eval_forfeits
            FROM episodes GROUP BY run_id
        ), cand AS (
            SELECT run_id, (count(*) FILTER (WHERE forfeit IS NOT NULL))::INTEGER AS forfeits
            FROM candidates GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        )
        SELECT r.run_id, r.name, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               json_extract_string(r.config, '$.policy') AS policy,
               CASE WHEN r.kind <> 'eval' THEN coalesce(json_extract_string(r.config, '$.strategy'), 'greedy')
               END AS strategy,
               CASE WHEN r.kind <> 'eval' THEN json_extract_string(r.config, '$.feedback') END AS feedback,
               json_extract_string(r.config, '$.batch') AS batch,
               r.made_by,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind = 'eval' THEN ep.mean_eval_return ELSE it.best_score END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error,
               CASE WHEN r.kind = 'eval' THEN coalesce(ep.eval_forfeits, 0) ELSE coalesce(cand.forfeits, 0)
               END AS forfeits
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN cand ON cand.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id;

        COMMENT ON VIEW learning_curve IS 'one row per iteration: score (NULL: forfeited) with its interval, best so far, LLM calls and tokens, times';
        COMMENT ON VIEW run_summary IS 'one row per run, what codearcade runs prints: label, settings, status, best score, forfeits, episodes, tokens';
        COMMENT ON VIEW lineage IS 'one row per candidate, with its edge to the candidate it improved, the score gained and any forfeit';
        COMMENT ON VIEW frontier IS 'each distinct version a run assessed, once, ranked by score (forfeited ones last)';
        """,
    )
)

# The held-out audit (issue 33, item 2): when a run finishes (and on demand, `codearcade audit RUN`), its best
# version and its starting policy play games on seeds the loop never played (games.base.AUDIT_SEED_BASE + i; kind
# `audit` in `episodes`), under the standard protocol and the run's own. One row per (run, role, protocol), replaced
# by the next audit of the run; `overfit` (on the best's standard row) flags a run whose gain over its starter does
# not hold up on the held-out games (store/scores.py, `overfit`). run_summary shows the audit beside the tuning score.
MIGRATIONS.append(
    (
        13,
        "audits (the best version and the starter on held-out seeds); audit scores and the overfit flag in "
        "run_summary",
        r"""
        CREATE TABLE audits (
            run_id              VARCHAR NOT NULL,
            role                VARCHAR NOT NULL,    -- best | starter
            protocol            VARCHAR NOT NULL,    -- standard (sticky 0.25, up to 30 no-op starts) | run (its own)
            policy_version_id   VARCHAR NOT NULL,
            iteration           INTEGER NOT NULL,    -- the iteration whose version it is (0: the starter)
            seeds               BIGINT[] NOT NULL,
            episode_ids         VARCHAR[] NOT NULL,
            score               DOUBLE,              -- mean return of the games (NULL: one was forfeited)
            score_low           DOUBLE,              -- its 95% bootstrap interval
            score_high          DOUBLE,
            forfeit             VARCHAR,             -- what ended a forfeited game
            tuning_score        DOUBLE,              -- the version's score in the loop, on the tuning seeds
            overfit             BOOLEAN,             -- best, standard: its gain over the starter did not hold up
            created_at          TIMESTAMP NOT NULL,
            PRIMARY KEY (run_id, role, protocol)
        );
        COMMENT ON TABLE audits IS 'the held-out audit of each run: its best version and its starter on seeds the loop never played, under the standard protocol and its own';

        CREATE OR REPLACE VIEW run_summary AS
        WITH it AS (
            SELECT run_id, (count(*) FILTER (WHERE iteration >= 1))::INTEGER AS iterations_done,
                   max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max(score, iteration) AS last_score
            FROM iterations GROUP BY run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval' AND end_reason IN ('terminated', 'truncated'))
                       AS mean_eval_return,
                   (count(*) FILTER (WHERE kind = 'eval' AND end_reason NOT IN ('terminated', 'truncated')))::INTEGER
                       AS eval_forfeits
            FROM episodes GROUP BY run_id
        ), cand AS (
            SELECT run_id, (count(*) FILTER (WHERE forfeit IS NOT NULL))::INTEGER AS forfeits
            FROM candidates GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        ), audit AS (
            SELECT run_id,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_score,
                   any_value(score_low) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_low,
                   any_value(score_high) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_high,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'run') AS audit_run_score,
                   any_value(score) FILTER (WHERE role = 'starter' AND protocol = 'standard') AS starter_audit_score,
                   any_value(overfit) FILTER (WHERE role = 'best' AND protocol = 'standard') AS overfit
            FROM audits GROUP BY run_id
        )
        SELECT r.run_id, r.name, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               json_extract_string(r.config, '$.policy') AS policy,
               CASE WHEN r.kind <> 'eval' THEN coalesce(json_extract_string(r.config, '$.strategy'), 'greedy')
               END AS strategy,
               CASE WHEN r.kind <> 'eval' THEN json_extract_string(r.config, '$.feedback') END AS feedback,
               json_extract_string(r.config, '$.batch') AS batch,
               r.made_by,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind = 'eval' THEN ep.mean_eval_return ELSE it.best_score END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error,
               CASE WHEN r.kind = 'eval' THEN coalesce(ep.eval_forfeits, 0) ELSE coalesce(cand.forfeits, 0)
               END AS forfeits,
               audit.audit_score, audit.audit_low, audit.audit_high, audit.audit_run_score,
               audit.starter_audit_score, audit.overfit
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN cand ON cand.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id
        LEFT JOIN audit ON audit.run_id = r.run_id;
        COMMENT ON VIEW run_summary IS 'one row per run, what codearcade runs prints: label, settings, status, best score, forfeits, audit, episodes, tokens';
        """,
    )
)

# Repair turns (issue 32, item 1): a reply rejected before it is played goes back to the model with the exact error,
# in the same conversation, up to `repairs` times. Each repair is its own call (purpose `repair`), linked to the call
# it repairs (`repair_of`; `repair_turn` 1, 2, ...; a first call is turn 0); a candidate records how many turns its
# reply took (`repairs`) and its `llm_call_id` is the last of them. An update "saved by a repair" is a candidate
# accepted after at least one. learning_curve and run_summary count both.
MIGRATIONS.append(
    (
        14,
        "llm_calls: repair_of, repair_turn; candidates: repairs; repair calls and updates saved by a repair in "
        "learning_curve and run_summary",
        r"""
        ALTER TABLE llm_calls ADD COLUMN repair_of VARCHAR;               -- the call whose rejected reply it repairs
        ALTER TABLE llm_calls ADD COLUMN repair_turn INTEGER DEFAULT 0;   -- 0: a first call; n: the nth repair turn
        ALTER TABLE candidates ADD COLUMN repairs INTEGER DEFAULT 0;      -- repair turns its reply took

        CREATE OR REPLACE VIEW learning_curve AS
        WITH calls AS (
            SELECT run_id, iteration, count(*) AS llm_calls,
                   count(*) FILTER (WHERE purpose = 'repair') AS repair_calls,
                   coalesce(sum(input_tokens), 0) AS input_tokens,
                   coalesce(sum(output_tokens), 0) AS output_tokens
            FROM llm_calls GROUP BY run_id, iteration
        ), saved AS (
            SELECT run_id, iteration, count(*) FILTER (WHERE repairs > 0 AND update_status = 'accepted') AS saved
            FROM candidates GROUP BY run_id, iteration
        )
        SELECT i.run_id, i.iteration, i.score, i.best_score, i.best_iteration, i.train_return, i.update_status,
               i.rolled_back, i.policy_version_id, i.best_version_id,
               coalesce(c.llm_calls, 0)::INTEGER AS llm_calls,
               coalesce(c.input_tokens, 0)::BIGINT AS input_tokens,
               coalesce(c.output_tokens, 0)::BIGINT AS output_tokens,
               (coalesce(c.input_tokens, 0) + coalesce(c.output_tokens, 0))::BIGINT AS total_tokens,
               sum(coalesce(c.input_tokens, 0) + coalesce(c.output_tokens, 0))
                   OVER (PARTITION BY i.run_id ORDER BY i.iteration)::BIGINT AS cumulative_tokens,
               i.llm_s, i.train_s, i.eval_s, i.wall_s,
               sum(i.wall_s) OVER (PARTITION BY i.run_id ORDER BY i.iteration) AS elapsed_s,
               i.started_at, i.finished_at,
               k.score_low, k.score_high, k.forfeit, k.forfeit_score,
               coalesce(c.repair_calls, 0)::INTEGER AS repair_calls,
               coalesce(s.saved, 0)::INTEGER AS saved_by_repair,
               coalesce(k.repairs, 0)::INTEGER AS repairs
        FROM iterations i
        LEFT JOIN calls c ON c.run_id = i.run_id AND c.iteration = i.iteration
        LEFT JOIN candidates k ON k.run_id = i.run_id AND k.iteration = i.iteration
             AND k.candidate = coalesce(i.candidate, 0)
        LEFT JOIN saved s ON s.run_id = i.run_id AND s.iteration = i.iteration;


        CREATE OR REPLACE VIEW run_summary AS
        WITH it AS (
            SELECT run_id, (count(*) FILTER (WHERE iteration >= 1))::INTEGER AS iterations_done,
                   max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max(score, iteration) AS last_score
            FROM iterations GROUP BY run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval' AND end_reason IN ('terminated', 'truncated'))
                       AS mean_eval_return,
                   (count(*) FILTER (WHERE kind = 'eval' AND end_reason NOT IN ('terminated', 'truncated')))::INTEGER
                       AS eval_forfeits
            FROM episodes GROUP BY run_id
        ), cand AS (
            SELECT run_id, (count(*) FILTER (WHERE forfeit IS NOT NULL))::INTEGER AS forfeits,
                   (count(*) FILTER (WHERE repairs > 0 AND update_status = 'accepted'))::INTEGER AS saved_by_repair
            FROM candidates GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   (count(*) FILTER (WHERE purpose = 'repair'))::INTEGER AS repair_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        ), audit AS (
            SELECT run_id,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_score,
                   any_value(score_low) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_low,
                   any_value(score_high) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_high,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'run') AS audit_run_score,
                   any_value(score) FILTER (WHERE role = 'starter' AND protocol = 'standard') AS starter_audit_score,
                   any_value(overfit) FILTER (WHERE role = 'best' AND protocol = 'standard') AS overfit
            FROM audits GROUP BY run_id
        )
        SELECT r.run_id, r.name, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               json_extract_string(r.config, '$.policy') AS policy,
               CASE WHEN r.kind <> 'eval' THEN coalesce(json_extract_string(r.config, '$.strategy'), 'greedy')
               END AS strategy,
               CASE WHEN r.kind <> 'eval' THEN json_extract_string(r.config, '$.feedback') END AS feedback,
               json_extract_string(r.config, '$.batch') AS batch,
               r.made_by,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind = 'eval' THEN ep.mean_eval_return ELSE it.best_score END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error,
               CASE WHEN r.kind = 'eval' THEN coalesce(ep.eval_forfeits, 0) ELSE coalesce(cand.forfeits, 0)
               END AS forfeits,
               audit.audit_score, audit.audit_low, audit.audit_high, audit.audit_run_score,
               audit.starter_audit_score, audit.overfit,
               coalesce(calls.repair_calls, 0) AS repair_calls, coalesce(cand.saved_by_repair, 0) AS saved_by_repair
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN cand ON cand.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id
        LEFT JOIN audit ON audit.run_id = r.run_id;
        COMMENT ON VIEW learning_curve IS 'one row per iteration: score (NULL: forfeited) with its interval, best so far, LLM calls (repairs among them), updates saved by a repair, tokens, times';
        COMMENT ON VIEW run_summary IS 'one row per run, what codearcade runs prints: label, settings, status, best score, forfeits, audit, episodes, tokens, repairs';
        """,
    )
)

# Model ensembles (issue 32): one row per (run, model) with what its calls brought. A candidate counts for the
# model of its llm_calls row; it improved when it was accepted and scored above its parent (or its parent forfeited):
# the rule of store/scores.py `beats`, as pipeline/optimizer/ensemble.py rewards the models.
MIGRATIONS.append(
    (
        15,
        "model_stats: per run and model, calls, share, accepted candidates, improvements, cost and latency",
        r"""
        CREATE VIEW model_stats AS
        WITH calls AS (
            SELECT run_id, request_model AS model, count(*)::INTEGER AS calls,
                   count(error_type)::INTEGER AS errors,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd,
                   coalesce(sum(latency_s), 0) AS latency_s,
                   avg(latency_s) AS mean_latency_s
            FROM llm_calls GROUP BY run_id, request_model
        ), cand AS (
            SELECT c.run_id, l.request_model AS model, count(*)::INTEGER AS candidates,
                   (count(*) FILTER (WHERE c.update_status = 'accepted'))::INTEGER AS accepted,
                   (count(*) FILTER (WHERE c.update_status = 'accepted' AND c.score IS NOT NULL
                                     AND (p.score IS NULL OR c.score > p.score)))::INTEGER AS improvements,
                   coalesce(sum(c.score - p.score) FILTER (WHERE c.update_status = 'accepted'
                                                          AND c.score > p.score), 0) AS gain
            FROM candidates c
            JOIN llm_calls l ON l.call_id = c.llm_call_id
            LEFT JOIN candidates p ON p.run_id = c.run_id AND p.iteration = c.parent_iteration
                                  AND p.candidate = coalesce(c.parent_candidate, 0)
            GROUP BY c.run_id, l.request_model
        )
        SELECT calls.run_id, calls.model, calls.calls,
               calls.calls / sum(calls.calls) OVER (PARTITION BY calls.run_id) AS share,
               calls.errors, coalesce(cand.candidates, 0) AS candidates, coalesce(cand.accepted, 0) AS accepted,
               coalesce(cand.improvements, 0) AS improvements, coalesce(cand.gain, 0) AS gain,
               calls.input_tokens, calls.output_tokens, calls.cost_usd,
               calls.cost_usd / nullif(cand.improvements, 0) AS cost_per_improvement,
               calls.latency_s, calls.mean_latency_s
        FROM calls LEFT JOIN cand ON cand.run_id = calls.run_id AND cand.model = calls.model;
        COMMENT ON VIEW model_stats IS 'one row per run and model it called (an ensemble has several): calls, share, accepted candidates, improvements over the parent, cost, latency';
        """,
    )
)

# The asynchronous proposal pool (issue 32, item 3; `pool`): a call of iteration i may start before iteration i - 1
# is committed, its prompt built from the iterations committed then. `history_iterations` records how many that was
# (its prompt saw iterations 0 .. n-1), so that --resume and `codearcade replay` build the same prompt again. Runs
# without the pool build every prompt of iteration i from iterations 0 .. i-1: the column says so for them too.
MIGRATIONS.append(
    (
        16,
        "llm_calls: history_iterations (the iterations its prompt was built from: the proposal pool)",
        r"""
        ALTER TABLE llm_calls ADD COLUMN history_iterations INTEGER;  -- its prompt saw iterations 0 .. n-1
        UPDATE llm_calls SET history_iterations = iteration;
        """,
    )
)

# One rule, every reader (issue 37, item 1): a set of episodes with a forfeit has no score (store/scores.py). An eval
# run that forfeited an episode has no score in run_summary either: its best_score is NULL (it was the mean of the
# episodes played out, which ranked a policy that quits when it is losing above one that plays on), and `forfeits`
# counts the episodes it forfeited. last_score is the latest iteration's score, NULL when that one forfeited (it was
# the latest score that was not NULL: an earlier iteration's).
MIGRATIONS.append(
    (
        17,
        "run_summary: an eval run with a forfeited episode has no score (best_score NULL); last_score is the latest "
        "iteration's, NULL when it forfeited",
        r"""
        CREATE OR REPLACE VIEW run_summary AS
        WITH it AS (
            SELECT run_id, (count(*) FILTER (WHERE iteration >= 1))::INTEGER AS iterations_done,
                   max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max_null(score, iteration) AS last_score
            FROM iterations GROUP BY run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval' AND end_reason IN ('terminated', 'truncated'))
                       AS mean_eval_return,
                   (count(*) FILTER (WHERE kind = 'eval' AND end_reason NOT IN ('terminated', 'truncated')))::INTEGER
                       AS eval_forfeits
            FROM episodes GROUP BY run_id
        ), cand AS (
            SELECT run_id, (count(*) FILTER (WHERE forfeit IS NOT NULL))::INTEGER AS forfeits,
                   (count(*) FILTER (WHERE repairs > 0 AND update_status = 'accepted'))::INTEGER AS saved_by_repair
            FROM candidates GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   (count(*) FILTER (WHERE purpose = 'repair'))::INTEGER AS repair_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        ), audit AS (
            SELECT run_id,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_score,
                   any_value(score_low) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_low,
                   any_value(score_high) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_high,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'run') AS audit_run_score,
                   any_value(score) FILTER (WHERE role = 'starter' AND protocol = 'standard') AS starter_audit_score,
                   any_value(overfit) FILTER (WHERE role = 'best' AND protocol = 'standard') AS overfit
            FROM audits GROUP BY run_id
        )
        SELECT r.run_id, r.name, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               json_extract_string(r.config, '$.policy') AS policy,
               CASE WHEN r.kind <> 'eval' THEN coalesce(json_extract_string(r.config, '$.strategy'), 'greedy')
               END AS strategy,
               CASE WHEN r.kind <> 'eval' THEN json_extract_string(r.config, '$.feedback') END AS feedback,
               json_extract_string(r.config, '$.batch') AS batch,
               r.made_by,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind <> 'eval' THEN it.best_score
                    WHEN coalesce(ep.eval_forfeits, 0) = 0 THEN ep.mean_eval_return END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error,
               CASE WHEN r.kind = 'eval' THEN coalesce(ep.eval_forfeits, 0) ELSE coalesce(cand.forfeits, 0)
               END AS forfeits,
               audit.audit_score, audit.audit_low, audit.audit_high, audit.audit_run_score,
               audit.starter_audit_score, audit.overfit,
               coalesce(calls.repair_calls, 0) AS repair_calls, coalesce(cand.saved_by_repair, 0) AS saved_by_repair
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN cand ON cand.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id
        LEFT JOIN audit ON audit.run_id = r.run_id;
        COMMENT ON VIEW run_summary IS 'one row per run, what codearcade runs prints: label, settings, status, best score (NULL: forfeited), forfeits, audit, episodes, tokens, repairs';
        """,
    )
)

# The budgeted bandit (issue 39, item 1): each first call of an ensemble's candidate records why its model was
# chosen (the estimates the rule compared: pipeline/optimizer/bandit.py); the view reads the JSON into columns.
MIGRATIONS.append(
    (
        18,
        "llm_calls: model_choice (why an ensemble chose the call's model); view model_choices",
        r"""
        ALTER TABLE llm_calls ADD COLUMN model_choice JSON;  -- NULL: one model, a repair turn, or stored before
        CREATE VIEW model_choices AS
        SELECT run_id, iteration, coalesce(candidate, 0) AS candidate, call_id, request_model AS model,
               json_extract_string(model_choice, '$.rule') AS rule,
               json_extract_string(model_choice, '$.budget') AS budget,
               json_extract_string(model_choice, '$.why') AS why,
               TRY_CAST(json_extract(model_choice, '$.level') AS DOUBLE) AS level,
               TRY_CAST(json_extract(model_choice, '$.pulls_left') AS DOUBLE) AS pulls_left,
               json_extract(model_choice, '$.models') AS models
        FROM llm_calls WHERE model_choice IS NOT NULL;
        COMMENT ON VIEW model_choices IS 'one row per model an ensemble chose: rule, the budget that bound the run, why, and per model the pulls, mean reward, cost per pull and index compared';
        """,
    )
)

# The proposal pool prompts from the freshest state (issue 39, item 2): a candidate's basis is the iterations committed
# when it starts and the candidates already assessed in iterations not committed yet. Each call records those
# candidates and when its basis was taken, and each candidate when the pool learnt its assessment, so that --resume
# and `codearcade replay` rebuild every prompt, and anyone can check that no call left out a candidate assessed
# before it started. NULL: a call or candidate of the barrier loop, or stored before.
MIGRATIONS.append(
    (
        21,
        "llm_calls: basis_candidates, basis_at; candidates: assessed_at (the proposal pool's freshest basis)",
        r"""
        ALTER TABLE llm_calls ADD COLUMN basis_candidates STRUCT(iteration INTEGER, candidate INTEGER)[];
        ALTER TABLE llm_calls ADD COLUMN basis_at TIMESTAMP;
        ALTER TABLE candidates ADD COLUMN assessed_at TIMESTAMP;
        """,
    )
)

# Budgets by construction: a reply whose endpoint reported no usable token count (none, negative, past the INTEGER
# column) is charged its worst case (our count of the prompt, a reply of max_tokens, at litellm's price), and says so.
MIGRATIONS.append(
    (
        22,
        "llm_calls: usage_estimated (tokens and cost charged at the worst case: the endpoint reported no usable count)",
        r"""
        ALTER TABLE llm_calls ADD COLUMN usage_estimated BOOLEAN;  -- NULL: reported by the endpoint, or stored before
        """,
    )
)

# A candidate whose version an earlier candidate of the run already had (an elite or ancestor copied from the
# prompt's memory, scored from the evaluation cache) is no improvement: pipeline/optimizer/ensemble.py's bandit
# gives it none, and model_stats counted it in improvements, gain and cost_per_improvement.
MIGRATIONS.append(
    (
        23,
        "model_stats: a copy of a version the run already had is not an improvement",
        r"""
        CREATE OR REPLACE VIEW model_stats AS
        WITH calls AS (
            SELECT run_id, request_model AS model, count(*)::INTEGER AS calls,
                   count(error_type)::INTEGER AS errors,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd,
                   coalesce(sum(latency_s), 0) AS latency_s,
                   avg(latency_s) AS mean_latency_s
            FROM llm_calls GROUP BY run_id, request_model
        ), fresh AS (  -- each candidate, and whether its version is new to the run
            SELECT c.*, NOT EXISTS (SELECT 1 FROM candidates e WHERE e.run_id = c.run_id
                                      AND e.policy_version_id = c.policy_version_id
                                      AND (e.iteration, e.candidate) < (c.iteration, c.candidate)) AS new_version
            FROM candidates c
        ), cand AS (
            SELECT c.run_id, l.request_model AS model, count(*)::INTEGER AS candidates,
                   (count(*) FILTER (WHERE c.update_status = 'accepted'))::INTEGER AS accepted,
                   (count(*) FILTER (WHERE c.update_status = 'accepted' AND c.new_version AND c.score IS NOT NULL
                                     AND (p.score IS NULL OR c.score > p.score)))::INTEGER AS improvements,
                   coalesce(sum(c.score - p.score) FILTER (WHERE c.update_status = 'accepted' AND c.new_version
                                                          AND c.score > p.score), 0) AS gain
            FROM fresh c
            JOIN llm_calls l ON l.call_id = c.llm_call_id
            LEFT JOIN candidates p ON p.run_id = c.run_id AND p.iteration = c.parent_iteration
                                  AND p.candidate = coalesce(c.parent_candidate, 0)
            GROUP BY c.run_id, l.request_model
        )
        SELECT calls.run_id, calls.model, calls.calls,
               calls.calls / sum(calls.calls) OVER (PARTITION BY calls.run_id) AS share,
               calls.errors, coalesce(cand.candidates, 0) AS candidates, coalesce(cand.accepted, 0) AS accepted,
               coalesce(cand.improvements, 0) AS improvements, coalesce(cand.gain, 0) AS gain,
               calls.input_tokens, calls.output_tokens, calls.cost_usd,
               calls.cost_usd / nullif(cand.improvements, 0) AS cost_per_improvement,
               calls.latency_s, calls.mean_latency_s
        FROM calls LEFT JOIN cand ON cand.run_id = calls.run_id AND cand.model = calls.model;
        COMMENT ON VIEW model_stats IS 'one row per run and model it called: calls, share, accepted, improvements over the parent (a copy of a known version is none), cost, latency';
        """,
    )
)

# A run resumed after its audit (`optimize --resume RUN --iterations N` whose new iterations found a new best, with no
# audit at its end or one that failed) kept the audit of its earlier best, and run_summary gave that version's
# held-out score and overfit flag as the audit of the run's best: `runs` printed "best 0 ... audit -15" for an audit
# of iteration 0 beside the best of iteration 1, and `report` the same. compare of runs already refused to pair them
# (pipeline/optimizer/runs.py). The audit columns now hold the audit only when it played the run's best of now (a
# served run's audit is of its best by validation, another version by design: docs/serve.md); audit_stale says when
# it played an earlier best, and audit_iteration which.
MIGRATIONS.append(
    (
        24,
        "run_summary: the audit columns only when the audit played the run's best of now; audit_stale, "
        "audit_iteration",
        r"""
        CREATE OR REPLACE VIEW run_summary AS
        WITH it AS (
            SELECT run_id, (count(*) FILTER (WHERE iteration >= 1))::INTEGER AS iterations_done,
                   max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max_null(score, iteration) AS last_score,
                   arg_max(best_version_id, iteration) AS best_version_id
            FROM iterations GROUP BY run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval' AND end_reason IN ('terminated', 'truncated'))
                       AS mean_eval_return,
                   (count(*) FILTER (WHERE kind = 'eval' AND end_reason NOT IN ('terminated', 'truncated')))::INTEGER
                       AS eval_forfeits
            FROM episodes GROUP BY run_id
        ), cand AS (
            SELECT run_id, (count(*) FILTER (WHERE forfeit IS NOT NULL))::INTEGER AS forfeits,
                   (count(*) FILTER (WHERE repairs > 0 AND update_status = 'accepted'))::INTEGER AS saved_by_repair
            FROM candidates GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   (count(*) FILTER (WHERE purpose = 'repair'))::INTEGER AS repair_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        ), audits_of AS (  -- whether the best's audit played the run's best of now (a served run's: by validation)
            SELECT a.run_id, r.kind = 'serve' OR a.policy_version_id = it.best_version_id AS current,
                   a.iteration AS audit_iteration
            FROM audits a JOIN runs r ON r.run_id = a.run_id LEFT JOIN it ON it.run_id = a.run_id
            WHERE a.role = 'best' AND a.protocol = 'standard'
        ), audit AS (
            SELECT run_id,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_score,
                   any_value(score_low) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_low,
                   any_value(score_high) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_high,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'run') AS audit_run_score,
                   any_value(score) FILTER (WHERE role = 'starter' AND protocol = 'standard') AS starter_audit_score,
                   any_value(overfit) FILTER (WHERE role = 'best' AND protocol = 'standard') AS overfit
            FROM audits WHERE run_id IN (SELECT run_id FROM audits_of WHERE current) GROUP BY run_id
        )
        SELECT r.run_id, r.name, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               json_extract_string(r.config, '$.policy') AS policy,
               CASE WHEN r.kind <> 'eval' THEN coalesce(json_extract_string(r.config, '$.strategy'), 'greedy')
               END AS strategy,
               CASE WHEN r.kind <> 'eval' THEN json_extract_string(r.config, '$.feedback') END AS feedback,
               json_extract_string(r.config, '$.batch') AS batch,
               r.made_by,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind <> 'eval' THEN it.best_score
                    WHEN coalesce(ep.eval_forfeits, 0) = 0 THEN ep.mean_eval_return END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error,
               CASE WHEN r.kind = 'eval' THEN coalesce(ep.eval_forfeits, 0) ELSE coalesce(cand.forfeits, 0)
               END AS forfeits,
               audit.audit_score, audit.audit_low, audit.audit_high, audit.audit_run_score,
               audit.starter_audit_score, audit.overfit,
               coalesce(calls.repair_calls, 0) AS repair_calls, coalesce(cand.saved_by_repair, 0) AS saved_by_repair,
               NOT audits_of.current AS audit_stale, audits_of.audit_iteration
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN cand ON cand.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id
        LEFT JOIN audit ON audit.run_id = r.run_id
        LEFT JOIN audits_of ON audits_of.run_id = r.run_id;
        COMMENT ON VIEW run_summary IS 'one row per run, what codearcade runs prints: settings, status, best score (NULL: forfeited), forfeits, audit of the best (audit_stale), tokens';
        """,
    )
)

# A served run is finalized by its best by validation (pipeline/serve/finalize.py), which blame RUN:best named, but
# run_summary's best_* came from the iterations table, the best by training score: `runs` printed "best 0" of
# iteration 1 beside the audit of iteration 2, report named and showed the methods of iteration 1's version, compare
# diffed and scored it, and the OTLP export's root span named it. run_best is now the one home of a run's best (the
# validation pick of a finalized served run, with its validation score and best_by saying so; the training best of
# one not finalized; the loop's best of an optimization), and run_summary, compare, blame and the exports read it.
MIGRATIONS.append(
    (
        25,
        "run_best: a run's best version and the score it was picked by (a finalized served run's: by validation); "
        "run_summary reads it: best_version_id, best_by, best_training_score",
        r"""
        CREATE OR REPLACE VIEW run_best AS
        WITH trained AS (  -- the best by the scores its iterations were chosen on (the loop's; a served run's training)
            SELECT run_id, max(best_score) AS best_score, arg_max(best_iteration, iteration) AS best_iteration,
                   arg_max(best_version_id, iteration) AS best_version_id
            FROM iterations GROUP BY run_id
        ), finalized AS (  -- a served run's finalize picked its best by validation (none: each forfeited a game)
            SELECT a.run_id,
                   any_value(a.policy_version_id) FILTER (WHERE a.role = 'best' AND a.protocol = 'standard') AS version,
                   any_value(a.iteration) FILTER (WHERE a.role = 'best' AND a.protocol = 'standard') AS iteration,
                   any_value(a.tuning_score) FILTER (WHERE a.role = 'best' AND a.protocol = 'standard') AS training
            FROM audits a JOIN runs r ON r.run_id = a.run_id WHERE r.kind = 'serve' GROUP BY a.run_id
        )
        SELECT t.run_id,
               CASE WHEN f.run_id IS NULL THEN t.best_version_id ELSE f.version END AS best_version_id,
               CASE WHEN f.run_id IS NULL THEN t.best_iteration ELSE f.iteration END AS best_iteration,
               CASE WHEN f.run_id IS NULL THEN t.best_score ELSE v.score END AS best_score,
               CASE WHEN f.run_id IS NOT NULL THEN 'validation' WHEN r.kind = 'serve' THEN 'training' ELSE 'tuning'
               END AS best_by,
               CASE WHEN f.run_id IS NULL THEN t.best_score ELSE f.training END AS best_training_score
        FROM trained t JOIN runs r ON r.run_id = t.run_id
        LEFT JOIN finalized f ON f.run_id = t.run_id
        LEFT JOIN audits v ON v.run_id = f.run_id AND v.protocol = 'validation' AND v.policy_version_id = f.version;
        COMMENT ON VIEW run_best IS 'one row per run with iterations: its best version and the score that picked it (best_by: validation, training, tuning)';
        CREATE OR REPLACE VIEW run_summary AS
        WITH it AS (
            SELECT i.run_id, (count(*) FILTER (WHERE i.iteration >= 1))::INTEGER AS iterations_done,
                   arg_max_null(i.score, i.iteration) AS last_score, any_value(b.best_score) AS best_score,
                   any_value(b.best_iteration) AS best_iteration, any_value(b.best_version_id) AS best_version_id,
                   any_value(b.best_by) AS best_by, any_value(b.best_training_score) AS best_training_score
            FROM iterations i LEFT JOIN run_best b ON b.run_id = i.run_id GROUP BY i.run_id
        ), ep AS (
            SELECT run_id, count(*)::INTEGER AS episodes, sum(length)::BIGINT AS steps,
                   avg("return") FILTER (WHERE kind = 'eval' AND end_reason IN ('terminated', 'truncated'))
                       AS mean_eval_return,
                   (count(*) FILTER (WHERE kind = 'eval' AND end_reason NOT IN ('terminated', 'truncated')))::INTEGER
                       AS eval_forfeits
            FROM episodes GROUP BY run_id
        ), cand AS (
            SELECT run_id, (count(*) FILTER (WHERE forfeit IS NOT NULL))::INTEGER AS forfeits,
                   (count(*) FILTER (WHERE repairs > 0 AND update_status = 'accepted'))::INTEGER AS saved_by_repair
            FROM candidates GROUP BY run_id
        ), calls AS (
            SELECT run_id, count(*)::INTEGER AS llm_calls,
                   (count(*) FILTER (WHERE purpose = 'repair'))::INTEGER AS repair_calls,
                   coalesce(sum(input_tokens), 0)::BIGINT AS input_tokens,
                   coalesce(sum(output_tokens), 0)::BIGINT AS output_tokens,
                   sum(cost_usd) AS cost_usd
            FROM llm_calls GROUP BY run_id
        ), audits_of AS (  -- whether the best's audit played the run's best of now (a served run's: by validation)
            SELECT a.run_id, a.policy_version_id = it.best_version_id AS current,
                   a.iteration AS audit_iteration
            FROM audits a LEFT JOIN it ON it.run_id = a.run_id
            WHERE a.role = 'best' AND a.protocol = 'standard'
        ), audit AS (
            SELECT run_id,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_score,
                   any_value(score_low) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_low,
                   any_value(score_high) FILTER (WHERE role = 'best' AND protocol = 'standard') AS audit_high,
                   any_value(score) FILTER (WHERE role = 'best' AND protocol = 'run') AS audit_run_score,
                   any_value(score) FILTER (WHERE role = 'starter' AND protocol = 'standard') AS starter_audit_score,
                   any_value(overfit) FILTER (WHERE role = 'best' AND protocol = 'standard') AS overfit
            FROM audits WHERE run_id IN (SELECT run_id FROM audits_of WHERE current) GROUP BY run_id
        )
        SELECT r.run_id, r.name, r.created_at, r.finished_at, r.kind, r.game, r.model, r.seed, r.status,
               json_extract_string(r.config, '$.policy') AS policy,
               CASE WHEN r.kind <> 'eval' THEN coalesce(json_extract_string(r.config, '$.strategy'), 'greedy')
               END AS strategy,
               CASE WHEN r.kind <> 'eval' THEN json_extract_string(r.config, '$.feedback') END AS feedback,
               json_extract_string(r.config, '$.batch') AS batch,
               r.made_by,
               coalesce(it.iterations_done, 0) AS iterations_done,
               TRY_CAST(json_extract(r.config, '$.iterations') AS INTEGER) AS iterations_planned,
               CASE WHEN r.kind <> 'eval' THEN it.best_score
                    WHEN coalesce(ep.eval_forfeits, 0) = 0 THEN ep.mean_eval_return END AS best_score,
               it.best_iteration, it.last_score,
               coalesce(ep.episodes, 0) AS episodes, coalesce(ep.steps, 0) AS steps,
               coalesce(calls.llm_calls, 0) AS llm_calls,
               coalesce(calls.input_tokens, 0) AS input_tokens,
               coalesce(calls.output_tokens, 0) AS output_tokens,
               (coalesce(calls.input_tokens, 0) + coalesce(calls.output_tokens, 0))::BIGINT AS total_tokens,
               calls.cost_usd,
               epoch(r.finished_at - r.created_at) AS duration_s,
               r.error,
               CASE WHEN r.kind = 'eval' THEN coalesce(ep.eval_forfeits, 0) ELSE coalesce(cand.forfeits, 0)
               END AS forfeits,
               audit.audit_score, audit.audit_low, audit.audit_high, audit.audit_run_score,
               audit.starter_audit_score, audit.overfit,
               coalesce(calls.repair_calls, 0) AS repair_calls, coalesce(cand.saved_by_repair, 0) AS saved_by_repair,
               NOT audits_of.current AS audit_stale, audits_of.audit_iteration,
               it.best_version_id, it.best_by, it.best_training_score
        FROM runs r
        LEFT JOIN it ON it.run_id = r.run_id
        LEFT JOIN ep ON ep.run_id = r.run_id
        LEFT JOIN cand ON cand.run_id = r.run_id
        LEFT JOIN calls ON calls.run_id = r.run_id
        LEFT JOIN audit ON audit.run_id = r.run_id
        LEFT JOIN audits_of ON audits_of.run_id = r.run_id;
        COMMENT ON VIEW run_summary IS 'one row per run, what codearcade runs prints: settings, status, best (run_best), forfeits, audit of the best (audit_stale), tokens';
        """,
    )
)

LATEST = MIGRATIONS[-1][0]

SCHEMA_MIGRATIONS_TABLE = ("CREATE TABLE IF NOT EXISTS schema_migrations "
                           "(version INTEGER PRIMARY KEY, name VARCHAR NOT NULL, applied_at TIMESTAMP NOT NULL)")
"""The table that lists the migrations a store has had, made before the first of them."""
