"""The recording streams of codearcade's Rerun recordings: their application id, deterministic ids, the ambient
recording, and entity paths built from any text.

Every recording (an episode's, ``viewers/rerun_episode.py``; a run's, ``viewers/rerun_run.py``; two episodes side
by side, ``viewers/rerun_compare.py``) is made by :func:`new_recording`: application id ``codearcade``, the recording
id given (an episode id, a run id), only our own timelines, so that a recording rebuilt from the store holds the same
data as one written live. Every function that logs takes an explicit ``recording`` and falls back to the ambient
one (:func:`resolve_recording`), as Rerun's own functions do.
"""

from __future__ import annotations

import errno
import os
import re
import threading
from typing import Any, Callable

import rerun as rr

from viewers.whole_files import discard, finish, partial_path

APPLICATION_ID = "codearcade"


def resolve_recording(recording: rr.RecordingStream | None) -> rr.RecordingStream:
    """``recording``, or the ambient (thread-local or global) one; error if there is none."""
    if recording is not None:
        return recording
    ambient = rr.get_data_recording()
    if ambient is None:
        raise RuntimeError("no Rerun recording: pass recording=... or call rr.init()/use `with rec:` first")
    return ambient


def new_recording(recording_id: str, name: str | None = None) -> rr.RecordingStream:
    """A recording stream of application ``codearcade`` with a deterministic id (not made the default)."""
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    rec.set_log_time_enabled(False)  # only our own timelines: a rebuilt recording holds the same data as a live one
    rec.set_log_tick_enabled(False)
    rec.send_recording_name(name or recording_id)
    return rec


def save_to(recording: rr.RecordingStream, path: str | os.PathLike, **options) -> None:
    """``recording.save(path, **options)``, with Rerun's failure to write the file (a ``RuntimeError`` whose text
    ends in ``(os error N)``: a full disk, a read-only file system) raised as the ``OSError`` it is, naming
    ``path``, so that the command says which file could not be written instead of showing Rerun's traceback."""
    try:
        recording.save(os.fspath(path), **options)
    except RuntimeError as exc:
        code = re.search(r"\(os error (\d+)\)", str(exc))
        if code is None:
            raise
        number = int(code.group(1))
        raise OSError(number, os.strerror(number) if number in errno.errorcode else str(exc), os.fspath(path)) \
            from None


SINK_TIMEOUT_S = 30.0
"""How long a recording's sink may take to open, flush or close its file (:func:`within`) before it is given up."""

wedged = False
"""A sink in this process did not answer within its time (:func:`within`): its Rust thread is stuck for good, and a
process that records again (a game host's next episode) should be a fresh one."""


def within(what: str, action: Callable[[], Any], path: str | os.PathLike | None = None,
           timeout_s: float = SINK_TIMEOUT_S) -> Any:
    """``action()`` (a Rerun call that waits on a recording's sink: ``save``, ``flush``, ``disconnect``) in a thread
    of its own, waited for at most ``timeout_s``: past it an ``OSError`` (ETIMEDOUT) naming ``path`` says that Rerun
    did not ``what``. Once the disk under a recording filled, Rerun's file-writer thread died and ``disconnect``
    waited on it for good, inside Rust, where no signal reaches Python: an episode recorded with ``--rerun DIR``
    held its host until its time limit and was stored as the policy's time-out; ``view --save`` hung past Ctrl-C
    and SIGTERM. Rerun's own failure to write (its ``RuntimeError``) is raised as an ``OSError`` naming ``path``."""
    global wedged
    done: list[Any] = []
    failed: list[BaseException] = []

    def run() -> None:
        try:
            done.append(action())
        except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread below
            failed.append(exc)

    thread = threading.Thread(target=run, name=f"rerun sink: {what}", daemon=True)
    thread.start()
    thread.join(timeout_s)
    where = os.fspath(path) if path is not None else None
    if thread.is_alive() or failed:
        # Rerun's own exit hook flushes every recording, this one too: a sink that failed or hangs hung the
        # process at its exit (`view --save` on a full disk), past Ctrl-C
        rr.unregister_shutdown()
    if thread.is_alive():
        wedged = True
        raise OSError(errno.ETIMEDOUT, f"Rerun did not {what} within {timeout_s:g} s (a full disk?)", where)
    if failed:
        exc = failed[0]
        if isinstance(exc, RuntimeError) and where is not None:
            raise OSError(errno.EIO, f"Rerun could not {what} ({str(exc)[:200]}; a full disk?)", where) from None
        raise exc
    return done[0] if done else None


def save_whole(recording: rr.RecordingStream, path: str | os.PathLike, timeout_s: float = SINK_TIMEOUT_S,
               **options) -> str | None:
    """Start saving ``recording`` for ``path`` (:func:`save_to`), into ``path.partial`` until :func:`close` renames
    it: a file cut short (a full disk, an error while logging) is never left under the name asked for
    (``viewers/whole_files.py``). Returns the partial file's path; None where ``path`` is something other than a
    plain file (a device such as /dev/full, a pipe, a link), which is written as it is: a rename would replace it."""
    partial = partial_path(path)
    try:
        within("open the file", lambda: save_to(recording, partial or os.fspath(path), **options), path, timeout_s)
    except OSError as exc:
        discard(partial)  # made, and not written to
        raise OSError(exc.errno, exc.strerror, os.fspath(path)) from None
    return partial


def close(recording: rr.RecordingStream, partial: str | None = None, path: str | os.PathLike | None = None,
          whole: bool = True, timeout_s: float = SINK_TIMEOUT_S) -> None:
    """Flush and close ``recording``, each within ``timeout_s`` (:func:`within`); a file started by
    :func:`save_whole` (``partial``) is renamed to ``path`` once closed whole, and removed otherwise (``whole``
    False: the caller failed while logging; the error is the caller's, the file goes)."""
    try:
        if whole:
            within("flush the recording", lambda: recording.flush(timeout_sec=timeout_s), path, timeout_s)
        within("close the recording", recording.disconnect, path, timeout_s)
    except BaseException:
        discard(partial)
        if whole:
            raise
        return
    if whole:
        finish(partial, path)
    else:
        discard(partial)


def entity(*parts: str) -> str:
    """An entity path from parts that may hold any characters (method names, categories)."""
    return "/" + "/".join(rr.escape_entity_path_part(p) for p in parts)
