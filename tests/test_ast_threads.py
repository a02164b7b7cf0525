"""``ast.parse`` one thread at a time (``tracing/ast_threads.py``): the proposal pool's threads parse at once, and
CPython before 3.13 failed a parse now and then (``SystemError: AST constructor recursion depth mismatch``)."""

from __future__ import annotations

import ast
import threading
import time

import pytest

from tracing.ast_threads import NEEDED, serialize_ast_parse


def _parse_on_threads(threads: int = 4, parses: int = 5) -> None:
    def parse_all() -> None:
        for _ in range(parses):
            assert isinstance(ast.parse("x = 1"), ast.Module)

    workers = [threading.Thread(target=parse_all) for _ in range(threads)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()


@pytest.mark.skipif(not NEEDED, reason="this Python keeps a parse's depth per call")
def test_threads_parse_one_at_a_time_once_serialized(monkeypatch):
    """By its effect: a parse that lasts 20 ms, on four threads, has one thread inside it at a time once serialized,
    and several before (the check can fail)."""
    real, lock = ast.parse, threading.Lock()
    inside, seen = [0], []

    def slow_parse(*args, **kwargs):
        with lock:
            inside[0] += 1
            seen.append(inside[0])
        time.sleep(0.02)
        with lock:
            inside[0] -= 1
        return real(*args, **kwargs)

    monkeypatch.setattr(ast, "parse", slow_parse)
    _parse_on_threads()
    assert max(seen) > 1, "without the lock the threads overlap: the check below could fail"
    serialize_ast_parse()
    seen.clear()
    _parse_on_threads()
    assert max(seen) == 1 and len(seen) == 20
    serialize_ast_parse()  # again: wrapped once, not twice
    assert ast.parse.one_at_a_time and ast.parse("y = 2").body[0].targets[0].id == "y"
