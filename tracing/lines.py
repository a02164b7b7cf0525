"""Which lines of a bundled method's source can run, and which did run in one call.

Lines are numbered within the method's own source as stored (``policy_versions.functions[].source``: the
``def`` line is 1, decorators are not part of it), so the lines recorded for a node, the lines of
``policy_lines`` (blame) and the line numbers a person reads in ``codearcade blame`` are the same numbers.

:func:`executable_lines` compiles the source (nothing runs) and reads the line table of its code objects,
nested ones (comprehensions, lambdas, inner functions) included: the lines that can report a line event.
The ``def`` line itself is left out, as are the docstring, comments, blank lines and ``else:``.

:class:`LineCall` runs one call under :func:`sys.settrace` (Python 3.11 has no ``sys.monitoring``),
limited to the frames of that method's code: the global trace function answers every Python call inside
the policy call, but it hands a line tracer only to frames of the method itself (and of code nested in it),
so line events fire only there. A bundled method called from inside the method is its own node and records
its own lines. The previous trace function (a debugger, coverage) is restored afterwards.
"""

from __future__ import annotations

import sys
import types
import warnings
from typing import Any, Callable


def executable_lines(source: str) -> list[int]:
    """Lines (1-based, within ``source``) of a method's ``def`` block that hold code; [] if it does not compile."""
    try:
        with warnings.catch_warnings():  # a policy's `x is 1` printed Python's SyntaxWarning on the user's stderr
            warnings.simplefilter("ignore")
            module = compile(source, "<lines>", "exec", dont_inherit=True)
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return []
    lines: set[int] = set()
    pending = [c for c in module.co_consts if isinstance(c, types.CodeType)]
    header = {c.co_firstlineno for c in pending}  # the def line (RESUME, MAKE_CELL): no line event fires there
    while pending:
        code = pending.pop()
        lines.update(line for _, _, line in code.co_lines() if line is not None)
        pending.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
    return sorted(lines - header)


_settrace, _gettrace = sys.settrace, sys.gettrace


class LineCall:
    """One call of a method with its lines recorded: ``call(*args)``, then ``lines()`` (also after a raise).

    It runs around every bundled call of a traced episode: the per-call work is two ``settrace`` calls and two
    closures; the rest is the trace function's, once per line that runs."""

    __slots__ = ("fn", "first_line", "last_line", "ran")

    def __init__(self, fn: Callable, first_line: int, n_lines: int):
        self.fn = fn
        self.first_line = first_line
        self.last_line = first_line + n_lines - 1
        self.ran: set[int] = set()

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        add = self.ran.add
        fn = self.fn
        target = fn.__code__
        filename, first, last = target.co_filename, self.first_line, self.last_line

        def on_line(frame: Any, event: str, _arg: Any) -> Any:
            if event == "line":
                add(frame.f_lineno)
            return on_line

        def on_call(frame: Any, event: str, _arg: Any) -> Any:
            code = frame.f_code
            if code is target or (code.co_filename == filename and first <= code.co_firstlineno <= last):
                return on_line
            return None  # any other function: no line events for it

        previous = _gettrace()
        _settrace(on_call)
        try:
            return fn(*args, **kwargs)
        finally:
            _settrace(previous)

    def lines(self) -> tuple[int, ...]:
        """Lines of the method's source (1-based) that ran, in order (a tuple: the garbage collector stops
        tracking a tuple of ints, and a traced episode keeps one per node)."""
        first, last = self.first_line, self.last_line
        offset = first - 1
        return tuple(sorted([line - offset for line in self.ran if first <= line <= last]))
