"""The store's schema, as ordered migrations recorded in the database itself.

Each migration is a (version, name, SQL) triple applied once, in order, inside a transaction, and recorded in
``schema_migrations``. Never edit a released migration: add a new one. A store whose highest recorded
version is above :data:`LATEST` was written by a newer codearcade and is refused (see ``store/db.py``).
The tables and their columns are documented in docs/schema.md; tests check that the two agree.
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
            purpose             VARCHAR NOT NULL,       -- update
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

LATEST = MIGRATIONS[-1][0]
