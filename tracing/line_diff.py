"""Which lines of two texts match, at a cost bounded by their length: for blame and for diffs of policy texts.

Policy texts come from LLM replies and served submissions, and they are matched in the trusted process, blame
inside the store's write transaction. :class:`difflib.SequenceMatcher` without its junk heuristic is cubic in
the worst case: a method of 1,000 lines alternating ``()`` and ``[]`` against its parent took 7.3 s, two replies
under the 8,000-token code cap held ``optimize`` (and the store, for every other command) for 326 s, and
``compare`` of two 100 KB files spent 84 s in ``difflib.unified_diff``. Here:

- texts whose lines multiply to at most :data:`EXACT_PAIRS` are matched by ``SequenceMatcher`` as before (every
  method a person or a model writes: the same result as ever);
- longer ones keep their common first and last lines, then match the lines that occur once on each side, in
  an order both keep (the patience diff's anchors: a longest increasing subsequence, ``O(n log n)``); each gap
  between anchors is matched exactly where it is small (:data:`EXACT_GAP_PAIRS`), and its lines otherwise
  count as changed. Every line is looked at a bounded number of times, so the cost grows as ``n log n`` plus
  at most ``n / 100`` small exact matches.
"""

from __future__ import annotations

import bisect
import difflib
from collections import Counter
from typing import Iterator, Sequence

EXACT_PAIRS = 200 * 200
"""Texts whose line counts multiply to at most this are matched exactly (``SequenceMatcher``, no junk)."""
EXACT_GAP_PAIRS = 100 * 100
"""A gap between anchors whose line counts multiply to at most this is matched exactly; a longer one is changed."""


def matching_lines(a: Sequence[str], b: Sequence[str]) -> list[tuple[int, int]]:
    """Pairs ``(i, j)`` of matched lines, ``a[i] == b[j]``, increasing in both (see the module docstring)."""
    if len(a) * len(b) <= EXACT_PAIRS:
        return _exact(a, b)
    head = 0
    while head < min(len(a), len(b)) and a[head] == b[head]:
        head += 1
    tail = 0
    while tail < min(len(a), len(b)) - head and a[len(a) - 1 - tail] == b[len(b) - 1 - tail]:
        tail += 1
    middle_a, middle_b = a[head:len(a) - tail], b[head:len(b) - tail]
    pairs = [(k, k) for k in range(head)]
    pairs += [(head + i, head + j) for i, j in _anchored(middle_a, middle_b)]
    pairs += [(len(a) - tail + k, len(b) - tail + k) for k in range(tail)]
    return pairs


def _exact(a: Sequence[str], b: Sequence[str]) -> list[tuple[int, int]]:
    matcher = difflib.SequenceMatcher(None, a, b, autojunk=False)
    return [(block.a + k, block.b + k) for block in matcher.get_matching_blocks() for k in range(block.size)]


def _anchored(a: Sequence[str], b: Sequence[str]) -> list[tuple[int, int]]:
    """Lines once on each side as anchors, in an order both keep; the gaps between them matched if small."""
    once_a, once_b = Counter(a), Counter(b)
    where_b = {line: j for j, line in enumerate(b) if once_b[line] == 1}
    anchors = _longest_increasing([(i, where_b[line]) for i, line in enumerate(a)
                                   if once_a[line] == 1 and line in where_b])
    pairs: list[tuple[int, int]] = []
    last_i = last_j = -1
    for i, j in [*anchors, (len(a), len(b))]:
        gap_a, gap_b = a[last_i + 1:i], b[last_j + 1:j]
        if gap_a and gap_b and len(gap_a) * len(gap_b) <= EXACT_GAP_PAIRS:
            pairs += [(last_i + 1 + x, last_j + 1 + y) for x, y in _exact(gap_a, gap_b)]
        if i < len(a):
            pairs.append((i, j))
        last_i, last_j = i, j
    return pairs


def _longest_increasing(pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The longest run of ``pairs`` (increasing in their first) whose seconds increase too: patience sorting."""
    tops: list[int] = []  # the smallest last second of a run of each length
    ends: list[int] = []  # the index in pairs of that run's last pair
    before = [-1] * len(pairs)
    for k, (_, j) in enumerate(pairs):
        length = bisect.bisect_left(tops, j)
        if length == len(tops):
            tops.append(j)
            ends.append(k)
        else:
            tops[length], ends[length] = j, k
        before[k] = ends[length - 1] if length else -1
    run, k = [], ends[-1] if ends else -1
    while k != -1:
        run.append(pairs[k])
        k = before[k]
    return run[::-1]


class BoundedMatcher(difflib.SequenceMatcher):
    """A ``SequenceMatcher`` of lines whose matching blocks are :func:`matching_lines`': ``get_opcodes`` and
    ``get_grouped_opcodes`` (what a unified diff is made of) then cost what it does."""

    def __init__(self, a: Sequence[str], b: Sequence[str]):
        super().__init__(None, a, b, autojunk=False)

    def find_longest_match(self, *args, **kwargs):  # pragma: no cover - only get_matching_blocks is used
        raise NotImplementedError("BoundedMatcher matches whole texts only")

    def get_matching_blocks(self) -> list[difflib.Match]:
        if self.matching_blocks is None:
            blocks: list[list[int]] = []
            for i, j in matching_lines(self.a, self.b):
                if blocks and blocks[-1][0] + blocks[-1][2] == i and blocks[-1][1] + blocks[-1][2] == j:
                    blocks[-1][2] += 1
                else:
                    blocks.append([i, j, 1])
            self.matching_blocks = [difflib.Match(*block) for block in blocks]
            self.matching_blocks.append(difflib.Match(len(self.a), len(self.b), 0))
        return self.matching_blocks


def unified_diff(a: Sequence[str], b: Sequence[str], fromfile: str, tofile: str, context: int = 3) -> Iterator[str]:
    """``difflib.unified_diff`` of two lists of lines (ends kept), its matching bounded (:class:`BoundedMatcher`)."""
    started = False
    for group in BoundedMatcher(a, b).get_grouped_opcodes(context):
        if not started:
            started = True
            yield f"--- {fromfile}\n"
            yield f"+++ {tofile}\n"
        first, last = group[0], group[-1]
        yield f"@@ -{_range(first[1], last[2])} +{_range(first[3], last[4])} @@\n"
        for tag, i1, i2, j1, j2 in group:
            if tag == "equal":
                yield from (" " + line for line in a[i1:i2])
                continue
            if tag in ("replace", "delete"):
                yield from ("-" + line for line in a[i1:i2])
            if tag in ("replace", "insert"):
                yield from ("+" + line for line in b[j1:j2])


def _range(start: int, stop: int) -> str:
    """A hunk's range as ``difflib.unified_diff`` writes it: ``start,length``, 1-based (``start`` alone for 1)."""
    beginning, length = start + 1, stop - start
    if length == 1:
        return f"{beginning}"
    if not length:
        beginning -= 1  # an empty range is written as the line before it
    return f"{beginning},{length}"
