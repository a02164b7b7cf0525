"""One in-memory DuckDB instance per process, to which store files are attached while they are used.

``duckdb.connect(path)`` starts a whole database instance (buffer manager, thread pool): ~15-25 ms, paid by
every batch of writes when a store is opened per use. ``ATTACH``ing the file to an instance that already runs
takes ~2 ms, and ``DETACH`` checkpoints the file and releases its lock just as closing a connection did (other
processes get in between uses as before). An evaluation writes after every episode; this makes each write
about three times cheaper.

Fork safety: a DuckDB instance keeps threads, and this process forks (episode workers; ``subprocess`` with
``preexec_fn``). Before a fork, an idle instance is closed, so no DuckDB thread exists in the forking process;
a child never uses an instance it inherited (it starts its own).
"""

from __future__ import annotations

import hashlib
import os
import threading
from dataclasses import dataclass

import duckdb


@dataclass
class _Attachment:
    alias: str
    read_only: bool
    users: int = 0


WRITE_ROW_GROUP_SIZE = 2048
"""Rows per row group of what this process appends (DuckDB's default: 122,880; 2,048 is its minimum).

Every commit's checkpoint rewrites the table's last, partly filled row group. Writing a Space Invaders
episode (660 steps, 24,000 objects) 120 times to a growing store took ~40 ms a write either way, but with the
default size the worst writes took 0.85-1 s, with 2,048-row groups 72-116 ms (bench/store_writes.py). Scans
of the steps table measured the same. Larger groups made a file smaller still (a traced Pong step 43 bytes with
16,384 rows, 69-80 with 2,048; bench/store_bytes.py) but widen what one checkpoint rewrites, and so holds: ten
episodes of 2,000 node values of 15.6 KB each, written one by one, peaked the writer at 1,047 MB of memory and
made a 470 MB file with 16,384-row groups, 378 MB and 314 MB with 2,048: what a row group of node rows can hold,
and a checkpoint rewrite, grows with its rows (2,048 rows of two 16,000-character values: about one episode's
byte budget)."""

NEW_STORE_BLOCK_SIZE = 65536
"""Block size of a store file this process creates (DuckDB's default: 256 KiB). A DuckDB file keeps the block size
it was made with, so an older store keeps its 256 KiB blocks and reads and writes as before.

A file grows by whole blocks, each table claims blocks of its own and each checkpoint's last block per table stays
partly empty: with 256 KiB blocks an empty store was 1.3 MB (396 KiB now) and the unfilled ends of blocks were
most of a step's bytes. 16 and 32 KiB blocks made the same evaluation's file larger again than 64 KiB ones (more
metadata per block); reading was no slower (bench/prompt_build.py on 1M steps)."""


class Hub:
    """The process's instance and the store files attached to it (see the module docstring)."""

    def __init__(self) -> None:
        self._con: duckdb.DuckDBPyConnection | None = None
        self._pid = 0
        self._lock = threading.RLock()
        self._attached: dict[str, _Attachment] = {}
        self._threads: int | None = None

    def _instance(self) -> duckdb.DuckDBPyConnection:
        if self._con is None or self._pid != os.getpid():
            self._con = duckdb.connect(":memory:")
            self._pid = os.getpid()
            self._attached = {}
            self._threads = None
        return self._con

    def open(self, path: str | os.PathLike, read_only: bool, threads: int | None = None) -> duckdb.DuckDBPyConnection:
        """A connection whose default database is the store file at ``path``; give it back with :meth:`release`.

        Attaches the file on its first use in this process; a use inside another of the same file shares the
        attachment (a read inside a write; a write inside a read-only use raises RuntimeError). DuckDB's errors
        (a lock held by another process, not a DuckDB file, ...) propagate unchanged, with nothing attached.
        ``threads`` sets the instance's thread count (writers take one, leaving the other cores to workers).
        """
        key = os.path.abspath(path)
        alias = "store_" + hashlib.sha1(key.encode()).hexdigest()[:12]
        with self._lock:
            con = self._instance()
            attachment = self._attached.get(key)
            if attachment is not None and attachment.read_only and not read_only:
                raise RuntimeError(f"{path} is open read-only in this process: a write cannot nest inside a read")
            try:
                if attachment is None:
                    quoted = key.replace("'", "''")
                    options = "READ_ONLY" if read_only else f"ROW_GROUP_SIZE {WRITE_ROW_GROUP_SIZE}"
                    if not read_only:  # the size of a file made by this ATTACH (an existing file keeps its own)
                        con.execute(f"SET default_block_size = {int(NEW_STORE_BLOCK_SIZE)}")
                    # a release that Ctrl-C cut between forgetting the file and detaching it may have left it
                    # attached: let it go first (a no-op otherwise)
                    con.execute(f"DETACH DATABASE IF EXISTS {alias}")
                    con.execute(f"ATTACH '{quoted}' AS {alias} ({options})")
                    attachment = self._attached[key] = _Attachment(alias, read_only)
                if threads is not None and threads != self._threads:
                    con.execute(f"SET threads = {int(threads)}")
                    self._threads = threads
                cursor = con.cursor()
                attachment.users += 1
            except BaseException:
                # Ctrl-C (KeyboardInterrupt) can land between any two of these steps, e.g. after DuckDB attached
                # the file and before it was recorded here: leave nothing half attached, or the next use (the
                # command marking its run interrupted) fails with "database ... already exists"
                if attachment is None or attachment.users == 0:
                    self._forget(key, alias)
                raise
        try:
            cursor.execute(f"USE {attachment.alias}")
        except BaseException:
            self.release(path, cursor)
            raise
        return cursor

    def release(self, path: str | os.PathLike, cursor: duckdb.DuckDBPyConnection) -> None:
        """Close ``cursor``; after the last use of the file, detach it (checkpointing it; errors propagate)."""
        key = os.path.abspath(path)
        try:
            cursor.close()
        finally:
            with self._lock:
                attachment = self._attached.get(key)
                if attachment is None or self._con is None:
                    return
                attachment.users -= 1
                if attachment.users > 0:
                    return
                del self._attached[key]
                try:
                    self._con.execute(f"DETACH {attachment.alias}")
                except BaseException:
                    self._close()  # the file may still be attached: closing the instance lets it go for sure
                    raise

    def _forget(self, key: str, alias: str) -> None:
        """Detach ``alias`` if DuckDB attached it, and forget it here (under the lock)."""
        self._attached.pop(key, None)
        if self._con is None:
            return
        try:
            self._con.execute(f"DETACH DATABASE IF EXISTS {alias}")
        except BaseException:
            self._close()  # closing the instance lets every file go for sure
            raise

    def _close(self) -> None:
        con, self._con, self._attached = self._con, None, {}
        if con is not None:
            con.close()

    def before_fork(self) -> None:
        """Close an idle instance, so that the process forks without DuckDB threads."""
        if self._lock.acquire(blocking=False):
            try:
                if self._con is not None and self._pid == os.getpid() and not self._attached:
                    self._close()
            finally:
                self._lock.release()

    def after_fork_in_child(self) -> None:
        """Forget the parent's instance: its threads do not exist here, so it is never used, nor even closed
        (closing would wait for them); it stays referenced until the process ends."""
        if self._con is not None:
            _inherited.append(self._con)
        self._con = None
        self._attached = {}
        self._lock = threading.RLock()


_inherited: list[duckdb.DuckDBPyConnection] = []


HUB = Hub()
os.register_at_fork(before=HUB.before_fork, after_in_child=HUB.after_fork_in_child)
