"""Opening the DuckDB store: per-use attachments, lock retries, migrations, clear errors.

DuckDB lets one process hold a database file for writing, and while it does every other process's open
(read-only too) fails. codearcade therefore never keeps the file open: every batch of writes and every query
attaches the file to the process's DuckDB instance (``store/hub.py``, ~2 ms), does its work and detaches it,
and an attach that meets a lock is retried with backoff for up to ``lock_timeout_s``. A writer holds the file for one transaction at a time, so readers (``codearcade sql``
during a run) get in between batches.

Errors are :class:`StoreError` with a one-line message: not a DuckDB file, written by a newer codearcade,
locked for too long, a directory that cannot be written, damaged (:func:`store_damage`: a table or view
missing, a truncated file; checked once per :class:`Store` before its first read or write, so nothing is
ever appended to a damaged store).
"""

from __future__ import annotations

import os
import random
import re
import sys
import threading
import time
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import duckdb

from store.hub import HUB
from store.locate import DEFAULT_STORE, StoreLocation, locate_store  # noqa: F401 (DEFAULT_STORE: re-exported)
from store.migrations import LATEST, MIGRATIONS, SCHEMA_MIGRATIONS_TABLE
from store.published import refresh_published


class StoreError(Exception):
    """A store that cannot be used; the message says why and what to do."""


class StoreFull(StoreError):
    """A store whose disk is full: its write was rolled back whole, and every process writing there fails alike
    until space is freed (a batch stops starting runs: ``pipeline/jobs/batch.py``)."""


class StoreDamaged(StoreError):
    """A store whose file is damaged (:func:`store_damage`, or cut too short for DuckDB to open it); ``problems``
    lists what was found, one short sentence each: the doctor reports them as findings."""

    def __init__(self, path: str | os.PathLike, problems: list[str], in_wal: bool = False) -> None:
        """``in_wal``: found by the checkpoint after a write (DuckDB reads a block only when it must): the write
        is committed to the WAL beside the file, which the file cannot take in."""
        kept = (f"this command's write stays in {os.path.basename(path)}.wal beside it, not in the file" if in_wal
                else "nothing was written to it")
        super().__init__(f"{path} is damaged: {'; '.join(problems)}; {kept} "
                         f"(`codearcade doctor --store {path}` reports what is left)")
        self.problems = problems


def _cut_short(path: str | os.PathLike, text: str) -> str | None:
    """The problem, when DuckDB's IO error ``text`` is a read past the end of the file at ``path`` (a truncated
    copy whose catalog lies beyond its end cannot even be opened); None for any other error."""
    match = re.search(r"attempted to read (\d+) bytes from location (\d+)", text)
    try:
        size = os.path.getsize(path)
    except OSError:
        return None
    if match is None or int(match[1]) + int(match[2]) <= size:
        return None
    return f"the file is truncated ({size:,} bytes; DuckDB reads {int(match[1]):,} at {int(match[2]):,})"


def default_store_path() -> str:
    """The store a command uses without ``--store`` (``store/locate.py``: ``$CODEARCADE_STORE``, the nearest
    ``codearcade.duckdb`` here or in a parent directory, the per-user store)."""
    return str(locate_store().path)


def utcnow() -> datetime:
    """Naive UTC timestamp, as the store's TIMESTAMP columns hold."""
    return datetime.now(timezone.utc).replace(tzinfo=None)


def _is_disk_full(exc: Exception) -> bool:
    text = str(exc)
    return "No space left" in text or "File too large" in text or "Disk quota" in text


def is_ctrl_c(exc: BaseException) -> bool:
    """Whether ``exc`` is a Ctrl-C that DuckDB caught. Two shapes: a SIGINT that arrives while a query runs is
    consumed by DuckDB's client and raised as ``RuntimeError('Query interrupted')`` (2.0; ``InterruptException`` in
    others); one that lands while DuckDB is calling Python (reading a registered Arrow table's schema, a Python
    function) is wrapped in the error DuckDB raises for that call, its text ending in the Python error's name:
    ``Invalid Input Error: reading the schema of the object registered as 'x' failed: KeyboardInterrupt:``."""
    if isinstance(exc, duckdb.InterruptException):
        return True
    if type(exc) is RuntimeError:
        return str(exc) == "Query interrupted"
    return isinstance(exc, duckdb.Error) and _WRAPPED_CTRL_C.search(str(exc)) is not None


_WRAPPED_CTRL_C = re.compile(r"(?:^|: )KeyboardInterrupt:?\s*\Z")
"""The end of the text of a DuckDB error that wraps a KeyboardInterrupt raised in the Python it called (anchored at
the end: a message that merely mentions the word, a stored value's, is not a Ctrl-C)."""


@contextmanager
def interrupted_by_ctrl_c(con: duckdb.DuckDBPyConnection) -> Iterator[None]:
    """While the block runs a query on ``con`` in the main thread: a Ctrl-C interrupts the query at once.

    Python runs a signal's handler only when the main thread runs Python code; DuckDB looks for one between its
    own steps, but while its threads call a Python function of the query's (``mean_ci`` over many rows) a press
    waited for the query's end, minutes later, and then had been ignored (the command ignores a second press
    while it winds down). The C-level handler also writes the signal's number to the wakeup file descriptor at
    once: a thread that watches it interrupts the query (``con.interrupt()``), and the press then ends it as any
    other (``is_ctrl_c``)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    import select
    import signal

    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    try:
        before = signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)
    except ValueError:  # not the main interpreter's main thread after all
        os.close(read_end)
        os.close(write_end)
        yield
        return
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            if select.select([read_end], [], [], 0.1)[0] and signal.SIGINT in os.read(read_end, 64):
                con.interrupt()

    watcher = threading.Thread(target=watch, name="ctrl-c watcher", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join()
        signal.set_wakeup_fd(before)
        os.close(read_end)
        os.close(write_end)


@contextmanager
def _ctrl_c_as_itself() -> Iterator[None]:
    """Give a Ctrl-C that DuckDB turned into an error back as the KeyboardInterrupt it was, so that the command
    winds down as after any Ctrl-C (the run interrupted, resumable; exit 130) instead of failing with a traceback.
    The transaction it cut has been rolled back by then."""
    try:
        yield
    except Exception as exc:
        if is_ctrl_c(exc):
            raise KeyboardInterrupt from None
        raise


@contextmanager
def _transaction(con: duckdb.DuckDBPyConnection) -> Iterator[None]:
    """The block in one transaction: committed at its end, rolled back if it raises."""
    con.execute("BEGIN TRANSACTION")
    try:
        yield
        con.execute("COMMIT")
    except BaseException:
        _rollback(con)
        raise


def _rollback(con: duckdb.DuckDBPyConnection) -> None:
    """Roll back the transaction, if one is still open (an interrupted or failed statement may have ended it)."""
    try:
        con.execute("ROLLBACK")
    except duckdb.Error:
        pass


def _first_line(exc: Exception) -> str:
    return str(exc).strip().splitlines()[0][:200]


def is_corrupt_block(exc: BaseException) -> bool:
    """Whether DuckDB raised ``exc`` for a block of the file whose checksum does not match (a plain ``duckdb.Error``,
    on opening or in any query that reads the block): the store's damage, never the query's fault."""
    return isinstance(exc, duckdb.Error) and "Corrupt database file" in str(exc)


def _corrupt_block(exc: BaseException) -> str:
    """The problem :func:`is_corrupt_block` names, with DuckDB's own words on the block (its last error)."""
    return f"a block is corrupt ({str(exc).split('Error: ', 1)[-1].split('Original error: ')[-1][:300]})"


def _lock_holder(text: str) -> str:
    """The process DuckDB's lock error ``text`` says holds the file (its path and PID)."""
    return text.split("Conflicting lock is held in", 1)[-1].split(". See also")[0].strip()


def _is_lock_error(exc: Exception) -> bool:
    text = str(exc)
    return "Could not set lock" in text or "Conflicting lock" in text


LOCK_NOTICE_AFTER_S = 3.0
"""How long a command waits on a store another process holds before it says so (once) on stderr."""
HEADER_BYTES = 3 * 4096
"""A DuckDB file's main header and its two database headers, before the first block."""


def required_objects(version: int) -> dict[str, str]:
    """The tables and views migrations 1..``version`` create (and do not drop), by name: ``TABLE`` or ``VIEW``."""
    objects: dict[str, str] = {"schema_migrations": "TABLE"} if version else {}
    pattern = re.compile(r"\b(CREATE(?:\s+OR\s+REPLACE)?|DROP)\s+(TABLE|VIEW)\s+(?:IF\s+(?:NOT\s+)?EXISTS\s+)?(\w+)",
                         re.IGNORECASE)
    for number, _, sql in MIGRATIONS:
        if number > version:
            break
        for verb, kind, name in pattern.findall(sql):
            if verb.upper() == "DROP":
                objects.pop(name.lower(), None)
            else:
                objects[name.lower()] = kind.upper()
    return objects


def store_damage(con: duckdb.DuckDBPyConnection, path: str | os.PathLike, version: int) -> list[str]:
    """Cheap structural checks of an open store at schema ``version`` (one catalog query, one size query): the
    tables and views its migrations made are there, and the file is long enough for the blocks DuckDB's header
    counts as used (a truncated copy is not). Each problem as a short sentence; an empty list when none is found. Deeper
    damage is ``codearcade doctor``'s (``store/doctor.py``)."""
    problems = []
    present = {name.lower(): kind for name, kind in con.execute(
        "SELECT table_name, CASE WHEN table_type = 'VIEW' THEN 'VIEW' ELSE 'TABLE' END "
        "FROM information_schema.tables WHERE table_catalog = current_database()").fetchall()}
    missing = [f"{kind.lower()} {name}" for name, kind in required_objects(version).items() if present.get(name) != kind]
    if missing:
        problems.append(f"{', '.join(missing)} missing")
    wal = Path(f"{path}.wal")
    if not wal.exists():  # a WAL not yet checkpointed may hold blocks the file does not have yet
        row = con.execute("SELECT block_size, used_blocks, total_blocks FROM pragma_database_size() "
                          "WHERE database_name = current_database()").fetchone()
        if row is not None:
            block, used, total = (int(x) for x in row)
            size = os.path.getsize(path)
            needed = HEADER_BYTES + block * used
            if size >= needed and size < HEADER_BYTES + block * total:
                # blocks past the file's end: free ones DuckDB cut off itself, or a cut file whose used blocks were
                # not all at its front (one sat at block 40 of a file of 34 used): where the tables' data lies
                needed = HEADER_BYTES + block * (_last_data_block(con) + 1)
            if size < needed:
                problems.append(f"the file is truncated ({size:,} bytes, its used blocks need at least {needed:,})")
    return problems


def _last_data_block(con: duckdb.DuckDBPyConnection) -> int:
    """The highest block that holds a segment of a table of the open store (-1: none); a scan of each table's
    storage layout, so only where the file is shorter than DuckDB's count of its blocks."""
    last = -1
    for (table,) in con.execute("SELECT table_name FROM duckdb_tables() WHERE database_name = current_database() "
                                "AND schema_name = 'main'").fetchall():
        found = con.execute("SELECT max(block_id) FROM pragma_storage_info(?) WHERE block_id >= 0",
                            [table]).fetchone()[0]
        if found is not None:
            last = max(last, int(found))
    return last


_USE_LOCKS: dict[str, threading.RLock] = {}
_USE_LOCKS_GUARD = threading.Lock()


def _one_use_at_a_time(path: Path) -> threading.RLock:
    """The lock that makes a process's threads use a store file one at a time (a read and a write of two threads
    at once would ask the hub to attach the file read-only and read-write together: ``store/hub.py``). Reentrant: a
    read inside a write of the same thread shares the write's attachment."""
    key = os.path.abspath(path)
    with _USE_LOCKS_GUARD:
        return _USE_LOCKS.setdefault(key, threading.RLock())


class Store:
    """A codearcade store at ``path``. Cheap to create; connections are opened per use.

    ``store.write()`` yields a read-write connection inside a transaction (committed on success, rolled back
    on error); ``store.read()`` yields a read-only connection. Both retry while another process holds the file.
    """

    def __init__(self, path: str | os.PathLike | StoreLocation | None = None, lock_timeout_s: float = 60.0,
                 write_lock_timeout_s: float = 600.0):
        location = path if isinstance(path, StoreLocation) else locate_store(path)
        self.location = location
        """How the store was chosen (``store/locate.py``): a path given here counts as ``--store``."""
        self.path = location.path
        self.lock_timeout_s = lock_timeout_s
        # a run must not fail because someone ran a long query meanwhile: writers wait longer than readers
        self.write_lock_timeout_s = max(write_lock_timeout_s, lock_timeout_s)
        self._migrated = False
        self._checked = False
        self._held = False
        """A :class:`Hold` of this object has the file attached: it was checked when it was taken."""

    def __repr__(self) -> str:
        return f"Store({str(self.path)!r})"

    def exists(self) -> bool:
        return self.path.exists()

    def _open(self, read_only: bool) -> duckdb.DuckDBPyConnection:
        """A connection to the store from the process's DuckDB instance (``store/hub.py``); give it back with
        ``HUB.release``. Retries while another process holds the file."""
        # Writes are small batches: one thread leaves the other core to the episode workers.
        if self.path.is_dir():
            raise StoreError(f"{self.path} is a directory, not a store file; give a file, e.g. --store "
                             f"{self.path / DEFAULT_STORE}")
        threads = (os.cpu_count() or 1) if read_only else 1
        timeout = self.lock_timeout_s if read_only else self.write_lock_timeout_s
        began = time.monotonic()
        deadline = began + timeout
        delay = 0.01
        told = False
        while True:
            try:
                return HUB.open(self.path, read_only=read_only, threads=threads)
            except duckdb.IOException as exc:
                text = str(exc)
                if "not a valid DuckDB database file" in text:
                    raise StoreError(f"{self.path} is not a codearcade store (not a DuckDB file); "
                                     "give another --store path") from None
                if _is_lock_error(exc):
                    if time.monotonic() >= deadline:
                        raise StoreError(f"{self.path} stayed locked by another process for "
                                         f"{timeout:g} s (held by {_lock_holder(text)}); wait for it or use "
                                         "another --store") from None
                    if not told and time.monotonic() - began >= LOCK_NOTICE_AFTER_S:
                        told = True  # a person waiting on a silent command: say what it waits for, once
                        print(f"codearcade: {self.path} is locked by another process ({_lock_holder(text)}); "
                              f"waiting up to {timeout:g} s for it (Ctrl-C stops)", file=sys.stderr, flush=True)
                    time.sleep(delay * (0.5 + random.random()))
                    delay = min(delay * 2, 0.25)
                    continue
                if "Permission denied" in text or "Read-only file system" in text:
                    raise StoreError(f"cannot write {self.path}: {text.split('Error: ', 1)[-1]}; "
                                     "choose a writable --store location") from None
                cut = _cut_short(self.path, text)
                if cut is not None:
                    raise StoreDamaged(self.path, [cut]) from None
                if "replaying WAL" in text:  # a WAL beside a file it was not written against: a backup put back
                    # beside a newer WAL, or a WAL copied in from another state of the store
                    raise StoreDamaged(self.path, [
                        f"its WAL ({self.path.name}.wal) does not belong to the file's state "
                        f"({text.split('Error: ', 1)[-1][:200]}): if the file is a backup put back, the WAL holds "
                        "writes made after it; move the WAL away only once you know you do not need them"]) \
                        from None
                raise StoreError(f"cannot open {self.path}: {text}") from None
            except duckdb.Error as exc:
                if is_corrupt_block(exc):
                    raise StoreDamaged(self.path, [_corrupt_block(exc)]) from None
                if "version" in str(exc).lower() and "storage" in str(exc).lower():
                    raise StoreError(f"{self.path} was written by an incompatible DuckDB: {exc}") from None
                raise

    def _check_version(self, con: duckdb.DuckDBPyConnection) -> int:
        has_table = con.execute(
            "SELECT count(*) FROM information_schema.tables "
            "WHERE table_catalog = current_database() AND table_name = 'schema_migrations'"
        ).fetchone()[0]
        if not has_table:
            others = con.execute(
                "SELECT count(*) FROM information_schema.tables WHERE table_catalog = current_database()"
            ).fetchone()[0]
            if others:  # an unrelated DuckDB database: never add our tables to it
                raise StoreError(f"{self.path} is a DuckDB database but not a codearcade store; "
                                 "give another --store path")
            return 0
        version = con.execute("SELECT coalesce(max(version), 0) FROM schema_migrations").fetchone()[0]
        if version > LATEST:
            raise StoreError(
                f"{self.path} has schema version {version}, newer than this codearcade understands ({LATEST}); "
                "upgrade codearcade to use it"
            )
        return version

    def _refuse_damage(self, con: duckdb.DuckDBPyConnection, version: int) -> None:
        """StoreError if :func:`store_damage` finds a problem (checked once per Store object)."""
        if self._checked or version == 0:
            return
        problems = store_damage(con, self.path, version)
        if problems:
            raise StoreDamaged(self.path, problems)
        self._checked = True

    def _migrate(self, con: duckdb.DuckDBPyConnection) -> None:
        current = self._check_version(con)
        self._refuse_damage(con, current)  # never append to, nor migrate, a damaged store
        if current == 0:  # a new store is made whole or not at all: a disk that filled up half-way left one of
            # version 2, which the next command "upgraded", saying so
            self._create(con)
            return
        if current < LATEST:  # the file changes for good, whatever verb opened it: say so, once
            print(f"codearcade: upgrading {self.path} from schema version {current} to {LATEST}; an older "
                  "codearcade will refuse it from now on", file=sys.stderr, flush=True)
        for version, name, sql in MIGRATIONS:
            if version <= current:
                continue
            with _transaction(con):
                self._apply(con, current, version, name, sql)
        with _transaction(con):  # the game modules' published figures, as they are in this code
            refresh_published(con)
        self._migrated = True

    def _create(self, con: duckdb.DuckDBPyConnection) -> None:
        """Every migration, and the published figures, in one transaction (a failure leaves no schema at all)."""
        with _transaction(con):
            con.execute(SCHEMA_MIGRATIONS_TABLE)
            for version, name, sql in MIGRATIONS:
                self._apply(con, 0, version, name, sql)
            refresh_published(con)
        self._migrated = True

    def _apply(self, con: duckdb.DuckDBPyConnection, current: int, version: int, name: str, sql: str) -> None:
        """Run migration ``version`` and record it, in the transaction open on ``con``."""
        try:
            con.execute(sql)
        except duckdb.CatalogException as exc:
            if "already exists" not in str(exc):
                raise
            # the tables of a migration the file does not list: its schema_migrations was emptied or edited (the
            # caller's transaction is rolled back)
            raise StoreDamaged(self.path, [f"schema_migrations lists version {current}, but the tables of "
                                           f"migration {version} ({name}) are there already"]) from None
        con.execute("INSERT INTO schema_migrations VALUES (?, ?, ?)", [version, name, utcnow()])

    def make_ready(self) -> None:
        """Create or upgrade the store and refuse a damaged one (:class:`StoreError`), unless this object has done
        so already: what a command checks before it plays anything."""
        if not self._migrated:
            with self.write():
                pass

    def hold(self) -> "Hold":
        """A :class:`Hold` on this store (not yet taken): see there."""
        return Hold(self)

    @contextmanager
    def write(self) -> Iterator[duckdb.DuckDBPyConnection]:
        """A read-write connection in a transaction; creates and migrates the store on first use.

        A transaction that fails (a full disk included) is rolled back whole: what was committed before stays.
        """
        parent = self.path.parent
        if not parent.exists() and self.location.rule == "user":  # the per-user store's directory, made once
            parent.mkdir(parents=True, exist_ok=True)
        if not parent.exists():
            raise StoreError(f"directory {parent} for the store does not exist; create it or choose another --store")
        if not os.access(parent, os.W_OK) and not self.path.exists():
            raise StoreError(f"cannot create {self.path}: directory {parent} is not writable; choose another --store")
        with _one_use_at_a_time(self.path), _ctrl_c_as_itself():
            yield from self._write()

    def _write(self) -> Iterator[duckdb.DuckDBPyConnection]:
        con = self._open(read_only=False)
        try:
            if not self._migrated:
                self._migrate(con)
            con.execute("BEGIN TRANSACTION")
            try:
                yield con
                con.execute("COMMIT")
            except BaseException:
                _rollback(con)  # a failed COMMIT has already ended the transaction
                raise
        except duckdb.Error as exc:
            if _is_disk_full(exc):
                raise StoreFull(f"cannot write {self.path}: the disk is full ({_first_line(exc)}); free space "
                                 "and run the command again: what was stored before is intact") from None
            if "Permission denied" in str(exc):  # the commit makes the WAL beside the file: its folder's rights
                raise StoreError(f"cannot write {self.path}: DuckDB writes {self.path.name}.wal beside it, and "
                                 f"{self.path.parent} is not writable ({_first_line(exc)}); make the folder "
                                 "writable or choose another --store: what was stored before is intact") from None
            raise
        finally:
            try:
                HUB.release(self.path, con)  # detaching checkpoints the WAL into the file: a full disk fails here too
            except duckdb.Error as exc:
                if is_corrupt_block(exc):  # a block no query had read: the checkpoint rewrote it and met the damage
                    raise StoreDamaged(self.path, [_corrupt_block(exc)], in_wal=True) from None
                if not _is_disk_full(exc):
                    raise

    @contextmanager
    def read(self, check: bool = True) -> Iterator[duckdb.DuckDBPyConnection]:
        """A read-only connection to an existing store; ``check=False`` skips the damage check (the doctor)."""
        if not self.path.exists():
            where = (f"no {DEFAULT_STORE} in {os.getcwd()} or a parent directory, and no per-user store at "
                     f"{self.path}" if self.location.rule == "user" else f"no store at {self.path}")
            raise StoreError(f"{where}; run `codearcade eval` or `codearcade optimize` first, "
                             "or point --store / CODEARCADE_STORE at an existing one")
        with _one_use_at_a_time(self.path), _ctrl_c_as_itself():
            yield from self._read(check)

    def _read(self, check: bool) -> Iterator[duckdb.DuckDBPyConnection]:
        if self._held:  # attached by this process's hold, checked and migrated: nothing to look at again
            con = self._open(read_only=True)
            try:
                yield con
            finally:
                HUB.release(self.path, con)
            return
        con = self._open(read_only=True)
        try:
            version = self._check_version(con)
            if check:
                self._refuse_damage(con, version)
            if version < LATEST and check:  # an older store: upgrade it once, then read
                HUB.release(self.path, con)
                con = None
                with self.write():
                    pass
                con = self._open(read_only=True)
            yield con
        finally:
            if con is not None:
                HUB.release(self.path, con)

    def query(self, sql: str, params: list[Any] | None = None) -> list[tuple]:
        """Run one read-only query and return all rows."""
        with self.read() as con:
            return con.execute(sql, params or []).fetchall()


class Hold:
    """Keeps a store's file attached across several short reads and writes of one process, so that they share
    one attachment and the file is checkpointed once, when the hold is let go, instead of after every write
    (each costs ~20 ms here whatever it writes). Commits still go to the write-ahead log as they happen: a
    process killed while holding loses nothing committed.

    While it is held no other process can open the file, so hold it only across work that takes milliseconds
    (the optimizer: from storing an iteration's LLM answers through its commit and the next iteration's prompt;
    let go while the model is asked and before episodes are played) — never across an LLM call or an episode.
    ``take()`` and ``release()`` may be called repeatedly, ``release()`` from another thread (the optimizer lets
    go, checkpointing, while its request is on its way).
    """

    def __init__(self, store: Store):
        self.store = store
        self._cursor: duckdb.DuckDBPyConnection | None = None

    def take(self) -> None:
        if self._cursor is None:
            self.store.make_ready()  # creates and migrates the store on first use
            self._cursor = self.store._open(read_only=False)
            self.store._held = True

    def release(self) -> None:
        cursor, self._cursor = self._cursor, None
        if cursor is not None:
            self.store._held = False
            try:
                with _ctrl_c_as_itself():  # a press during the checkpoint is a Ctrl-C, not a failure of the run
                    HUB.release(self.store.path, cursor)  # the checkpoint: a full disk fails here
            except duckdb.Error as exc:
                if not _is_disk_full(exc):
                    raise

    def __enter__(self) -> "Hold":
        self.take()
        return self

    def __exit__(self, *exc) -> None:
        self.release()
