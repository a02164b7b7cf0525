"""Trainable policy code: the ``bundle`` decorator, the ``Module`` base class and the ``model`` class decorator.

A policy in the paper's style runs with only its import line changed::

    import tracing as trace

    @trace.model
    class Policy(trace.Module):
        def __call__(self, obs):
            y = self.predict_ball_trajectory(obs)
            return self.select_action(y, obs)

        @trace.bundle(trainable=True)
        def predict_ball_trajectory(self, obs):
            "Return the y where the ball meets the paddle plane, or None."
            ...

Each bundled method is a :class:`BundledMethod` descriptor on the class. Its current code is a
:class:`TrainableCode` parameter: ``policy.parameters()`` lists them, ``param.source`` is the method's source
text (the ``def`` through its end, docstring included, decorators left out) and ``param.set_source(text)``
compiles new text in the policy's sandboxed namespace and swaps the behaviour in at once, for every
instance of the class. When a :class:`~tracing.capture.NodeRecorder` is active, every call of a bundled
method is recorded as a node (see ``tracing/capture.py``); when none is, the call costs one extra check.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import linecache
import textwrap
from typing import Any, Callable

from tracing import capture
from tracing.sandbox import PolicyCodeError, check_source


class TrainableCode:
    """The source of one bundled method: a parameter that can be read and replaced at run time."""

    def __init__(self, name: str, fn: Callable, source: str, trainable: bool, owner_name: str, first_line: int = 1):
        self.name = name
        self.trainable = trainable
        self.owner_name = owner_name
        self.fn = fn
        self.source = source
        self.first_line = first_line
        """Line of ``fn``'s code file where ``source`` begins: line ``k`` of ``source`` is line
        ``first_line + k - 1`` there (node capture maps the lines that ran back to ``source``'s numbering)."""

    @property
    def docstring(self) -> str | None:
        """The method's docstring, read from the current source."""
        return ast.get_docstring(_single_function(self.source, self.name))

    @property
    def signature(self) -> str:
        """``name(arg, ...)`` of the current source, for prompts and validation."""
        node = _single_function(self.source, self.name)
        return f"{self.name}({ast.unparse(node.args)})"

    def set_source(self, source: str) -> None:
        """Compile ``source`` (one ``def`` of the same name) in the policy's namespace and use it from now on.

        Raises :class:`~tracing.sandbox.PolicyCodeError` if the text does not parse, defines something else,
        or uses a construct the sandbox refuses; the current code is kept then.
        """
        source = _normalize(source)
        self.fn = compile_method(source, self.name, self.fn.__globals__, f"{self.owner_name}.{self.name}")
        self.source = source
        self.first_line = 1  # compile_method compiles exactly ``source``

    def __repr__(self) -> str:
        return f"TrainableCode({self.owner_name}.{self.name}, trainable={self.trainable}, {len(self.source)} chars)"


def _normalize(source: str) -> str:
    return textwrap.dedent(source).strip("\n") + "\n"


def _single_function(source: str, name: str) -> ast.FunctionDef:
    try:
        tree = ast.parse(textwrap.dedent(source))
    except SyntaxError as exc:
        raise PolicyCodeError(f"syntax error: {exc.msg}", f"<{name}>", exc.lineno) from None
    functions = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    if len(functions) != 1 or len(tree.body) != 1:
        raise PolicyCodeError(f"expected exactly one 'def {name}(...)' and nothing else", f"<{name}>")
    node = functions[0]
    if isinstance(node, ast.AsyncFunctionDef):
        raise PolicyCodeError("async methods are not supported", f"<{name}>", node.lineno)
    if node.name != name:
        raise PolicyCodeError(f"the code defines '{node.name}' but the parameter is '{name}'", f"<{name}>", node.lineno)
    return node


def compile_method(source: str, name: str, namespace: dict[str, Any], qualname: str) -> Callable:
    """Compile one method's source (decorators dropped) in ``namespace`` and return the plain function.

    The text is registered in :mod:`linecache` under a content-addressed file name, so tracebacks and node
    exceptions show the failing line of the new code.
    """
    source = _normalize(source)
    digest = hashlib.sha256(source.encode()).hexdigest()[:10]
    filename = f"<policy {qualname} {digest}>"
    check_source(source, filename)
    node = _single_function(source, name)
    node.decorator_list = []
    code = compile(ast.Module(body=[node], type_ignores=[]), filename, "exec")
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    local: dict[str, Any] = {}
    exec(code, namespace, local)
    fn = local[name]
    fn.__qualname__ = qualname
    return fn


def method_source(fn: Callable) -> str:
    """The ``def`` block of ``fn`` (without decorators), dedented, read from the file it was compiled from."""
    return method_block(fn)[0]


def method_block(fn: Callable) -> tuple[str, int]:
    """:func:`method_source` and the line of the file where that block (its ``def`` line) begins."""
    code = fn.__code__
    lines = linecache.getlines(code.co_filename)
    if not lines:
        raise PolicyCodeError(f"cannot read the source of {fn.__qualname__}", code.co_filename)
    for name, first, start, end in _functions("".join(lines)):
        if name == fn.__name__ and code.co_firstlineno in (first, start):
            return _normalize("".join(lines[start - 1 : end])), start
    raise PolicyCodeError(f"cannot find the source of {fn.__qualname__}: bundle a method written with `def` in "
                          "the class, under the bundle decorator (not a lambda, nor a function another decorator "
                          "made)", code.co_filename, code.co_firstlineno)


@functools.lru_cache(maxsize=16)
def _functions(text: str) -> tuple[tuple[str, int, int, int], ...]:
    """Every function defined in ``text``: (name, line of its first decorator or its ``def``, line of its ``def``,
    its last line). Parsed once per text: each bundled method of a policy asks while its class is built, and a
    whole-file parse per method cost a policy process ~1 ms each at every load."""
    found = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.decorator_list[0].lineno if node.decorator_list else node.lineno
            found.append((node.name, first, node.lineno, node.end_lineno))
    return tuple(found)


class BundledMethod:
    """Descriptor for a method marked with :func:`bundle`; holds its :class:`TrainableCode` parameter."""

    def __init__(self, fn: Callable, trainable: bool):
        self._fn = fn
        self.trainable = trainable
        self.parameter: TrainableCode | None = None
        self.__doc__ = fn.__doc__
        self.__name__ = fn.__name__

    def __set_name__(self, owner: type, name: str) -> None:
        source, first_line = method_block(self._fn)
        self.parameter = TrainableCode(name, self._fn, source, self.trainable, owner.__name__, first_line)

    def __get__(self, instance: Any, owner: type | None = None) -> Any:
        if instance is None:
            return self
        parameter = self.parameter

        def call(*args: Any, **kwargs: Any) -> Any:
            recorder = capture.ACTIVE
            if recorder is None:
                return parameter.fn(instance, *args, **kwargs)
            return recorder.call(parameter, instance, args, kwargs)

        return call


def bundle(trainable: bool = False, **_ignored: Any) -> Callable[[Callable], BundledMethod]:
    """Mark a policy method as a traced operation; ``trainable=True`` lets the optimizer rewrite it.

    Extra keyword arguments of Trace's ``bundle`` (``catch_execution_error``, ``allow_external_dependencies``,
    ...) are accepted and ignored, so the paper's policies run unchanged.
    """

    def decorate(fn: Callable) -> BundledMethod:
        if isinstance(fn, BundledMethod):
            return fn
        return BundledMethod(fn, trainable)

    return decorate


class Module:
    """Base class of policies: ``policy(obs)`` calls ``forward(obs)`` unless the class defines ``__call__``."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        forward = getattr(self, "forward", None)
        if forward is None:
            raise NotImplementedError(f"{type(self).__name__} must define __call__(self, obs) or forward(self, obs)")
        return forward(*args, **kwargs)

    @classmethod
    def bundled_methods(cls) -> dict[str, BundledMethod]:
        """Every bundled method of the class and its bases, by name (subclass definitions win)."""
        found: dict[str, BundledMethod] = {}
        for klass in reversed(cls.__mro__):
            for name, value in vars(klass).items():
                if isinstance(value, BundledMethod):
                    found[name] = value
        return found

    def parameters(self, trainable_only: bool = True) -> list[TrainableCode]:
        """The code parameters of this policy in definition order (trainable ones by default)."""
        return [
            m.parameter
            for m in self.bundled_methods().values()
            if m.parameter is not None and (m.trainable or not trainable_only)
        ]

    def parameter(self, name: str) -> TrainableCode:
        """The parameter of the bundled method ``name``; KeyError with the known names otherwise."""
        for p in self.parameters(trainable_only=False):
            if p.name == name:
                return p
        known = ", ".join(p.name for p in self.parameters(trainable_only=False))
        raise KeyError(f"no bundled method '{name}' (known: {known})")


def model(cls: type) -> type:
    """Class decorator (Trace's ``@trace.model``): make ``cls`` a :class:`Module` if it is not one already."""
    if issubclass(cls, Module):
        return cls
    return type(cls.__name__, (cls, Module), {"__module__": cls.__module__, "__qualname__": cls.__qualname__,
                                              "__doc__": cls.__doc__})
