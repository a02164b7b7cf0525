"""Files the viewers write appear whole or not at all: written as ``FILE.partial``, renamed to ``FILE`` once whole.

A full disk left a PNG cut short or an empty README.md under the name asked for (``report``, ``compare --out``), and
a Rerun recording cut short at 40-130 KB (``eval --rerun``, ``view --save``); a kill while a file was written, the
same. Two decisions, made here once for every such file: where to write (:func:`partial_path`: the partial file, or
the path itself where it exists and is not a plain file, since a rename would replace a device such as /dev/full, a
pipe or a link) and what becomes of it (:func:`finish` renames, :func:`discard` removes quietly). :func:`writing` is
both around a block, for writers that finish within one (matplotlib's PNGs, Markdown); Rerun's recordings are opened
and closed apart (``viewers/rerun_recording.py``). No Rerun, no matplotlib here: the report must not import Rerun.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

PARTIAL_SUFFIX = ".partial"


def partial_path(path: str | os.PathLike) -> str | None:
    """Where to write ``path``: ``path.partial``, or None where ``path`` exists and is not a plain file (a link, a
    device such as /dev/full, a pipe), which is written as it is."""
    target = os.fspath(path)
    if os.path.lexists(target) and (os.path.islink(target) or not os.path.isfile(target)):
        return None
    return target + PARTIAL_SUFFIX


def finish(partial: str | None, path: str | os.PathLike) -> None:
    """``partial`` (from :func:`partial_path`) written whole: it becomes ``path`` (nothing to do where it was None)."""
    if partial is not None:
        os.replace(partial, os.fspath(path))


def discard(partial: str | None) -> None:
    """``partial`` not written whole: removed, quietly (never made, or already gone: nothing cut short is left
    either way)."""
    if partial is None:
        return
    try:
        os.unlink(partial)
    except OSError:
        pass


@contextmanager
def writing(path: Path) -> Iterator[Path]:
    """Write ``path`` in the block, into the path it yields (:func:`partial_path`, or ``path`` itself), renamed to
    ``path`` once the block ended whole and removed otherwise (an error, Ctrl-C, SIGTERM). An ``OSError`` that names
    no file (PIL's, and a write's, on a full disk) is raised naming ``path``, so that the command says in one line
    which file it could not write (it showed a traceback)."""
    partial = partial_path(path)
    into = Path(partial) if partial is not None else path
    try:
        yield into
        finish(partial, path)
    except BaseException as exc:
        discard(partial)
        if not isinstance(exc, OSError) or exc.filename is not None and exc.filename != os.fspath(into):
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
