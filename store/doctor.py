"""``codearcade doctor``: an integrity check of a store.

Each check is one SQL query that returns the offending rows (nothing, when the store is sound):

- references: every row's run exists; every step and node belongs to an episode; every blob hash a row
  refers to is in ``blobs`` (policy texts, method sources, prompts, replies, suggestions, feedback);
- uniqueness: one row per (episode, step), per (episode, step, call), per (run, iteration);
- completeness: each run's iterations are 0, 1, ..., n without a gap; each iteration has its feedback, its
  evaluated policy version, its chosen candidate, its episodes and (for updates that called a model) its LLM
  call; every candidate's episodes exist (a cached one's are an earlier candidate's); each episode has
  ``length`` step rows numbered from 0 (one more, with no action, where the policy failed); an episode that
  ``continues`` another (the authors' one-life protocol) finds it in its run, and starts where it ended
  (``start_step``);
- damage to the file itself (``store.db.store_damage``: a table or view missing, a truncated file) and any
  check that cannot run (a block that cannot be read) are findings too, so a damaged store gets a report, not
  a traceback;
- runs left ``running`` by a process that no longer holds the run's lock are reported as interrupted
  (a warning: ``--resume`` finishes them), not as damage.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import duckdb

from store.locks import run_is_live
from store.migrations import MIGRATIONS, SCHEMA_MIGRATIONS_TABLE

CHECKS: list[tuple[str, str]] = [
    ("orphan rows: run missing", """
        SELECT 'policy_versions' AS tbl, run_id FROM policy_versions WHERE run_id NOT IN (SELECT run_id FROM runs)
        UNION ALL SELECT 'iterations', run_id FROM iterations WHERE run_id NOT IN (SELECT run_id FROM runs)
        UNION ALL SELECT 'candidates', run_id FROM candidates WHERE run_id NOT IN (SELECT run_id FROM runs)
        UNION ALL SELECT 'feedback', run_id FROM feedback WHERE run_id NOT IN (SELECT run_id FROM runs)
        UNION ALL SELECT 'llm_calls', run_id FROM llm_calls WHERE run_id NOT IN (SELECT run_id FROM runs)
        UNION ALL SELECT 'episodes', run_id FROM episodes WHERE run_id NOT IN (SELECT run_id FROM runs)"""),
    ("orphan rows: episode missing", """
        SELECT 'steps' AS tbl, episode_id, count(*) FROM steps WHERE episode_id NOT IN (SELECT episode_id FROM episodes) GROUP BY ALL
        UNION ALL SELECT 'nodes', episode_id, count(*) FROM nodes WHERE episode_id NOT IN (SELECT episode_id FROM episodes) GROUP BY ALL"""),
    ("missing blobs", """
        WITH refs AS (
            SELECT 'runs.starter_policy_hash' AS ref, starter_policy_hash AS hash FROM runs
            UNION ALL SELECT 'policy_versions.source_hash', source_hash FROM policy_versions
            UNION ALL SELECT 'policy_versions.functions', f.source_hash FROM (SELECT unnest(functions) AS f FROM policy_versions)
            UNION ALL SELECT 'llm_calls.prompt_hash', prompt_hash FROM llm_calls
            UNION ALL SELECT 'llm_calls.reply_hash', reply_hash FROM llm_calls
            UNION ALL SELECT 'llm_calls.suggestion_hash', suggestion_hash FROM llm_calls
            UNION ALL SELECT 'candidates.feedback_hash', feedback_hash FROM candidates)
        SELECT ref, hash FROM refs WHERE hash IS NOT NULL AND hash NOT IN (SELECT hash FROM blobs)"""),
    ("duplicate steps", "SELECT episode_id, step, count(*) FROM steps GROUP BY ALL HAVING count(*) > 1"),
    ("duplicate nodes", "SELECT episode_id, step, call_index, count(*) FROM nodes GROUP BY ALL HAVING count(*) > 1"),
    ("iteration gaps", """
        SELECT run_id, count(*) AS iterations, max(iteration) AS last FROM iterations GROUP BY run_id
        HAVING count(*) <> max(iteration) + 1 OR min(iteration) <> 0"""),
    ("iterations without feedback", """
        SELECT i.run_id, i.iteration FROM iterations i
        LEFT JOIN feedback f ON f.run_id = i.run_id AND f.iteration = i.iteration WHERE f.run_id IS NULL"""),
    ("iterations whose policy version is missing", """
        SELECT i.run_id, i.iteration, i.policy_version_id FROM iterations i
        WHERE NOT EXISTS (SELECT 1 FROM policy_versions v WHERE v.run_id = i.run_id
                          AND v.policy_version_id = i.policy_version_id)"""),
    ("iterations whose episodes are missing", """
        SELECT i.run_id, i.iteration, e.episode_id FROM iterations i,
               unnest(list_prepend(i.train_episode_id, i.eval_episode_ids)) AS e(episode_id)
        WHERE e.episode_id IS NOT NULL  -- an iteration that played nothing (a served run's starter)
          AND e.episode_id NOT IN (SELECT episode_id FROM episodes)"""),
    ("iterations without their candidates", """
        SELECT i.run_id, i.iteration, i.candidate FROM iterations i
        WHERE NOT EXISTS (SELECT 1 FROM candidates c WHERE c.run_id = i.run_id AND c.iteration = i.iteration
                          AND c.candidate = coalesce(i.candidate, 0))"""),
    ("candidates whose episodes are missing", """
        SELECT c.run_id, c.iteration, c.candidate, e.episode_id FROM candidates c,
               unnest(list_prepend(c.train_episode_id, c.eval_episode_ids)) AS e(episode_id)
        WHERE e.episode_id IS NOT NULL  -- an iteration that played nothing (a served run's starter)
          AND e.episode_id NOT IN (SELECT episode_id FROM episodes)"""),
    ("audits whose episodes are missing", """
        SELECT a.run_id, a.role, a.protocol, e.episode_id FROM audits a, unnest(a.episode_ids) AS e(episode_id)
        WHERE e.episode_id NOT IN (SELECT episode_id FROM episodes)"""),
    ("iterations whose LLM call is missing", """
        SELECT run_id, iteration, llm_call_id FROM iterations
        WHERE llm_call_id IS NOT NULL AND llm_call_id NOT IN (SELECT call_id FROM llm_calls)"""),
    ("episodes whose steps do not match their length", """
        SELECT e.episode_id, e.length, e.end_reason, count(s.step) AS rows, min(s.step) AS first, max(s.step) AS last
        FROM episodes e LEFT JOIN steps s USING (episode_id) GROUP BY ALL
        HAVING NOT (
            (count(s.step) = e.length OR (count(s.step) = e.length + 1 AND e.end_reason IN ('policy_error', 'timeout')))
            AND coalesce(min(s.step), 0) = 0 AND coalesce(max(s.step), -1) = count(s.step) - 1)"""),
    ("episodes that continue a game that is not there", """
        SELECT e.episode_id, e.continues, e.start_step, p.start_step + p.length AS game_steps_before
        FROM episodes e LEFT JOIN episodes p ON p.episode_id = e.continues
        WHERE e.continues IS NOT NULL AND (p.episode_id IS NULL OR p.run_id <> e.run_id
                                           OR e.start_step IS DISTINCT FROM p.start_step + p.length)"""),
]


@dataclass
class Finding:
    check: str
    rows: list[tuple]
    warning: bool = False

    def summary(self, limit: int = 3) -> str:
        shown = "; ".join(", ".join(str(v) for v in row) for row in self.rows[:limit])
        more = f" (and {len(self.rows) - limit} more)" if len(self.rows) > limit else ""
        return f"{self.check}: {len(self.rows)} — {shown}{more}"


@functools.cache
def expected_columns(version: int) -> frozenset[tuple[str, str]]:
    """(table or view, column) of everything migrations 1..``version`` make: they are applied to an empty database
    in memory (~70 ms), so the answer is DuckDB's own, not a reading of their SQL."""
    con = duckdb.connect()
    try:
        con.execute(SCHEMA_MIGRATIONS_TABLE)
        for number, _, sql in MIGRATIONS:
            if number <= version:
                con.execute(sql)
        return frozenset(con.execute("SELECT table_name, column_name FROM information_schema.columns "
                                     "WHERE table_catalog = current_database()").fetchall())
    finally:
        con.close()


def missing_columns(con: duckdb.DuckDBPyConnection, version: int) -> list[str]:
    """``table.column`` of each column the store's migrations 1..``version`` made that it no longer has (dropped or
    renamed by hand), sorted; empty when none is (or when the catalog cannot even be described)."""
    try:
        present = set(con.execute("SELECT table_name, column_name FROM information_schema.columns "
                                  "WHERE table_catalog = current_database()").fetchall())
    except duckdb.Error:  # a view whose table lost a column may not even describe itself
        return []
    return [f"{table}.{column}" for table, column in sorted(expected_columns(version) - present)] if present else []


def check_store(con: duckdb.DuckDBPyConnection, store_path) -> list[Finding]:
    """Every problem found, errors first; an empty list means the store is sound. A damaged file (a table
    missing, truncated, unreadable blocks) gives findings too, never an exception."""
    from store.db import store_damage
    from store.views import one_line

    findings = []
    try:
        version = con.execute("SELECT coalesce(max(version), 0) FROM schema_migrations").fetchone()[0]
    except duckdb.CatalogException:  # a DuckDB file, but no store: not one table of ours in it
        return [Finding("not a codearcade store", [("the file holds no schema_migrations table: another program's "
                                                    "DuckDB file, or an empty one",)])]
    listed = [v for (v,) in con.execute("SELECT version FROM schema_migrations ORDER BY version").fetchall()]
    tables = con.execute("SELECT count(*) FROM information_schema.tables WHERE table_catalog = current_database() "
                         "AND table_name <> 'schema_migrations'").fetchone()[0]
    known = [v for v, _, _ in MIGRATIONS]  # an older store lists the first of them, a newer codearcade's more
    if (listed != known[:len(listed)] and max(listed) <= known[-1]) or (not listed and tables):
        findings.append(Finding("schema_migrations", [(f"lists versions {listed or 'none'} for a file that holds "
                                                       f"{tables} other tables: emptied or edited",)]))
    missing = missing_columns(con, version)
    if missing:
        findings.append(Finding("columns missing", [(name,) for name in missing]))
    damage = store_damage(con, store_path, version)
    if damage:
        findings.append(Finding("damaged file", [(problem,) for problem in damage]))
    for name, sql in CHECKS:
        try:
            rows = con.execute(sql).fetchall()
        except duckdb.Error as exc:  # a missing table, a block that cannot be read
            findings.append(Finding(f"{name}: the check could not run", [(one_line(exc)[:300],)]))
            continue
        if rows:
            findings.append(Finding(name, rows))
    stale: dict[str, list[tuple[str]]] = {}  # by how each kind goes on
    try:
        running = con.execute("SELECT run_id, kind FROM runs WHERE status = 'running'").fetchall()
    except duckdb.Error:
        running = []
    for run_id, kind in running:
        if not run_is_live(store_path, run_id):
            stale.setdefault(GOING_ON.get(kind, GOING_ON["eval"]), []).append((run_id,))
    for going_on, runs in stale.items():
        findings.append(Finding(f"runs interrupted (no process is working on them; {going_on})", runs, warning=True))
    return findings


GOING_ON = {"optimize": "finish with `codearcade optimize --resume RUN`",
            "serve": "serve again with `codearcade serve --resume RUN`",
            "eval": "an evaluation is not resumed: evaluate the policy again"}
"""What to do with an interrupted run of each kind (a replay and a comparison's evaluations: as an evaluation)."""


COUNTED_TABLES = ("runs", "iterations", "episodes", "steps", "nodes", "llm_calls")


def table_counts(con: duckdb.DuckDBPyConnection) -> dict[str, int | None]:
    """Rows in each main table (None where a table cannot be read: the findings say why)."""
    counts: dict[str, int | None] = {}
    for table in COUNTED_TABLES:
        try:
            counts[table] = con.execute(f"SELECT count(*) FROM {table}").fetchone()[0]
        except duckdb.Error:
            counts[table] = None
    return counts
