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

LATEST = MIGRATIONS[-1][0]
