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

import rerun as rr

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


def entity(*parts: str) -> str:
    """An entity path from parts that may hold any characters (method names, categories)."""
    return "/" + "/".join(rr.escape_entity_path_part(p) for p in parts)
