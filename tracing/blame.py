"""Line origins of policy versions, carried from version to version like ``git blame``.

Every line of a version's trainable methods has an origin: the version that introduced it. A line of a new
version that the diff against its parent version (the same method's source; ``tracing/line_diff.py``: difflib's
matcher without its junk heuristic, at a bounded cost for long ones) matches to a parent line keeps that line's
origin; every other line (added or changed) has the new version as its origin. A method the parent lacks is all
new. Lines are compared as written, trailing whitespace aside: a re-indented line is a changed line, as in git.

Origins are opaque here (the store passes its own ``(version, iteration, produced_by)`` records); the line
texts and numbers are those of the method's stored source (``tracing/lines.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, Mapping, Sequence, TypeVar

from tracing.line_diff import matching_lines
from tracing.lines import executable_lines

Origin = TypeVar("Origin")


@dataclass(frozen=True)
class BlamedLine(Generic[Origin]):
    """One line of a method's source with where it came from."""

    line_no: int
    text: str
    executable: bool
    origin: Origin


def source_lines(source: str) -> list[str]:
    """The lines of a method's source as blame numbers them (1-based by position), without line ends."""
    return source.splitlines()


def blame_function(source: str, parent: Sequence[tuple[str, Origin]] | None, new_origin: Origin) -> list[BlamedLine]:
    """Every line of ``source`` with its origin: carried from ``parent`` (its lines as ``(text, origin)``,
    in order) where the diff matches them, ``new_origin`` elsewhere."""
    lines = source_lines(source)
    origins: list[Origin] = [new_origin] * len(lines)
    if parent:
        old = [text.rstrip() for text, _ in parent]
        for i, j in matching_lines(old, [text.rstrip() for text in lines]):
            origins[j] = parent[i][1]
    runnable = set(executable_lines(source))
    return [BlamedLine(i + 1, text, i + 1 in runnable, origins[i]) for i, text in enumerate(lines)]


def blame_version(sources: Mapping[str, str], parent: Mapping[str, Sequence[tuple[str, Origin]]] | None,
                  new_origin: Origin) -> dict[str, list[BlamedLine]]:
    """:func:`blame_function` for each method of a version (``sources`` by name), against the parent's
    lines of the method of the same name."""
    parent = parent or {}
    return {name: blame_function(source, parent.get(name), new_origin) for name, source in sources.items()}
