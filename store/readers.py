"""Readers that return slices of the store as plain Python values, for the optimizer and the viewers.

Each takes an open connection (``with store.read() as con:``) so a caller can read several slices in one
open. Step slices come back with the observation dict rebuilt exactly as the policy saw it.
"""

from __future__ import annotations

import statistics
from typing import Any, Callable, Iterable, Mapping, Sequence

import duckdb

from store.db import StoreError
from store.held_values import bounded_value, held_bytes
from tracing.bounded import MAX_CHARS, PREVIEW_CHARS, load_json
from tracing.steps import objects_to_obs


def _rows(cursor: duckdb.DuckDBPyConnection) -> list[dict[str, Any]]:
    names = [d[0] for d in cursor.description]
    return [dict(zip(names, row)) for row in cursor.fetchall()]


def episode_steps(
    con: duckdb.DuckDBPyConnection,
    episode_id: str,
    start: int = 0,
    stop: int | None = None,
    list_widths: Mapping[str, int] | None = None,
    derive: Callable[[dict, int], None] | None = None,
) -> list[dict[str, Any]]:
    """Steps ``start <= step < stop`` of an episode, in order; each with ``obs`` rebuilt as the policy saw it
    (see tracing/steps.py): ``list_widths`` and ``derive`` are the game's (``games.Game``), which adds the
    fields it computes from the objects and the step's lives."""
    rows = _rows(
        con.execute(
            """SELECT step, action, reward, score, terminated, truncated, lives, objects
               FROM steps WHERE episode_id = ? AND step >= ? AND step < ? ORDER BY step""",
            [episode_id, start, stop if stop is not None else 2**31 - 1],
        )
    )
    for row in rows:
        row["obs"] = objects_to_obs(row.pop("objects"), list_widths)
        if derive is not None:
            derive(row["obs"], row["lives"])
    return rows


def step_nodes(
    con: duckdb.DuckDBPyConnection, episode_id: str, start: int = 0, stop: int | None = None,
    value_chars: int | None = None, max_bytes: int | None = None,
) -> list[dict[str, Any]]:
    """Node calls of steps ``start <= step < stop``, ordered by step and call index; JSON decoded within the bounds
    of ``tracing/bounded.py`` (a value nested too deep or too long comes back cut or as its marker, never an
    error: a store holding one stays readable and its run resumable).

    ``value_chars``: the reader shows at most that many characters of each value (the prompt's width), so it
    decodes no more (:func:`bounded_value`): SQL hands over a value's whole text only when it is that short (or
    an object of inputs, split by key), else its first ``value_chars`` characters and its length, which come back
    as a :class:`JsonHead`; and only the columns the prompt shows (step, call index, function, values,
    exception). Each row then holds a few kilobytes at most, whatever the policy stored (issue 38: values of
    16,000 characters of ``[{},{},…]`` in 2,000 rows decoded whole to 2 GB). None: every value decoded whole.
    ``max_bytes`` (with ``value_chars``): the rows stop, in step order, once what they hold passes it
    (:func:`held_bytes`): the slice is bounded in bytes, and so in rows, whatever the policy stored."""
    if value_chars is None:
        rows = _rows(con.execute(
            """SELECT step, call_index, function, trainable, policy_version_id, inputs, output, exc_type,
                      exc_message, exc_line, exc_source, duration_us, parents
               FROM nodes WHERE episode_id = ? AND step >= ? AND step < ? ORDER BY step, call_index""",
            [episode_id, start, stop if stop is not None else 2**31 - 1]))
        for row in rows:
            row["inputs"] = load_json(row["inputs"]) if row["inputs"] is not None else None
            row["output"] = load_json(row["output"]) if row["output"] is not None else None
        return rows
    cursor = con.execute(
        """SELECT step, call_index, function, length(inputs) AS inputs_length,
                  CASE WHEN length(inputs) <= $chars
                         OR (length(inputs) <= $max_chars AND starts_with(inputs::VARCHAR, '{')) THEN inputs::VARCHAR
                       ELSE substr(inputs::VARCHAR, 1, CASE WHEN length(inputs) > $max_chars THEN $preview
                                                           ELSE $chars END) END AS inputs,
                  length(output) AS output_length,
                  CASE WHEN length(output) <= $chars
                         OR (length(output) <= $max_chars AND starts_with(output::VARCHAR, '{"$truncated": '))
                       THEN output::VARCHAR
                       ELSE substr(output::VARCHAR, 1, CASE WHEN length(output) > $max_chars THEN $preview
                                                           ELSE $chars END) END AS output,
                  exc_type, exc_message, exc_line, exc_source
           FROM nodes WHERE episode_id = $episode AND step >= $start AND step < $stop ORDER BY step, call_index""",
        {"episode": episode_id, "start": start, "stop": stop if stop is not None else 2**31 - 1,
         "chars": value_chars, "max_chars": MAX_CHARS, "preview": PREVIEW_CHARS})
    names = [d[0] for d in cursor.description]
    rows = []
    held = 0
    while batch := cursor.fetchmany(_BATCH_ROWS):  # an object of inputs comes whole (<= MAX_CHARS): a batch at a time
        for values in batch:
            row = dict(zip(names, values))
            row["inputs"] = bounded_value(row["inputs"], row.pop("inputs_length"), value_chars, split=True)
            row["output"] = bounded_value(row["output"], row.pop("output_length"), value_chars)
            held += held_bytes([row])
            if max_bytes is not None and held > max_bytes:
                con.abort()  # the rest of the result is never read
                return rows
            rows.append(row)
    return rows


_BATCH_ROWS = 256


def cut_value_sql(column: str, chars: int) -> str:
    """SQL of a node value's JSON text cut for a reader that shows ``chars`` characters of it: the text itself when
    it is that short, else the ``$truncated`` marker of ``tracing/bounded.py`` (its length and a preview of
    :data:`PREVIEW_CHARS`), which decodes to a few kilobytes whatever the value."""
    return (f"CASE WHEN length({column}) <= {int(chars)} THEN {column}::VARCHAR "
            f"ELSE json_object('$truncated', length({column}), 'preview', "
            f"substr({column}::VARCHAR, 1, {PREVIEW_CHARS}))::VARCHAR END")


def step_outputs(con: duckdb.DuckDBPyConnection, episode_id: str, start: int, stop: int,
                 value_chars: int = PREVIEW_CHARS) -> list[dict[str, Any]]:
    """What each method returned (``output``, decoded) or raised (``exc_type``, ``exc_message``) in steps ``start
    <= step < stop``, its last call in a step only, in step order: at most one row per method and step, each value
    cut to ``value_chars`` characters (:func:`cut_value_sql`), however many calls the policy made."""
    rows = _rows(con.execute(
        f"""SELECT step, function, exc_type, exc_message, {cut_value_sql('output', value_chars)} AS output
            FROM nodes WHERE episode_id = ? AND step >= ? AND step < ?
            QUALIFY row_number() OVER (PARTITION BY step, function ORDER BY call_index DESC) = 1
            ORDER BY step, call_index""", [episode_id, start, stop]))
    for row in rows:
        row["output"] = load_json(row["output"]) if row["output"] is not None else None
    return rows


def run_episodes(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """Every episode of a run with its return, length and end reason, in (iteration, kind, index) order."""
    return _rows(
        con.execute(
            """SELECT episode_id, iteration, kind, episode_index, seed, policy_version_id, return, length,
                      lives_lost, end_reason, error, duration_s
               FROM episodes WHERE run_id = ? ORDER BY iteration, kind, episode_index""",
            [run_id],
        )
    )


def get_run(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any] | None:
    rows = _rows(con.execute("SELECT * FROM runs WHERE run_id = ?", [run_id]))
    return rows[0] if rows else None


def blob_text(con: duckdb.DuckDBPyConnection, digest: str) -> str | None:
    row = con.execute("SELECT text FROM blobs WHERE hash = ?", [digest]).fetchone()
    return row[0] if row else None


def blob_starts(con: duckdb.DuckDBPyConnection, digests: Iterable[str | None], chars: int) -> dict[str, tuple[str, int]]:
    """(the first ``chars`` characters, the whole length) of each blob of ``digests`` there is, read one blob at a
    time: DuckDB builds a whole text to cut it, so one query over a run's replies (up to 16 MiB each) held them all
    at once."""
    starts: dict[str, tuple[str, int]] = {}
    for digest in dict.fromkeys(d for d in digests if d is not None):
        row = con.execute("SELECT left(text, ?), length(text) FROM blobs WHERE hash = ?", [chars, digest]).fetchone()
        if row is not None:
            starts[digest] = row
    return starts


class MissingVersionError(StoreError, KeyError):
    """A policy version a run's rows name that the run does not have, or whose source is gone: a store changed by
    hand or damaged (a store is anyone's file). A KeyError to the readers that look for one that may be missing;
    to the command line, a user error (StoreError) of one line."""

    def __init__(self, run_id: str, version_id: str):
        super().__init__(f"run {run_id} has no policy version {version_id} (the store was changed by hand or is "
                         "damaged: `codearcade doctor` reports what is left)")

    __str__ = Exception.__str__  # the message itself, not KeyError's quoted repr of it


def policy_text(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str) -> str:
    """The whole policy file of a version used or considered in a run."""
    row = con.execute(
        "SELECT b.text FROM policy_versions v JOIN blobs b ON b.hash = v.source_hash "
        "WHERE v.run_id = ? AND v.policy_version_id = ? LIMIT 1", [run_id, version_id]).fetchone()
    if row is None:
        raise MissingVersionError(run_id, version_id)
    return row[0]


def policy_texts(con: duckdb.DuckDBPyConnection, run_id: str, version_ids: list[str]) -> dict[str, str]:
    """:func:`policy_text` of several versions in one query (KeyError naming one the run does not have)."""
    found = dict(con.execute(
        "SELECT v.policy_version_id, any_value(b.text) FROM policy_versions v JOIN blobs b ON b.hash = v.source_hash "
        "WHERE v.run_id = ? AND list_contains(?, v.policy_version_id) GROUP BY v.policy_version_id",
        [run_id, sorted(set(version_ids))]).fetchall())
    for version_id in version_ids:
        if version_id not in found:
            raise MissingVersionError(run_id, version_id)
    return found


def run_spending(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, float]:
    """What a run has used so far: LLM cost (USD, calls with a known price), tokens, calls, and iteration wall
    time."""
    cost, tokens, calls = con.execute(
        "SELECT coalesce(sum(cost_usd), 0), coalesce(sum(coalesce(input_tokens, 0) + coalesce(output_tokens, 0)), 0), "
        "count(*) FROM llm_calls WHERE run_id = ? AND NOT replayed", [run_id]).fetchone()
    wall, last_wall = con.execute(
        "SELECT coalesce(sum(wall_s), 0), coalesce(arg_max(wall_s, iteration), 0) FROM iterations WHERE run_id = ?",
        [run_id]).fetchone()
    return {"cost_usd": float(cost), "tokens": int(tokens), "calls": int(calls), "wall_s": float(wall),
            "last_wall_s": float(last_wall)}


def model_spending(con: duckdb.DuckDBPyConnection, run_id: str) -> list[tuple[str, int, float | None]]:
    """(model, calls, cost in USD or None without a price) of each model a run has called, most calls first (an
    ensemble's progress)."""
    return [(m, int(n), None if cost is None else float(cost)) for m, n, cost in con.execute(
        "SELECT request_model, count(*), sum(cost_usd) FROM llm_calls WHERE run_id = ? "
        "GROUP BY request_model ORDER BY count(*) DESC, request_model", [run_id]).fetchall()]


# ---------------------------------------------------------------------------------------------- the optimizer


def call_models(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, str]:
    """call id -> the model it asked (``request_model``) of each LLM call of a run: which model of an ensemble
    made each candidate (``pipeline/optimizer/ensemble.py``)."""
    return dict(con.execute("SELECT call_id, request_model FROM llm_calls WHERE run_id = ?", [run_id]).fetchall())


def bandit_usage(con: duckdb.DuckDBPyConnection, run_id: str, before: int) -> dict[str, Any]:
    """What the LLM calls of iterations 0 .. ``before``-1 used, as an ensemble's bandit counts it
    (``pipeline/optimizer/ensemble.py``): ``calls``, (model, tokens, dollars, seconds) of each call in order;
    ``wall_s``, those iterations' wall time; ``play_s``, the part of iterations 1 .. before-1 not spent waiting
    for the model. A replay's calls report no usage, so a replay counts its original's (the run it replays, back
    to the first that is not a replay): it makes the same choices."""
    source = run_id
    for _ in range(100):
        row = con.execute("SELECT kind, json_extract_string(config, '$.replay_of') FROM runs WHERE run_id = ?",
                          [source]).fetchone()
        if row is None or row[0] != "replay" or not row[1]:
            break
        source = row[1]
    calls = con.execute(
        "SELECT request_model, CASE WHEN input_tokens IS NULL AND output_tokens IS NULL THEN NULL "
        "ELSE coalesce(input_tokens, 0) + coalesce(output_tokens, 0) END, cost_usd, latency_s FROM llm_calls "
        "WHERE run_id = ? AND iteration < ? ORDER BY iteration, coalesce(candidate, 0), coalesce(repair_turn, 0), "
        "created_at", [source, before]).fetchall()
    wall, play = con.execute(
        "SELECT coalesce(sum(wall_s), 0), coalesce(sum(greatest(wall_s - coalesce(llm_s, 0), 0)) "
        "FILTER (WHERE iteration > 0), 0) FROM iterations WHERE run_id = ? AND iteration < ?",
        [source, before]).fetchone()
    return {"calls": [(m, None if t is None else int(t), d, s) for m, t, d, s in calls], "wall_s": float(wall),
            "play_s": float(play)}


def model_choice_rows(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """Each recorded choice of an ensemble's model in a run, in order: iteration, candidate, the model asked and the
    stored reason (``choice``, JSON text: ``llm_calls.model_choice``)."""
    return [{"iteration": it, "candidate": cand, "model": model, "choice": choice} for it, cand, model, choice in
            con.execute("SELECT iteration, coalesce(candidate, 0), request_model, model_choice FROM llm_calls "
                        "WHERE run_id = ? AND model_choice IS NOT NULL ORDER BY iteration, 2, created_at",
                        [run_id]).fetchall()]


def stored_replies(con: duckdb.DuckDBPyConnection, run_id: str,
                   iteration: int) -> dict[tuple[str, int], tuple[str, str]]:
    """(call id, reply text) of the first successful call for each (prompt hash, candidate) of one iteration of a
    run: what a resumed iteration reuses (its proposals can share one prompt: each keeps its own reply;
    ``codearcade replay`` answers from :func:`replay_replies`)."""
    rows = con.execute(
        "SELECT c.prompt_hash, coalesce(c.candidate, 0), c.call_id, b.text FROM llm_calls c "
        "JOIN blobs b ON b.hash = c.reply_hash WHERE c.run_id = ? AND c.iteration = ? "
        "AND c.error_type IS NULL ORDER BY c.created_at", [run_id, iteration]).fetchall()
    replies: dict[tuple[str, int], tuple[str, str]] = {}
    for digest, candidate, call_id, text in rows:
        replies.setdefault((digest, candidate), (call_id, text))
    return replies


def first_call_models(con: duckdb.DuckDBPyConnection, run_id: str, before: int) -> dict[tuple[int, int], str]:
    """(iteration, candidate) -> the model of its first call, for the iterations before ``before``, in order: the
    models an ensemble's proposal pool counts as chosen before the candidates it starts (``optimizer/pool.py``)."""
    rows = con.execute(
        "SELECT iteration, coalesce(candidate, 0), any_value(request_model) FROM llm_calls WHERE run_id = ? "
        "AND iteration < ? AND coalesce(repair_turn, 0) = 0 GROUP BY ALL ORDER BY 1, 2", [run_id, before]).fetchall()
    return {(iteration, candidate): model for iteration, candidate, model in rows}


def replay_replies(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[tuple[int, str, int], str]:
    """The hash of the reply (its blob) of the first successful call for each (iteration, prompt hash, candidate) of
    a run: what ``codearcade replay`` answers with (the proposal pool may send one prompt in two iterations, each
    with its own reply). Hashes, not texts: a run's replies together may be far larger than one (up to 16 MiB
    each), so the replay reads each text when it is asked for (:func:`blob_text`)."""
    rows = con.execute(
        "SELECT c.iteration, c.prompt_hash, coalesce(c.candidate, 0), c.reply_hash FROM llm_calls c "
        "JOIN blobs b ON b.hash = c.reply_hash WHERE c.run_id = ? AND c.error_type IS NULL ORDER BY c.created_at",
        [run_id]).fetchall()
    replies: dict[tuple[int, str, int], str] = {}
    for iteration, digest, candidate, reply_hash in rows:
        replies.setdefault((iteration, digest, candidate), reply_hash)
    return replies


def replay_errors(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[tuple[int, str, int], tuple[str, str, int]]:
    """(error type, message, attempts) of the first call of each (iteration, prompt hash, candidate) of a run that
    no call ever got a reply for: what ``codearcade replay`` answers such a call with (the error again)."""
    rows = con.execute(
        "SELECT c.iteration, c.prompt_hash, coalesce(c.candidate, 0), arg_min(c.error_type, c.created_at), "
        "arg_min(coalesce(c.error_message, ''), c.created_at), arg_min(c.attempts, c.created_at) FROM llm_calls c "
        "WHERE c.run_id = ? GROUP BY ALL HAVING bool_and(c.error_type IS NOT NULL)", [run_id]).fetchall()
    return {(iteration, digest, candidate): (error, message, attempts)
            for iteration, digest, candidate, error, message, attempts in rows}


def pool_bases(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[tuple[int, int], tuple[int, tuple[tuple[int, int], ...]]]:
    """(iteration, candidate) -> the basis of its first call: how many iterations its prompt was built from
    (``llm_calls.history_iterations``) and the candidates assessed but not committed that it was built from too
    (``basis_candidates``, as (iteration, candidate) pairs; none before migration 21): what a proposal pool's resume
    and replay build each prompt from again."""
    rows = con.execute(
        "SELECT iteration, coalesce(candidate, 0), arg_min(history_iterations, created_at), "
        "arg_min(basis_candidates, created_at) FROM llm_calls WHERE run_id = ? "
        "AND coalesce(repair_turn, 0) = 0 AND history_iterations IS NOT NULL GROUP BY ALL", [run_id]).fetchall()
    return {(iteration, candidate): (basis, tuple((r["iteration"], r["candidate"]) for r in fresh or ()))
            for iteration, candidate, basis, fresh in rows}


def first_call_errors(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[tuple[int, int], str | None]:
    """(iteration, candidate) -> the error of its first-turn call (None: a reply is stored), for every candidate
    that has one (a successful call counts over a failed one): where a replay's record ends."""
    rows = con.execute(
        "SELECT iteration, coalesce(candidate, 0), CASE WHEN bool_or(error_type IS NULL) THEN NULL "
        "ELSE any_value(error_type) END FROM llm_calls WHERE run_id = ? AND coalesce(repair_turn, 0) = 0 "
        "GROUP BY ALL", [run_id]).fetchall()
    return {(iteration, candidate): error for iteration, candidate, error in rows}


def starter_version_id(con: duckdb.DuckDBPyConnection, run_id: str) -> str:
    return con.execute("SELECT starter_version_id FROM runs WHERE run_id = ?", [run_id]).fetchone()[0]


def last_iteration(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[str, Any] | None:
    """The newest ``iterations`` row of a run (where a resumed run continues), or None."""
    rows = _rows(con.execute(
        "SELECT iteration, best_score, best_iteration, best_version_id FROM iterations WHERE run_id = ? "
        "ORDER BY iteration DESC LIMIT 1", [run_id]))
    return rows[0] if rows else None


def audit_subjects(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """What a run's audit plays: its best version (role ``best``) and its starting policy (``starter``), each
    with its iteration, its tuning score and its policy text; one row when the best is the starter (no rows for a
    run without iterations)."""
    return _rows(con.execute(
        """WITH last AS (SELECT best_version_id, best_iteration, best_score FROM iterations WHERE run_id = $run
                         ORDER BY iteration DESC LIMIT 1),
                subjects AS (
                    SELECT 'best' AS role, best_version_id AS policy_version_id, best_iteration AS iteration,
                           best_score AS tuning_score FROM last
                    UNION ALL
                    SELECT 'starter', i.policy_version_id, 0, i.score FROM iterations i
                    WHERE i.run_id = $run AND i.iteration = 0)
           SELECT s.role, s.policy_version_id, s.iteration, s.tuning_score, b.text AS policy_text
           FROM subjects s
           JOIN (SELECT policy_version_id, any_value(source_hash) AS source_hash FROM policy_versions
                 WHERE run_id = $run GROUP BY policy_version_id) v USING (policy_version_id)
           JOIN blobs b ON b.hash = v.source_hash
           ORDER BY s.role""", {"run": run_id}))


def audits(con: duckdb.DuckDBPyConnection, run_id: str) -> list[dict[str, Any]]:
    """A run's ``audits`` rows (best first, the standard protocol first)."""
    return _rows(con.execute(
        "SELECT * FROM audits WHERE run_id = ? ORDER BY role, protocol DESC", [run_id]))


def iteration_count(con: duckdb.DuckDBPyConnection, run_id: str) -> int:
    return con.execute("SELECT count(*) FROM iterations WHERE run_id = ?", [run_id]).fetchone()[0]


def iteration_update(con: duckdb.DuckDBPyConnection, run_id: str, iteration: int) -> tuple[str | None, list[str]]:
    """What one iteration did with its update: its ``update_status`` (None: no such iteration) and the versions its
    candidates proposed, in candidate order (those whose reply held no usable code left out)."""
    row = con.execute("SELECT update_status FROM iterations WHERE run_id = ? AND iteration = ?",
                      [run_id, iteration]).fetchone()
    proposed = con.execute("SELECT proposed_version_id FROM candidates WHERE run_id = ? AND iteration = ? AND "
                           "proposed_version_id IS NOT NULL ORDER BY candidate", [run_id, iteration]).fetchall()
    return (row[0] if row else None), [version for (version,) in proposed]


HISTORY_ITERATION_COLUMNS = ("iteration", "candidate", "policy_version_id", "update_status", "score", "rolled_back",
                             "best_score", "best_iteration", "best_version_id")
"""The fields of an ``iterations`` row in a run's history (:func:`iterations`)."""


def iterations(con: duckdb.DuckDBPyConnection, run_id: str, before_iteration: int | None = None) -> list[dict[str, Any]]:
    """A run's ``iterations`` rows (before ``before_iteration`` if given), in order: score, best so far, the
    chosen candidate and whether it rolled back."""
    columns = ", ".join("coalesce(candidate, 0) AS candidate" if c == "candidate" else c
                        for c in HISTORY_ITERATION_COLUMNS)
    return _rows(con.execute(
        f"SELECT {columns} FROM iterations WHERE run_id = ? AND iteration < ? ORDER BY iteration",
        [run_id, before_iteration if before_iteration is not None else 2**31 - 1]))


HISTORY_CANDIDATE_COLUMNS = (
    "run_id", "iteration", "candidate", "strategy", "parent_iteration", "parent_candidate", "parent_version_id",
    "proposed_version_id", "policy_version_id", "llm_call_id", "update_status", "evaluation", "train_episode_id",
    "eval_episode_ids", "robust_episode_ids", "train_return", "score", "deterministic_score", "standard_score",
    "decision", "feedback", "complexity", "eval_length", "forfeit")
"""The fields of a candidate in a run's history (:func:`candidates`): its ``candidates`` row, its feedback text,
its version's complexity and the mean length of its evaluation games."""
_CANDIDATE_FROM = {"feedback": "b.text", "complexity": "v.complexity", "eval_length": "e.eval_length"}
CANDIDATE_COLUMNS = ", ".join(f"{_CANDIDATE_FROM.get(name, 'c.' + name)} AS {name}" for name in HISTORY_CANDIDATE_COLUMNS)


def candidates(con: duckdb.DuckDBPyConnection, run_id: str, before_iteration: int | None = None) -> list[dict[str, Any]]:
    """The candidates of a run's completed iterations (optionally those before ``before_iteration``), in
    (iteration, candidate) order, with their feedback text: the whole history a strategy decides from."""
    return _rows(con.execute(
        f"""WITH mine AS (SELECT * FROM candidates WHERE run_id = $run AND iteration < $before),
                 v AS (SELECT policy_version_id, any_value(complexity) AS complexity FROM policy_versions
                       WHERE run_id = $run GROUP BY policy_version_id),
                 e AS (SELECT m.iteration, m.candidate, avg(ep.length) AS eval_length
                       FROM mine m, unnest(m.eval_episode_ids) AS u(episode_id)
                       JOIN episodes ep ON ep.episode_id = u.episode_id GROUP BY ALL)
            SELECT {CANDIDATE_COLUMNS} FROM mine c LEFT JOIN blobs b ON b.hash = c.feedback_hash
            JOIN iterations i ON i.run_id = c.run_id AND i.iteration = c.iteration
            LEFT JOIN v ON v.policy_version_id = c.policy_version_id
            LEFT JOIN e ON e.iteration = c.iteration AND e.candidate = c.candidate
            ORDER BY c.iteration, c.candidate""",
        {"run": run_id, "before": before_iteration if before_iteration is not None else 2**31 - 1}))


def earlier_screen(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str) -> dict[str, Any] | None:
    """The first screening game (cascade evaluation) a version played in this run: its episode id, verified
    return and end."""
    rows = _rows(con.execute(
        """SELECT e.episode_id, e.return AS score, e.return, e.end_reason, e.length, e.error FROM candidates c
           JOIN episodes e ON e.episode_id = c.screen_episode_id
           WHERE c.run_id = ? AND c.proposed_version_id = ? AND e.verified AND e.end_reason <> 'timeout'
           ORDER BY c.iteration, c.candidate LIMIT 1""", [run_id, version_id]))
    return rows[0] if rows else None


def score_at_step(con: duckdb.DuckDBPyConnection, episode_id: str, step: int) -> float:
    """The cumulative score of an episode after ``step`` (its final score if it ended before)."""
    row = con.execute("SELECT arg_max(score, step) FROM steps WHERE episode_id = ? AND step <= ? AND score IS NOT NULL",
                      [episode_id, step]).fetchone()
    return float(row[0]) if row and row[0] is not None else 0.0


def version_complexity(con: duckdb.DuckDBPyConnection, run_id: str, version_ids: list[str]) -> dict[str, int]:
    """Cyclomatic complexity of each of ``version_ids`` (as stored with the version)."""
    return dict(con.execute(
        "SELECT policy_version_id, any_value(complexity) FROM policy_versions WHERE run_id = ? "
        "AND list_contains(?, policy_version_id) GROUP BY policy_version_id", [run_id, version_ids]).fetchall())


def episode_summaries(con: duckdb.DuckDBPyConnection, episode_ids: list[str]) -> list[dict[str, Any]]:
    """Return, length, lives lost and end of each of ``episode_ids``, in their order, in one query (a
    placeholder saying ``missing`` for one that is gone)."""
    found = {row["episode_id"]: row for row in _rows(con.execute(
        "SELECT episode_id, return, length, lives_lost, end_reason, error FROM episodes "
        "WHERE list_contains(?, episode_id)", [list(episode_ids)]))}
    return [found.get(e) or {"episode_id": e, "return": 0.0, "length": 0, "lives_lost": 0, "end_reason": "missing",
                             "error": None} for e in episode_ids]


def reusable_assessment(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str,
                        pending: Sequence[dict[str, Any]] = ()) -> dict[str, Any] | None:
    """The first assessment of ``version_id`` in this run whose episodes can stand for a new one (the
    evaluation cache): played, not caught tampering, every episode stored, verified and ended by the game or
    the step cap, never by a time limit (which depends on the machine's load, not on the code). ``pending``:
    assessments of it not committed yet (the proposal pool's, whose episodes are stored already), in the shape of
    a ``candidates`` row, looked at after the committed ones.

    Two plain queries and a loop here: one query joining the episodes to each assessment took ~4 times as long,
    and the optimizer asks this for every candidate."""
    assessments = _rows(con.execute(
        """SELECT iteration, candidate, train_episode_id, eval_episode_ids, robust_episode_ids, train_return, score,
                  deterministic_score, standard_score, score_low, score_high
           FROM candidates
           WHERE run_id = ? AND policy_version_id = ? AND evaluation = 'played'
             AND NOT (decision = 'rejected' AND policy_version_id IS NOT DISTINCT FROM proposed_version_id)
           ORDER BY iteration, candidate""", [run_id, version_id])) + list(pending)
    if not assessments:
        return None
    usable = dict(con.execute(
        "SELECT episode_id, length FROM episodes WHERE run_id = ? AND policy_version_id = ? AND verified "
        "AND end_reason IN ('terminated', 'truncated')", [run_id, version_id]).fetchall())
    for row in assessments:
        episodes = [row["train_episode_id"], *row["eval_episode_ids"], *(row["robust_episode_ids"] or [])]
        if all(e in usable for e in episodes):
            return {**row, "train_length": usable[row["train_episode_id"]],
                    "eval_length": statistics.fmean([usable[e] for e in row["eval_episode_ids"]] or [0])}
    return None


def update_failures(con: duckdb.DuckDBPyConnection, run_id: str) -> tuple[int, int, str | None]:
    """(updates, updates that ended in an LLM error, the last LLM error) of a run."""
    return con.execute(
        "SELECT count(*), count(*) FILTER (WHERE i.update_status = 'llm_error'), "
        "(SELECT arg_max(error_type || ': ' || error_message, created_at) FROM llm_calls "
        " WHERE run_id = ? AND error_type IS NOT NULL) "
        "FROM iterations i WHERE i.run_id = ? AND i.iteration > 0", [run_id, run_id]).fetchone()


def iteration_prompts(con: duckdb.DuckDBPyConnection, run_id: str) -> dict[int, tuple[str | None, float | None]]:
    """Per iteration of a run: (a digest of its prompts, its score) — what ``codearcade replay`` compares. The
    digest is the prompt hash when the iteration sent one prompt, else the hash of its distinct prompt hashes; an
    iteration that never completed (where a replay diverged) still has its prompts, with no score."""
    rows = con.execute(
        """WITH prompts AS (
               SELECT iteration, CASE WHEN count(DISTINCT prompt_hash) = 1 THEN any_value(prompt_hash)
                                      ELSE sha256(string_agg(DISTINCT prompt_hash, ',' ORDER BY prompt_hash))
                                 END AS digest
               FROM llm_calls WHERE run_id = ? GROUP BY iteration)
           SELECT coalesce(i.iteration, p.iteration), p.digest, i.score
           FROM (SELECT iteration, score FROM iterations WHERE run_id = ?) i
           FULL JOIN prompts p ON p.iteration = i.iteration""", [run_id, run_id]).fetchall()
    return {it: (digest, score) for it, digest, score in rows}


# ---------------------------------------------------------------------------------------------- batches


def batch_runs(con: duckdb.DuckDBPyConnection, batch: str) -> list[tuple[str, str, str, str | None]]:
    """(batch key, run id, status, name) of every run of the batch ``batch``, oldest first."""
    return con.execute(
        "SELECT json_extract_string(config, '$.batch_key'), run_id, status, name FROM runs "
        "WHERE json_extract_string(config, '$.batch') = ? ORDER BY created_at", [batch]).fetchall()


def batch_progress(con: duckdb.DuckDBPyConnection, batch: str) -> list[tuple[str, str, int | None, float | None]]:
    """(batch key, run id, latest iteration, best score) of every run of the batch ``batch``."""
    return con.execute(
        """SELECT json_extract_string(r.config, '$.batch_key'), r.run_id, max(i.iteration), max(i.best_score)
           FROM runs r LEFT JOIN iterations i USING (run_id)
           WHERE json_extract_string(r.config, '$.batch') = ? GROUP BY ALL""", [batch]).fetchall()


# ---------------------------------------------------------------------------------------------- versions


def version_of_iteration(con: duckdb.DuckDBPyConnection, run_id: str, iteration: int) -> str:
    """The version iteration ``iteration`` of a run evaluated (or, for one without a row, the version it
    stored); ValueError naming the iterations there are."""
    rows = con.execute("SELECT policy_version_id FROM iterations WHERE run_id = ? AND iteration = ?",
                       [run_id, iteration]).fetchall()
    if not rows:
        rows = con.execute("SELECT policy_version_id FROM policy_versions WHERE run_id = ? AND iteration = ? "
                           "AND validation = 'accepted'", [run_id, iteration]).fetchall()
    if not rows:
        # every iteration has an ``iterations`` row, not always a version of its own (a parse error, no change)
        (last,) = con.execute("SELECT greatest((SELECT max(iteration) FROM iterations WHERE run_id = $run), "
                              "(SELECT max(iteration) FROM policy_versions WHERE run_id = $run))",
                              {"run": run_id}).fetchone()
        raise ValueError(f"run {run_id} has no iteration {iteration} (iterations 0..{last}); give --iteration "
                         "within them")
    return rows[0][0]


def first_iteration_of(con: duckdb.DuckDBPyConnection, run_id: str, version_id: str) -> int | None:
    """The first iteration of a run that stored ``version_id``."""
    return con.execute("SELECT min(iteration) FROM policy_versions WHERE run_id = ? AND policy_version_id = ?",
                       [run_id, version_id]).fetchone()[0]


REPLAY_EPISODE_COLUMNS = ("episode_id", "game", "seed", "sticky", "noop_max", "max_steps", "return", "length",
                          "lives_lost", "end_reason", "continues")
"""What a replay of a stored episode needs of its row (``codearcade doctor --replay``)."""
REPLAY_STEP_COLUMNS = ("step", "action", "reward", "score", "terminated", "truncated", "lives")


def replay_material(con: duckdb.DuckDBPyConnection, run_id: str) -> list[tuple[dict[str, Any], Any]]:
    """Each episode of a run that ended by the game or the step cap (a policy error ends by the policy: its last
    step has no action), with its step rows as an Arrow table, in the order they were played (an episode that
    ``continues`` another after it)."""
    columns = ", ".join(f'"{c}"' for c in REPLAY_EPISODE_COLUMNS)
    episodes = _rows(con.execute(
        f"SELECT {columns} FROM episodes WHERE run_id = ? AND end_reason IN ('terminated', 'truncated') "
        "ORDER BY started_at, episode_id", [run_id]))
    steps = [con.sql(f"SELECT {', '.join(REPLAY_STEP_COLUMNS)} FROM steps WHERE episode_id = $episode ORDER BY step",
                     params={"episode": row["episode_id"]}).to_arrow_table() for row in episodes]
    return list(zip(episodes, steps))
