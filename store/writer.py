"""Batched writes into the store: runs, content-addressed blobs, policy versions, whole episodes (grouped in
time by :class:`EpisodeWriter`).

Every function takes an open read-write connection (``with store.write() as con:``), so a caller groups
what belongs together into one transaction. Step and node rows arrive as Arrow tables and go in with
``INSERT ... BY NAME SELECT`` (node rows in slices of :data:`NODE_SLICE_BYTES`, so that the cast of their JSON
holds a bounded amount at once), never row by row. Re-playing an episode (resume) writes it with
``replace=True``, which first deletes its earlier rows, so rows are never duplicated.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from datetime import datetime
from typing import Any, Callable, Iterator

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from store.db import Store, utcnow
from store.incoming import insert_arrow
from store.lines import write_version_lines
from store.runs import check_run_name


def text_hash(text: str) -> str:
    """Content address of a blob: SHA-256 hex."""
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()


def _insert(con: duckdb.DuckDBPyConnection, table: str, row: dict[str, Any]) -> None:
    """Insert one row given by column name (never by position)."""
    _insert_rows(con, table, [row])


def _insert_rows(con: duckdb.DuckDBPyConnection, table: str, rows: list[dict[str, Any]]) -> None:
    """Insert rows given by column name (never by position): one statement for the rows of each set of columns."""
    by_columns: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for row in rows:
        by_columns.setdefault(tuple(row), []).append(row)
    for columns, group in by_columns.items():
        values = "(" + ", ".join("?" * len(columns)) + ")"
        con.execute(f"INSERT INTO {table} ({', '.join(columns)}) VALUES {', '.join([values] * len(group))}",
                    [row[c] for row in group for c in columns])


def put_blob(con: duckdb.DuckDBPyConnection, kind: str, text: str) -> str:
    """Store ``text`` once under its content hash and return the hash."""
    return put_blobs(con, [(kind, text)])[0]


def put_blobs(con: duckdb.DuckDBPyConnection, blobs: list[tuple[str, str]]) -> list[str]:
    """Store each ``(kind, text)`` once under its content hash, in one statement; their hashes, in order."""
    digests = [text_hash(text) for _, text in blobs]
    new = {digest: (kind, text) for digest, (kind, text) in zip(digests, blobs)}  # once per statement
    if new:
        con.execute(
            "INSERT INTO blobs (hash, kind, text, chars) VALUES " + ", ".join(["(?, ?, ?, ?)"] * len(new))
            + " ON CONFLICT DO NOTHING",
            [value for digest, (kind, text) in new.items() for value in (digest, kind, text, len(text))])
    return digests


def insert_run(
    con: duckdb.DuckDBPyConnection,
    run_id: str,
    kind: str,
    game: str,
    config: dict[str, Any],
    starter_text: str,
    starter_version_id: str,
    package_versions: dict[str, str],
    model: str | None = None,
    seed: int | None = None,
    created_at: datetime | None = None,
    name: str | None = None,
    made_by: str | None = None,
) -> None:
    """The run's row, status ``running``. ``name`` is its label (checked by :func:`store.runs.check_run_name`);
    ``made_by`` names the command that made the run for its own use (``compare``), which ``runs`` and ``last``
    leave out."""
    if name is not None:
        check_run_name(name)
    starter_hash = put_blob(con, "policy", starter_text)
    con.execute(
        """INSERT INTO runs (run_id, created_at, kind, game, config, model, seed, status, package_versions,
                             starter_policy_hash, starter_version_id, name, made_by)
           VALUES (?, ?, ?, ?, ?, ?, ?, 'running', ?, ?, ?, ?, ?)""",
        [run_id, created_at or utcnow(), kind, game, json.dumps(config, sort_keys=True), model, seed,
         json.dumps(package_versions, sort_keys=True), starter_hash, starter_version_id, name, made_by],
    )


def set_run_name(con: duckdb.DuckDBPyConnection, run_id: str, name: str | None) -> None:
    """Give a run a label (or take it away with None)."""
    if name is not None:
        check_run_name(name)
    con.execute("UPDATE runs SET name = ? WHERE run_id = ?", [name, run_id])


def finish_run(con: duckdb.DuckDBPyConnection, run_id: str, status: str, error: str | None = None) -> None:
    con.execute(
        "UPDATE runs SET status = ?, finished_at = ?, error = ? WHERE run_id = ?",
        [status, utcnow(), error, run_id],
    )


def insert_llm_calls(con: duckdb.DuckDBPyConnection,
                     calls: list[tuple[dict[str, Any], str, str | None, str | None]]) -> None:
    """Insert ``llm_calls`` rows, each given as ``(row, prompt, reply, suggestion)``: ``row`` holds its columns
    by name (``parse_error`` among them); the prompt, the reply and what the reply parsed into (a suggestion,
    JSON) are stored as blobs — in one statement for all, a prompt shared by several calls once — and referenced
    by hash."""
    kinds = ("prompt", "reply", "suggestion")
    texts = [(kind, text) for _, *call_texts in calls for kind, text in zip(kinds, call_texts) if text is not None]
    digests = iter(put_blobs(con, texts))
    for row, *call_texts in calls:
        row = dict(row)
        for kind, text in zip(kinds, call_texts):
            row[f"{kind}_hash"] = next(digests) if text is not None else None
        row.setdefault("created_at", utcnow())
        _insert(con, "llm_calls", row)


def insert_policy_version(con: duckdb.DuckDBPyConnection, row: dict[str, Any]) -> None:
    """Insert one ``policy_versions`` row (``row`` holds its columns; ``source`` is stored as a blob) and the
    ``policy_lines`` of its trainable methods, their origins carried from the parent's (``store/lines.py``)."""
    row = dict(row)
    row["functions"] = [dict(function) for function in row.get("functions") or []]
    trainable = {f["name"]: f["source"] for f in row["functions"] if f.get("trainable")}
    digests = put_blobs(con, [("policy", row.pop("source"))] + [("source", f.pop("source")) for f in row["functions"]])
    row["source_hash"] = digests[0]
    for function, digest in zip(row["functions"], digests[1:]):
        function["source_hash"] = digest
    row.setdefault("created_at", utcnow())
    columns = list(row)
    con.execute(
        f"INSERT OR REPLACE INTO policy_versions ({', '.join(columns)}) VALUES ({', '.join('?' * len(columns))})",
        [row[c] for c in columns],
    )
    write_version_lines(con, row["run_id"], row["policy_version_id"], row["iteration"], row["produced_by"],
                        row.get("parent_id"), trainable)


def write_episode(
    con: duckdb.DuckDBPyConnection,
    episode: dict[str, Any],
    steps: pa.Table,
    nodes: pa.Table | None,
    replace: bool = False,
) -> None:
    """Insert an episode row with its steps and nodes (:func:`write_episodes` of one)."""
    write_episodes(con, [(episode, steps, nodes)], replace=replace)


def write_episodes(
    con: duckdb.DuckDBPyConnection,
    episodes: list[tuple[dict[str, Any], pa.Table, pa.Table | None]],
    replace: bool = False,
) -> None:
    """Insert episode rows with their steps and nodes: every episode row in one statement and every step in one
    more (DuckDB plans each statement anew, ~0.5 ms, as much as a short episode's steps take to insert).

    ``replace=True`` first deletes earlier rows of the same ``episode_id`` s (re-playing an episode on resume);
    it costs a scan of the steps table, so fresh episodes skip it.
    """
    if not episodes:
        return
    ids = [episode["episode_id"] for episode, _, _ in episodes]
    if replace:
        delete_episodes(con, ids)
    _insert_rows(con, "episodes", [episode for episode, _, _ in episodes])
    played = [(episode_id, steps) for episode_id, (_, steps, _) in zip(ids, episodes) if steps.num_rows]
    if played and all(steps.schema.equals(played[0][1].schema) for _, steps in played):
        steps = pa.concat_tables([steps for _, steps in played])
        ids_column = np.repeat(np.array([i for i, _ in played], dtype=object), [t.num_rows for _, t in played])
        insert_arrow(con, "incoming_steps", steps.append_column("episode_id", pa.array(ids_column, pa.string())),
                     "INSERT INTO steps BY NAME SELECT * FROM incoming_steps")
    else:  # tables of several shapes (a test's, an old run's): each its own insert, BY NAME
        for episode_id, steps in played:
            insert_arrow(con, "incoming_steps", steps,
                         "INSERT INTO steps BY NAME SELECT ? AS episode_id, * FROM incoming_steps", [episode_id])
    for episode, _, nodes in episodes:
        if nodes is not None and nodes.num_rows:
            # in slices of at most NODE_SLICE_BYTES: the JSON cast of ``inputs`` and ``output`` holds several times
            # the text it parses (9 x for "[{},{},...]"), so one INSERT of a whole episode held that of all of it
            for part in _slices(nodes, NODE_SLICE_BYTES):
                insert_arrow(con, "incoming_nodes", part,
                             "INSERT INTO nodes BY NAME SELECT ? AS episode_id, ? AS policy_version_id, * "
                             "FROM incoming_nodes", [episode["episode_id"], episode["policy_version_id"]])


def delete_episodes(con: duckdb.DuckDBPyConnection, episode_ids: list[str]) -> None:
    """Delete the episodes ``episode_ids`` with their steps and nodes (a scan of each table)."""
    for table in ("nodes", "steps", "episodes"):
        con.execute(f"DELETE FROM {table} WHERE list_contains(?, episode_id)", [episode_ids])


NODE_SLICE_BYTES = 2 * 2**20
"""Bytes of node rows one INSERT casts at a time (what the cast holds is a multiple of this, not of the episode)."""


def _slices(table: pa.Table, limit: int) -> Iterator[pa.Table]:
    """``table`` in consecutive slices of at most ``limit`` bytes each (a row larger than that alone)."""
    sizes = pc.binary_length(table.column("inputs")).fill_null(0).to_numpy() \
        + pc.binary_length(table.column("output")).fill_null(0).to_numpy() + 64
    ends = np.cumsum(sizes)
    start, n = 0, len(sizes)
    while start < n:
        before = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, before + limit, side="right")))
        yield table.slice(start, stop - start)
        start = stop


class EpisodeWriter:
    """Writes finished episodes to a store in groups, one transaction each, at most one every ``every_s`` seconds
    (and what is left at :meth:`flush`).

    Each write attaches the store file, commits and checkpoints it (``store/hub.py``): ~20-30 ms of this
    process whatever it writes, on the cores the episodes play on. One write per episode cost an evaluation of
    short episodes several per cent of its throughput; grouped, the file is still let go between writes, so other
    processes get in as before. An episode is in the store at most ``every_s`` after it ended, and a process
    killed meanwhile loses only what it had not yet written (episodes that are played again on resume).
    Use it as a context manager, or call :meth:`flush` before reading what was written.
    """

    def __init__(self, store: Store, replace: bool = False, every_s: float = 1.0) -> None:
        self.store = store
        self.replace = replace
        """Re-played episodes (resume): their earlier rows are deleted first (:func:`write_episode`)."""
        self.every_s = every_s
        self.waiting: list[tuple[dict[str, Any], pa.Table, pa.Table | None]] = []
        self.written_at = time.monotonic()

    def add(self, episode: dict[str, Any], steps: pa.Table, nodes: pa.Table | None) -> None:
        """Queue an episode; write the queue if the last write is ``every_s`` old."""
        self.waiting.append((episode, steps, nodes))
        if time.monotonic() - self.written_at >= self.every_s:
            self.flush()

    def flush(self, also: Callable[[duckdb.DuckDBPyConnection], None] | None = None) -> None:
        """Write the queued episodes in one transaction, with ``also(con)`` (a run's end) in the same one."""
        if not self.waiting and also is None:
            return
        waiting, self.waiting = self.waiting, []
        try:
            with self.store.write() as con:
                write_episodes(con, waiting, replace=self.replace)
                if also is not None:
                    also(con)
        except duckdb.Error:
            if len(waiting) < 2 or not self._one_by_one(waiting):
                raise
            if also is not None:
                with self.store.write() as con:
                    also(con)
        self.written_at = time.monotonic()

    def _one_by_one(self, waiting: list[tuple[dict[str, Any], pa.Table, pa.Table | None]]) -> bool:
        """After a group's transaction failed (rolled back whole): each episode in a transaction of its own, so
        that one the store refuses does not lose the others; whether any was written (none: the store itself
        failed, e.g. a full disk, and the caller hears of it). The episodes refused again are left out, said on
        stderr."""
        written, refused = 0, []
        for episode, steps, nodes in waiting:
            try:
                with self.store.write() as con:
                    write_episode(con, episode, steps, nodes, replace=self.replace)
                written += 1
            except duckdb.Error as exc:
                refused.append((episode["episode_id"], exc))
        for episode_id, exc in refused:
            print(f"codearcade: episode {episode_id} not stored: {str(exc).splitlines()[0][:300]}", file=sys.stderr)
        return written > 0

    def __enter__(self) -> "EpisodeWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.flush()


def insert_candidate(con: duckdb.DuckDBPyConnection, row: dict[str, Any]) -> None:
    """Insert one ``candidates`` row; its ``feedback`` text is stored as a blob and referenced by hash."""
    row = dict(row)
    feedback = row.pop("feedback", None)
    row["feedback_hash"] = put_blob(con, "feedback", feedback) if feedback is not None else None
    row.setdefault("created_at", utcnow())
    _insert(con, "candidates", row)


def replace_audits(con: duckdb.DuckDBPyConnection, run_id: str, rows: list[dict[str, Any]]) -> None:
    """The run's ``audits`` rows, replacing those of an earlier audit of the run, and its audit episodes that the
    rows do not list (an earlier audit of more games, or of a best version since superseded): what is left of
    ``kind = 'audit'`` is this audit's games, as its rows say."""
    listed = [episode for row in rows for episode in row["episode_ids"]]
    earlier = [episode for (episode,) in con.execute(
        "SELECT episode_id FROM episodes WHERE run_id = ? AND kind = 'audit' AND NOT list_contains(?, episode_id)",
        [run_id, listed]).fetchall()]
    if earlier:
        delete_episodes(con, earlier)
    con.execute("DELETE FROM audits WHERE run_id = ?", [run_id])
    for row in rows:
        _insert(con, "audits", {"created_at": utcnow(), **row, "run_id": run_id})


def insert_iteration(con: duckdb.DuckDBPyConnection, row: dict[str, Any]) -> None:
    """Insert the ``iterations`` row that completes an iteration (the candidate its strategy chose)."""
    _insert(con, "iterations", row)


def insert_feedback(con: duckdb.DuckDBPyConnection, row: dict[str, Any]) -> None:
    """Insert the ``feedback`` row of an iteration (the feedback of its chosen candidate)."""
    _insert(con, "feedback", row)


def reject_policy_version(con: duckdb.DuckDBPyConnection, run_id: str, iteration: int, version_id: str,
                          reason: str) -> None:
    """Mark a version rejected after it was played (caught tampering with its score)."""
    con.execute("UPDATE policy_versions SET validation = 'rejected', validation_error = ? WHERE run_id = ? "
                "AND iteration = ? AND policy_version_id = ?", [reason, run_id, iteration, version_id])


def end_run_left_running(con: duckdb.DuckDBPyConnection, run_id: str, status: str, error: str | None) -> None:
    """End a run whose row still says 'running' (its loop never took it over); one ended already is left as it is."""
    con.execute("UPDATE runs SET status = ?, finished_at = ?, error = ? WHERE run_id = ? AND status = 'running'",
                [status, utcnow(), error, run_id])


def mark_run_running(con: duckdb.DuckDBPyConnection, run_id: str) -> None:
    con.execute("UPDATE runs SET status = 'running', finished_at = NULL, error = NULL WHERE run_id = ?", [run_id])


def merge_run_config(con: duckdb.DuckDBPyConnection, run_id: str, changed: dict[str, Any]) -> None:
    """Record settings changed on ``--resume`` (budgets, limits, endpoint) in the run's config."""
    con.execute("UPDATE runs SET config = json_merge_patch(config, ?) WHERE run_id = ?",
                [json.dumps(changed), run_id])
