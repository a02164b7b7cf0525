"""One process per run: an advisory lock file per run, beside the store.

Two processes working on the same optimization run (a batch started twice, ``--resume`` of a run that is
still going) would both write its next iteration. :func:`run_lock` takes an exclusive ``flock`` on
``<store>.locks/<run_id>.lock`` for as long as the run is worked on. The kernel drops the lock when the
holder dies, ``kill -9`` included, so a killed run can be resumed at once, and a live one cannot be run twice.
"""

from __future__ import annotations

import fcntl
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


class RunBusyError(RuntimeError):
    """Another live process is working on the run: ``holder`` (its pid, as its lock file says)."""

    def __init__(self, message: str, holder: str) -> None:
        super().__init__(message)
        self.holder = holder


def lock_path(store_path: str | os.PathLike, run_id: str) -> Path:
    store_path = Path(store_path)
    return store_path.with_name(store_path.name + ".locks") / f"{run_id}.lock"


def lock_folder(store_path: str | os.PathLike) -> Path:
    """The folder of the store's run locks, made if it is not there; :class:`~store.db.StoreError` in one line
    when it cannot be (a file of that name, a folder that is not writable); left to the store where the store's
    own folder is not there yet. Called before a run is made, so that a run is never made that could not be locked
    (it was, then failed)."""
    from store.db import StoreError

    folder = lock_path(store_path, "-").parent
    if not folder.parent.is_dir():  # the store's own folder: the store makes it (the per-user one), or says why not
        return folder
    try:
        folder.mkdir(exist_ok=True)
    except FileExistsError:
        raise StoreError(f"{folder} is a file: codearcade keeps the store's run locks in a folder of that name "
                         "beside the store; move the file away") from None
    except OSError as exc:
        raise StoreError(f"cannot make {folder}, where codearcade keeps the store's run locks: "
                         f"{exc.strerror or exc}") from None
    return folder


@contextmanager
def run_lock(store_path: str | os.PathLike, run_id: str) -> Iterator[None]:
    """Hold the run's lock for the block; :class:`RunBusyError` at once if another process holds it."""
    path = lock_path(store_path, run_id)
    lock_folder(store_path)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "another process"
            raise RunBusyError(f"run {run_id} is being worked on by process {holder}; wait for it to finish "
                               "(or stop it) first", holder) from None
        os.ftruncate(fd, 0)
        try:
            os.pwrite(fd, str(os.getpid()).encode(), 0)
        except OSError:  # a full disk: the pid only names the holder in another's error; the lock is the flock
            pass  # (`batch` and `optimize` died here with a traceback before saying the store's disk was full)
        yield
    finally:
        os.close(fd)  # closing drops the lock


def run_is_live(store_path: str | os.PathLike, run_id: str) -> bool:
    """Whether some live process holds the run's lock (a run left ``running`` without one was killed)."""
    path = lock_path(store_path, run_id)
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
