"""Line matching at a bounded cost (tracing/line_diff.py): what blame and compare's diffs are made of.

Two oracles: on texts of the size people and models write, the result is difflib's, to the character; on long,
hostile texts (shapes that made difflib's matcher cubic: 326 s of a held store for two replies under the code
cap, 84 s of `compare`), every exact match it makes is on a bounded number of line pairs, and what it matches is
a valid alignment (equal lines, in both texts' order).
"""

from __future__ import annotations

import difflib
import random

import pytest

from tracing import line_diff
from tracing.blame import blame_function


@pytest.mark.parametrize("seed", range(6))
def test_on_texts_people_write_the_diff_is_difflib_s(seed):
    rng = random.Random(seed)
    for _ in range(400):
        pool = [f"line {k}\n" for k in range(rng.randint(1, 9))]
        a = [rng.choice(pool) for _ in range(rng.randint(0, 60))]
        b = [rng.choice(pool) for _ in range(rng.randint(0, 60))]
        if a and rng.random() < 0.3:
            a[-1] = a[-1].rstrip("\n")  # a last line without its end, as difflib writes it
        assert list(line_diff.unified_diff(a, b, "A", "B")) == list(difflib.unified_diff(a, b, "A", "B"))
        matched = line_diff.matching_lines([x.rstrip() for x in a], [x.rstrip() for x in b])
        expected = difflib.SequenceMatcher(None, [x.rstrip() for x in a], [x.rstrip() for x in b], autojunk=False)
        assert matched == [(m.a + k, m.b + k) for m in expected.get_matching_blocks() for k in range(m.size)]


def _hostile(n: int, shape: str, rng: random.Random) -> tuple[list[str], list[str]]:
    """Two long texts of a shape that is costly to match."""
    def alternating(count: int, flip: int) -> list[str]:
        return ["    x = ()" if (k + flip) % 2 else "    x = []" for k in range(count)]

    if shape == "one line against alternating":
        return ["    x = ()"] * n, alternating(n, 0)
    if shape == "alternating, shifted":
        return alternating(n, 0), alternating(n, 1)
    if shape == "anchors between alternating runs":
        gap = rng.randint(50, 220)
        a = [line for k in range(0, n, gap + 1) for line in [f"    anchor_{k} = 1", *alternating(gap, 0)]][:n]
        b = [line for k in range(0, n, gap + 1) for line in [f"    anchor_{k} = 1", *alternating(gap, 1)]][:n]
        return a, b
    lines = [f"    v{k} = {k}" for k in range(n)]  # unique lines, shuffled in blocks
    shuffled = list(lines)
    for start in range(0, n, 37):
        block = shuffled[start:start + 37]
        rng.shuffle(block)
        shuffled[start:start + 37] = block
    return lines, shuffled


@pytest.mark.parametrize("shape", ["one line against alternating", "alternating, shifted",
                                   "anchors between alternating runs", "unique lines shuffled in blocks"])
def test_long_hostile_texts_are_matched_at_a_bounded_cost(shape, monkeypatch):
    rng = random.Random(shape)
    exact_calls = []
    real_exact = line_diff._exact

    def counted(a, b):
        exact_calls.append(len(a) * len(b))
        return real_exact(a, b)

    monkeypatch.setattr(line_diff, "_exact", counted)
    for n in (250, 1000, 3200, 18_000):  # 18,000 lines: a served submission's 200,000 characters
        exact_calls.clear()
        a, b = _hostile(n, shape, rng)
        pairs = line_diff.matching_lines(a, b)
        assert all(a[i] == b[j] for i, j in pairs)
        assert all(i1 < i2 and j1 < j2 for (i1, j1), (i2, j2) in zip(pairs, pairs[1:])), "an alignment"
        assert all(work <= line_diff.EXACT_GAP_PAIRS for work in exact_calls), (n, max(exact_calls))
        assert sum(exact_calls) <= line_diff.EXACT_GAP_PAIRS * (n // 100 + 1), (n, sum(exact_calls))
    # blame goes through it: a 3,200-line method against its parent, each line's origin one of the two
    parent, child = _hostile(3200, shape, rng)
    blamed = blame_function("\n".join(child), [(line, "parent") for line in parent], "child")
    assert len(blamed) == 3200 and {line.origin for line in blamed} <= {"parent", "child"}


def test_the_prompt_s_memory_diffs_are_difflib_s_at_a_bounded_cost(monkeypatch):
    """The optimizer's prompt diffs each memory entry's methods against the current version's (both from replies):
    it used difflib's own matcher, and two methods built for it (lines cycling through 50 names just under its
    popularity filter, against the same names each followed by `()`) took 2.7 s a prompt, 20 s within a 32k budget,
    with the store held. Oracles: people-size methods get difflib's text to the character (a replay's prompts
    stay the same); the hostile pair is matched with a bounded area of line pairs searched."""
    import string

    from pipeline.optimizer import prompt

    def difflib_diff(old: dict[str, str], new: dict[str, str]) -> str:  # the prompt's diff as it was
        lines: list[str] = []
        for name in sorted(set(old) | set(new)):
            a, b = old.get(name, "").splitlines(), new.get(name, "").splitlines()
            if a != b:
                lines.extend(difflib.unified_diff(a, b, f"iteration version: {name}", f"current version: {name}",
                                                  n=1, lineterm=""))
        return "\n".join(lines)

    rng = random.Random(7)
    for _ in range(300):
        pool = [f"    x = {k}" for k in range(rng.randint(1, 12))]
        methods = [{name: "\n".join(rng.choice(pool) for _ in range(rng.randint(0, 150)))
                    for name in rng.sample(["act", "aim", "plan"], rng.randint(1, 3))} for _ in range(2)]
        assert prompt._diff(*methods) == difflib_diff(*methods)
    searched = []
    real_search = difflib.SequenceMatcher.find_longest_match

    def counted(self, alo=0, ahi=None, blo=0, bhi=None):
        ahi, bhi = len(self.a) if ahi is None else ahi, len(self.b) if bhi is None else bhi
        searched.append((ahi - alo) * (bhi - blo))
        return real_search(self, alo, ahi, blo, bhi)

    monkeypatch.setattr(difflib.SequenceMatcher, "find_longest_match", counted)
    names = [a + b for a in string.ascii_lowercase for b in string.ascii_lowercase][:50]
    old = "def act(self, obs):\n    return 0\n" + "".join(f"    {names[k % 50]}\n" for k in range(2100))
    new = "def act(self, obs):\n    return 0\n" + "".join(f"    {names[k % 50]}\n    ()\n" for k in range(1250))
    diff = prompt._diff({"act": old}, {"act": new})
    assert diff.startswith("--- iteration version: act\n+++ current version: act\n@@ ") and "+    ()" in diff
    assert sum(searched) <= line_diff.EXACT_GAP_PAIRS * (len(new.splitlines()) // 100 + 1), sum(searched)
