"""What ``codearcade serve`` reads from the store: a served run's submissions and spent budget, and the visible part
of the run that the agent's read-only SQL may query.

The visible part is copied into a private in-memory database (:func:`visible_query`) that holds nothing else: the
agent's SQL cannot reach another run, the run's config (its training seeds), any ``seed`` column, or the
validation and held-out episodes and scores (episode kinds other than ``train`` are left out), and it runs with
external access off, so it can read no file either.
"""

from __future__ import annotations

import decimal
import json
import math
import re
import threading
import warnings
from typing import Any

import duckdb

from store.readers import _rows
from store.views import QueryError, check_user_sql

_COMMITTED = """(SELECT unnest(eval_episode_ids) FROM candidates WHERE run_id = $run AND iteration >= 1)"""
"""The training episodes of committed submissions (a killed server may leave a submission's episodes without one)."""

VISIBLE_TABLES = {
    "submissions": """SELECT c.iteration AS submission, c.policy_version_id, c.parent_iteration AS parent,
                             c.update_status, len(c.eval_episode_ids) AS episodes, c.score, c.score_low,
                             c.score_high, c.forfeit, c.created_at
                      FROM candidates c WHERE c.run_id = $run AND c.iteration >= 1""",
    "episodes": """SELECT episode_id, iteration AS submission, episode_index AS instance, policy_version_id,
                          "return", length, lives_lost, end_reason, error, max_steps
                   FROM episodes WHERE run_id = $run AND kind = 'train' AND episode_id IN """ + _COMMITTED,
    "steps": """SELECT s.episode_id, s.step, s.action, s.reward, s.score, s.terminated, s.truncated, s.lives,
                       s.player_x, s.player_y, s.ball_x, s.ball_y, s.objects
                FROM steps s WHERE s.episode_id IN """ + _COMMITTED,
    "nodes": """SELECT n.episode_id, n.step, n.call_index, n.function, n.trainable, n.policy_version_id,
                       n.inputs, n.output, n.exc_type, n.exc_message, n.exc_line, n.duration_us, n.parents
                FROM nodes n WHERE n.episode_id IN """ + _COMMITTED,
}
"""The tables the agent's SQL sees, each a slice of its own run's training play (no seed, no other kind)."""


def served_submissions(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """The committed submissions of a served run (iteration >= 1), in order: version, parent, episodes, score,
    interval, forfeit, training episodes' ids."""
    return _rows(con.execute(
        """SELECT iteration, policy_version_id, parent_iteration, parent_version_id, update_status, eval_episode_ids,
                  score, score_low, score_high, forfeit, train_return
           FROM candidates WHERE run_id = ? AND iteration >= 1 ORDER BY iteration""", [run_id]))


def submission_episodes(con: duckdb.DuckDBPyConnection, episode_ids: list[str]) -> list[dict[str, Any]]:
    """The visible summary of training episodes (never their seed), in the order given."""
    rows = {r["episode_id"]: r for r in _rows(con.execute(
        """SELECT episode_id, episode_index AS instance, "return", length, lives_lost, end_reason, error
           FROM episodes WHERE list_contains(?, episode_id)""", [list(episode_ids)]))}
    return [rows[e] for e in episode_ids if e in rows]


def visible_query(con: duckdb.DuckDBPyConnection, run_id: str, sql: str, max_rows: int, max_bytes: int,
                  time_limit_s: float = 10.0) -> dict[str, Any]:
    """Run the agent's ``sql`` over the visible part of ``run_id`` (see the module docstring): its columns and the
    first rows, at most ``max_rows`` of them and at most ``max_bytes`` of JSON (``truncated`` says whether rows were
    left out; ``note`` why, when it was their size), every value one standard JSON holds (NaN and the infinities as
    null). A statement that is not a query, or one that runs past ``time_limit_s``, raises :class:`QueryError`; a
    query DuckDB refuses, ``duckdb.Error`` with its message."""
    check_user_sql(sql, refuser="sql")  # the copy is the agent's own, but a DELETE that answers "Count: 3" misleads
    mem = duckdb.connect(":memory:", config={"memory_limit": "512MB", "threads": 1, "enable_external_access": False,
                                             "lock_configuration": True})
    timer = threading.Timer(time_limit_s, mem.interrupt)  # a query of the agent's may be endless: range(1e15)
    try:
        named = [name for name in VISIBLE_TABLES if re.search(rf"\b{name}\b", sql, re.IGNORECASE)]
        for name, query in ((name, VISIBLE_TABLES[name]) for name in named):  # a run's steps and nodes are big:
            # only the tables the query names are copied
            with warnings.catch_warnings():  # the copy it warns of is the point: the agent's database is its own
                warnings.simplefilter("ignore", UserWarning)
                table = con.execute(query, {"run": run_id}).to_arrow_table()
            mem.register(f"_{name}", table)
            mem.execute(f"CREATE TABLE {name} AS SELECT * FROM _{name}")
            mem.unregister(f"_{name}")
        timer.start()
        try:
            relation = mem.sql(sql)
            columns = list(relation.columns) if relation is not None else []
            # row by row, as Arrow first: a row's values become Python objects only once their Arrow size says its
            # JSON could fit (one row of 8 million structs was 65 MB of Arrow and 6 GB as Python objects). DuckDB
            # itself still builds 2,048 rows at a time, values included (docs/serve.md).
            reader = relation.to_arrow_reader(1) if relation is not None else iter(())
            rows: list[list[Any]] = []
            size, note, more = 0, None, False
            for batch in reader:
                if batch.num_rows == 0:
                    continue
                if len(rows) == max_rows:
                    more = True
                    break
                if batch.nbytes > ARROW_BYTES_PER_JSON_BYTE * (max_bytes - size):
                    more, note = True, TOO_LONG.format(max_bytes)
                    break
                row = [_json_value(value) for value in (batch.column(i)[0].as_py() for i in range(batch.num_columns))]
                # its texts' lengths first: a value of 100 MB is not encoded only to learn that it does not fit
                texts = sum(len(v) for v in row if isinstance(v, (str, bytes)))
                # + 2: the ", " between rows in the answer's list
                size += 2 + (texts if size + texts > max_bytes else len(json.dumps(row, default=str)))
                if size > max_bytes:
                    more, note = True, TOO_LONG.format(max_bytes)
                    break
                rows.append(row)
        except duckdb.InterruptException:
            raise QueryError(f"the query ran past its limit of {time_limit_s:g} s: ask for less (a LIMIT, fewer "
                             "rows or columns)") from None
        return {"columns": columns, "rows": rows, "truncated": more,
                **({"note": note} if note is not None else {})}
    finally:
        timer.cancel()
        mem.close()


TOO_LONG = "rows past {:,} bytes of JSON left out: ask for fewer or shorter values"
ARROW_BYTES_PER_JSON_BYTE = 16
"""A row's Arrow bytes per byte of its JSON, at most: a list of 16-byte integers takes 8 for ``0,`` (2 bytes of
JSON), one of 8-byte ones 4; text about 1. A row whose Arrow bytes pass this times what is left of the answer could
not fit in it, and is never made into Python objects."""


def _json_value(value: Any) -> Any:
    """``value`` as standard JSON holds it: a float that is not finite as None, a DECIMAL (DuckDB's type of a
    literal such as 1.5) as a number, inside lists and structs too."""
    if isinstance(value, decimal.Decimal):
        value = float(value)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    if isinstance(value, dict):
        return {k: _json_value(v) for k, v in value.items()}
    return value
