"""``ast.parse`` one thread at a time, on the Python versions whose parser needs it.

CPython before 3.13 keeps the depth of the tree ``ast.parse`` is converting to Python objects in state the whole
interpreter shares. When an allocation of that conversion runs a finalizer and the interpreter switches threads,
another thread's parse moves the depth, and the first parse fails with ``SystemError: AST constructor recursion
depth mismatch`` (python/cpython#106905). The proposal pool parses on several threads at once (each candidate's
prompt, reply and checks, and radon's metrics): CI saw a pool run end with that error, once.
:func:`serialize_ast_parse` wraps ``ast.parse`` with a lock for the whole process, radon's calls included; a parse
takes microseconds to milliseconds, so threads wait for each other no longer than that.
"""

from __future__ import annotations

import ast
import sys
import threading

NEEDED = sys.version_info < (3, 13)
"""Whether this Python shares a parse's depth between threads."""

_one_at_a_time = threading.RLock()  # re-entrant: a finalizer run inside a parse may parse too


def serialize_ast_parse() -> None:
    """Wrap ``ast.parse`` in this process with a lock, once; nothing where :data:`NEEDED` is false. Called before
    threads that parse start."""
    if not NEEDED or getattr(ast.parse, "one_at_a_time", False):
        return
    parse = ast.parse

    def parse_one_at_a_time(*args, **kwargs):
        with _one_at_a_time:
            return parse(*args, **kwargs)

    parse_one_at_a_time.__doc__ = parse.__doc__
    parse_one_at_a_time.one_at_a_time = True
    ast.parse = parse_one_at_a_time
