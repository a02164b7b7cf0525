"""Guarded execution of untrusted policy code: a source check, restricted builtins, an import allow-list,
and time limits.

Policy files and LLM-generated methods are untrusted. This module is the in-process layer of defence:

- :func:`check_source` rejects, before anything runs, code that reaches for interpreter internals: dunder
  attributes (``x.__class__.__subclasses__``), frame and code attributes (``gi_frame``, ``f_globals``, ...),
  names such as ``eval``/``exec``/``open``/``__import__``, and ``except:`` / ``except BaseException``
  (which would swallow the time limit).
- :func:`safe_builtins` is the builtins namespace policy code sees: no ``open``, ``eval``, ``exec``,
  ``compile``, ``input``, ``globals``...; ``__import__`` admits only :data:`ALLOWED_MODULES` and hands out a
  read-only view of the module without its private (``_``-prefixed) names, so ``random._os`` is out of reach;
  ``getattr``/``setattr``/``delattr``/``hasattr`` refuse dunder names.
- Microsoft Trace's policy API: ``import opto.trace as trace``, ``from opto.trace import bundle, Module, ...``
  and ``from opto import trace`` are admitted for the modules and names of :data:`TRACE_API`, and answered
  with read-only views of codearcade's own implementation (``tracing/trace_api.py``). Nothing named ``opto``
  is installed or imported: a real Trace beside codearcade is neither shadowed nor used, and the rest of
  Trace (``opto.optimizers``, ``opto.utils``, ...) is refused like any other module.
- :class:`CallTimer` / :func:`time_limit` interrupt a call that runs too long with :class:`PolicyTimeout`
  (SIGALRM; main thread); :class:`EpisodeTimer` does it for every call of an episode in a process with no other
  thread (the policy process), with one interval timer instead of two system calls a call.

What this does not do: it is no security boundary (any allowed module that re-exports ``sys`` or
``builtins`` leaks, and it cannot interrupt a long-running C call). The boundary is the operating system:
policy code runs only in a worker process with no secrets, confined by the kernel (``pipeline/boundary/zygotes.py``,
``pipeline/boundary/zygote.py``, ``pipeline/boundary/confine.py``; see docs/sandbox.md).
"""

from __future__ import annotations

import ast
import builtins
import signal
import time
import types
from contextlib import contextmanager
from typing import Any, Callable, Iterator

ALLOWED_MODULES = frozenset(
    {
        "math", "cmath", "random", "numpy", "collections", "itertools", "functools", "operator",
        "statistics", "heapq", "bisect", "dataclasses", "typing", "enum", "copy", "string", "re",
        "fractions", "decimal", "abc", "__future__", "tracing",
    }
)
"""Top-level modules policy code may import (their submodules too, such as ``numpy.linalg``)."""

TRACE_PACKAGE = "opto"
TRACE_API: dict[str, tuple[str, ...]] = {
    "opto.trace": ("ExecutionError", "GRAPH", "Module", "Node", "bundle", "model", "node", "stop_tracing"),
    "opto.trace.bundle": ("bundle",),
    "opto.trace.errors": ("ExecutionError",),
    "opto.trace.modules": ("Module", "model"),
    "opto.trace.nodes": ("GRAPH", "Node", "node"),
}
"""Trace's policy API as policy code may import it: each ``opto.trace`` module and the names it offers (where
Trace defines them), all implemented by ``tracing/trace_api.py``. ``from opto import trace`` is admitted too."""

FORBIDDEN_NAMES = frozenset(
    {
        "eval", "exec", "compile", "open", "input", "breakpoint", "globals", "locals", "vars", "help",
        "exit", "quit", "memoryview", "__import__", "__builtins__", "__loader__", "__spec__",
    }
)
"""Names policy code may not even mention."""

FORBIDDEN_ATTRIBUTES = frozenset(
    {
        "gi_frame", "gi_code", "cr_frame", "cr_code", "ag_frame", "ag_code", "f_globals", "f_locals",
        "f_builtins", "f_back", "f_code", "tb_frame", "tb_next", "co_code", "func_globals", "mro",
    }
)
"""Non-dunder attributes that lead to frames, globals or code objects."""

ALLOWED_DUNDERS = frozenset({"__init__", "__call__", "__name__", "__len__", "__iter__", "__next__"})
"""Dunder attributes that are harmless and common in ordinary code (``super().__init__()``)."""

# Submodules/functions of allowed modules that touch files, native code or processes.
_DENIED_MODULE_ATTRIBUTES = frozenset(
    {
        "ctypeslib", "f2py", "distutils", "testing", "load", "save", "savez", "savez_compressed",
        "savetxt", "loadtxt", "genfromtxt", "fromfile", "memmap", "DataSource", "show_config",
        "SystemRandom",
    }
)


class PolicyCodeError(Exception):
    """Policy source that is refused before it runs (syntax error or a forbidden construct)."""

    def __init__(self, message: str, filename: str = "<policy>", lineno: int | None = None):
        self.filename = filename
        self.lineno = lineno
        where = f"{filename}:{lineno}: " if lineno else f"{filename}: "
        super().__init__(where + message)


class PolicyTimeout(BaseException):
    """Raised inside policy code that exceeded its time limit.

    A BaseException so that ``except Exception`` in policy code does not swallow it (``except:`` and
    ``except BaseException`` are refused by :func:`check_source`).
    """


def _is_dunder(name: str) -> bool:
    return name.startswith("__") and name.endswith("__")


def check_source(source: str, filename: str = "<policy>") -> ast.Module:
    """Parse ``source`` and refuse forbidden constructs; return the AST. Raises :class:`PolicyCodeError`."""
    try:
        tree = ast.parse(source, filename=filename)
    except SyntaxError as exc:
        raise PolicyCodeError(f"syntax error: {exc.msg}", filename, exc.lineno) from None
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            attr = node.attr
            if (_is_dunder(attr) and attr not in ALLOWED_DUNDERS) or attr in FORBIDDEN_ATTRIBUTES:
                raise PolicyCodeError(f"access to attribute '{attr}' is not allowed", filename, node.lineno)
        elif isinstance(node, ast.Name):
            if node.id in FORBIDDEN_NAMES:
                raise PolicyCodeError(f"use of '{node.id}' is not allowed", filename, node.lineno)
        elif isinstance(node, ast.ExceptHandler):
            caught = node.type
            names = []
            if caught is None:
                names = ["(bare except)"]
            else:
                for n in caught.elts if isinstance(caught, ast.Tuple) else [caught]:
                    if isinstance(n, ast.Name) and n.id in ("BaseException", "KeyboardInterrupt", "SystemExit"):
                        names.append(n.id)
            if names:
                raise PolicyCodeError(
                    f"catching {names[0]} is not allowed (it would swallow the time limit); "
                    "catch Exception or a specific error instead",
                    filename,
                    node.lineno,
                )
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            if isinstance(node, ast.ImportFrom) and node.level:
                raise PolicyCodeError("relative imports are not allowed", filename, node.lineno)
            if isinstance(node, ast.Import):
                for alias in node.names:
                    _check_module_allowed(alias.name, None, filename, node.lineno)
            else:
                module = node.module or ""
                _check_module_allowed(module, [a.name for a in node.names], filename, node.lineno)
            for alias in node.names:
                if alias.name.startswith("_") and isinstance(node, ast.ImportFrom) and module != "__future__":
                    raise PolicyCodeError(f"importing private name '{alias.name}' is not allowed", filename, node.lineno)
    return tree


def _check_module_allowed(module: str, names: list[str] | None = None, filename: str = "<policy>",
                          lineno: int | None = None) -> None:
    """Refuse an import of ``module`` (``names``: what ``from module import ...`` takes; None for ``import``)."""
    top = module.split(".")[0]
    if top == TRACE_PACKAGE:
        _check_trace_import(module, names, filename, lineno)
    elif top not in ALLOWED_MODULES:
        raise PolicyCodeError(
            f"import of '{module}' is not allowed; allowed modules: {', '.join(sorted(ALLOWED_MODULES - {'__future__'}))}",
            filename,
            lineno,
        )


def _trace_children(module: str) -> list[str]:
    """The short names of :data:`TRACE_API`'s modules directly below ``module`` (``opto``: ``trace``)."""
    prefix = module + "."
    return [m[len(prefix):] for m in TRACE_API if m.startswith(prefix) and "." not in m[len(prefix):]]


def _check_trace_import(module: str, names: list[str] | None, filename: str, lineno: int | None) -> None:
    offered = ", ".join(TRACE_API["opto.trace"])
    if module not in TRACE_API and module != TRACE_PACKAGE:
        raise PolicyCodeError(
            f"import of '{module}' is not allowed; of Trace, policy code may import only its policy API, "
            f"opto.trace ({offered}), which codearcade provides",
            filename,
            lineno,
        )
    if module == TRACE_PACKAGE and names is None:
        raise PolicyCodeError("write `import opto.trace as trace` or `from opto import trace`: of Trace, policy "
                              "code may import only opto.trace", filename, lineno)
    available = set(TRACE_API.get(module, ())) | set(_trace_children(module))
    for name in names or ():
        if name != "*" and name not in available:
            raise PolicyCodeError(
                f"'{name}' is not part of Trace's policy API as codearcade provides it; {module} offers "
                f"{', '.join(sorted(available))}",
                filename,
                lineno,
            )


class SafeModule(types.ModuleType):
    """A read-only view of an allowed module without its private names or file/native-code entry points."""

    def __init__(self, module: types.ModuleType):
        super().__init__(module.__name__, getattr(module, "__doc__", None))
        object.__setattr__(self, "_SafeModule__module", module)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_") or name in _DENIED_MODULE_ATTRIBUTES:
            raise AttributeError(f"module '{self.__name__}' has no attribute '{name}' available to policies")
        value = getattr(self._SafeModule__module, name)
        if isinstance(value, types.ModuleType) and not isinstance(value, SafeModule):
            return _safe_module(value)
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"module '{self.__name__}' is read-only for policies")

    def __dir__(self) -> list[str]:
        return [n for n in dir(self._SafeModule__module) if not n.startswith("_")]


_safe_modules: dict[str, SafeModule] = {}


def _safe_module(module: types.ModuleType) -> SafeModule:
    view = _safe_modules.get(module.__name__)
    if view is None:
        view = _safe_modules[module.__name__] = SafeModule(module)
    return view


def _trace_view(module: str, api: types.ModuleType) -> SafeModule:
    """The read-only view policy code gets for ``opto`` or a module of :data:`TRACE_API`: exactly the names that
    module offers, taken from ``api`` (``tracing/trace_api.py``), and the views of the modules below it."""
    view = _safe_modules.get(module)  # policy code can import no real module named opto*, so no clash
    if view is None:
        stub = types.ModuleType(module, api.__doc__)
        for child in _trace_children(module):
            setattr(stub, child, _trace_view(f"{module}.{child}", api))
        for name in TRACE_API.get(module, ()):
            setattr(stub, name, getattr(api, name))  # a name wins over a module of the same name, as in Trace
        view = _safe_modules[module] = SafeModule(stub)
        object.__setattr__(view, "__all__", list(TRACE_API.get(module, _trace_children(module))))
    return view


def _guarded_import(name, globals=None, locals=None, fromlist=(), level=0, *, trace_api=None):
    if level:
        raise ImportError("relative imports are not allowed in policy code")
    try:
        _check_module_allowed(name, list(fromlist) if fromlist else None)
    except PolicyCodeError as exc:
        raise ImportError(str(exc).split(": ", 1)[1]) from None
    if name.split(".")[0] == TRACE_PACKAGE:
        if trace_api is None:
            raise ImportError(f"Trace's policy API ({name}) is not offered here")
        # `from opto.trace import x` takes x from opto.trace's view; `import opto.trace [as t]` binds opto.
        return _trace_view(name if fromlist else TRACE_PACKAGE, trace_api)
    module = builtins.__import__(name, None, None, fromlist or (), 0)
    if fromlist:
        for item in fromlist:
            if item.startswith("_") and name != "__future__":
                raise ImportError(f"importing private name '{item}' is not allowed")
        return _safe_module(module) if name != "__future__" else module
    # `import a.b` binds the top-level package `a`.
    return _safe_module(module)


def _refuse_dunder(name: Any) -> None:
    if isinstance(name, str) and ((_is_dunder(name) and name not in ALLOWED_DUNDERS) or name in FORBIDDEN_ATTRIBUTES):
        raise AttributeError(f"attribute '{name}' is not accessible to policy code")


def _safe_getattr(obj, name, *default):
    _refuse_dunder(name)
    return getattr(obj, name, *default)


def _safe_hasattr(obj, name):
    _refuse_dunder(name)
    return hasattr(obj, name)


def _safe_setattr(obj, name, value):
    _refuse_dunder(name)
    if isinstance(obj, (type, types.ModuleType)):
        raise AttributeError("policy code may not modify classes or modules with setattr")
    return setattr(obj, name, value)


def _safe_delattr(obj, name):
    _refuse_dunder(name)
    return delattr(obj, name)


def safe_builtins(trace_api: types.ModuleType | None = None) -> dict[str, Any]:
    """The ``__builtins__`` mapping for policy code (a fresh dict: policies cannot alter each other's).

    ``trace_api``: the module whose names answer imports of Trace's policy API (``tracing/trace_api.py``, which
    the policy loader passes: it is built on ``tracing/bundle.py``, which uses this module's checks, so this
    module does not import it); None: such imports raise ImportError."""
    allowed = {
        name: value
        for name, value in vars(builtins).items()
        if not name.startswith("_") and name not in FORBIDDEN_NAMES
    }
    allowed.update(
        # a closure, not functools.partial: a partial shows its arguments as plain attributes
        __import__=lambda name, globals=None, locals=None, fromlist=(), level=0: _guarded_import(
            name, globals, locals, fromlist, level, trace_api=trace_api),
        __build_class__=builtins.__build_class__,
        __name__="builtins",
        getattr=_safe_getattr,
        hasattr=_safe_hasattr,
        setattr=_safe_setattr,
        delattr=_safe_delattr,
    )
    return allowed


class CallTimer:
    """Interrupt policy calls that run too long, with :class:`PolicyTimeout` raised from SIGALRM.

    Enter it once per episode (it installs the signal handler), then ``arm(seconds)`` before each policy call
    and ``disarm()`` after: two cheap ``setitimer`` calls per step. Main thread only. An expired limit re-fires
    every 50 ms until disarmed, so code that swallows one interruption still cannot continue for long.
    """

    REFIRE_S = 0.05

    def __init__(self) -> None:
        self._message = "policy call exceeded its time limit"
        self._armed_for: tuple[float, str] | None = None
        self._previous: Any = None

    def __enter__(self) -> "CallTimer":
        self._previous = signal.signal(signal.SIGALRM, self._expired)
        return self

    def __exit__(self, *exc: object) -> None:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, self._previous)

    def _expired(self, signum: int, frame: Any) -> None:
        raise PolicyTimeout(self._message)

    def arm(self, seconds: float | None, what: str = "policy call") -> None:
        if seconds and 0 < seconds < float("inf"):  # inf (``--call-time-limit 0``): no limit; setitimer refuses it
            if self._armed_for != (seconds, what):  # the same limit every step: its message is made once
                self._armed_for = (seconds, what)
                self._message = f"{what} exceeded its time limit of {seconds:g} s"
            signal.setitimer(signal.ITIMER_REAL, seconds, self.REFIRE_S)

    def disarm(self) -> None:
        signal.setitimer(signal.ITIMER_REAL, 0)

    def call(self, seconds: float | None, policy: Callable[[Any], Any], obs: Any) -> Any:
        """``policy(obs)`` under a limit of ``seconds``: the one policy call of a step."""
        self.arm(seconds)
        try:
            return policy(obs)
        finally:
            self.disarm()


class EpisodeTimer:
    """The call limit of every policy call of an episode, for a process whose only thread is the one that calls the
    policy (the policy process: its seccomp filter refuses threads). :class:`CallTimer` arms and disarms a timer
    around each call, two ``setitimer`` system calls a step; this one starts one interval timer for the episode,
    ticking every :data:`CallTimer.REFIRE_S` (a tenth of the limit if that is less), and each tick raises
    :class:`PolicyTimeout` if a call has run past the limit: a call is stopped within a tick of its limit, and code
    that swallows one interruption is interrupted again at the next tick, as with :class:`CallTimer`. Between
    calls a tick does nothing (a blocking read it interrupts is resumed)."""

    def __init__(self, seconds: float | None, what: str = "policy call") -> None:
        self.limit = seconds if seconds and 0 < seconds < float("inf") else None
        self.tick = min(CallTimer.REFIRE_S, self.limit / 10) if self.limit else None
        self._message = f"{what} exceeded its time limit of {seconds:g} s" if self.limit else ""
        self._since: float | None = None
        """When the call under way began (``time.monotonic()``); None between calls."""
        self._previous: Any = None

    def __enter__(self) -> "EpisodeTimer":
        if self.limit is not None:
            self._previous = signal.signal(signal.SIGALRM, self._tick)
            signal.setitimer(signal.ITIMER_REAL, self.tick, self.tick)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.limit is not None:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self._previous)

    def _tick(self, signum: int, frame: Any) -> None:
        since = self._since
        if since is not None and time.monotonic() - since >= self.limit:
            raise PolicyTimeout(self._message)

    def call(self, policy: Callable[[Any], Any], obs: Any) -> Any:
        """``policy(obs)`` under the episode's limit: the one policy call of a step."""
        self._since = time.monotonic()
        try:
            return policy(obs)
        finally:
            self._since = None


@contextmanager
def time_limit(seconds: float | None, what: str = "policy call") -> Iterator[None]:
    """Run the block under a :class:`CallTimer` limit of ``seconds`` (None or <= 0: no limit)."""
    with CallTimer() as timer:
        timer.arm(seconds, what)
        try:
            yield
        finally:
            timer.disarm()
