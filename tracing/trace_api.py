"""Microsoft Trace's policy API (``opto.trace``), implemented by codearcade, so that policy files written for
Trace run unchanged.

A Trace policy file begins ``import opto.trace as trace`` / ``from opto.trace import bundle, Module, node,
model, GRAPH`` (or ``from opto import trace``). codearcade installs no ``opto`` package: the policy sandbox's
import hook answers those imports, and only those (:data:`tracing.sandbox.TRACE_API`), with read-only views
of this module. A real Trace installed beside codearcade is neither shadowed nor used, and the rest of Trace
(``opto.optimizers``, ``opto.utils``, ...) stays refused like any other import. Policy code written this way
is optimized, traced, blamed and compared like any other: the bundled methods are the same
:class:`~tracing.bundle.BundledMethod` parameters, and the optimizer splices new method text into the file,
so its imports and decorators are kept.

How each name behaves here, against Trace (trace-opt 0.1.x, which the authors' repository pins):

- ``bundle(description=None, traceable_code=False, _process_inputs=True, trainable=False,
  catch_execution_error=True, allow_external_dependencies=False, overwrite_python_recursion=False)``: Trace's
  parameters in Trace's order (a positional argument is the description, as there; newer keywords are
  accepted too). ``trainable=True`` makes the method's code a parameter the optimizer rewrites; the others
  change nothing here but ``catch_execution_error`` (below).
- ``Module``, ``model``: codearcade's (``tracing/bundle.py``): ``policy(obs)`` calls ``__call__``, else
  ``forward``; ``@model`` on a class that already subclasses ``Module`` changes nothing (Trace wraps it in a
  subclass named ``ModelWrapper``; here the class keeps its name).
- ``init``: Trace calls nothing named ``init``; the ``def init(self): pass`` of the authors' policies is an
  ordinary method here too. A policy is built as ``Policy()``, without arguments, in Trace's drivers and here.
- Values are plain. Trace wraps what a bundled method returns in a node and hands bundled methods the data of
  the nodes they are given; codearcade records the same calls by capture (``tracing/capture.py``) and passes
  plain values throughout, so a bundled method receives what it receives under Trace, and ``__call__``
  returns the action itself. ``node(x)`` is ``x``; ``node(x, trainable=True)`` (a trainable value) is refused:
  codearcade optimizes code, not values. ``Node`` exists for ``isinstance`` checks, which are False.
- ``ExecutionError``: as in Trace (``catch_execution_error=True``, the default), an exception raised inside a
  bundled method leaves the call as an ``ExecutionError`` whose message is ``(ZeroDivisionError) division by
  zero``; ``except trace.ExecutionError`` catches it, and the node of that call records the original
  exception. Uncaught, it ends the episode as a ``policy_error`` naming it and the failing line, as the
  authors' drivers end a rollout on one.
- ``GRAPH.clear()`` and ``stop_tracing()`` do nothing: there is no graph of nodes to clear or pause.
"""

from __future__ import annotations

from typing import Any, Callable

from tracing import capture
from tracing.bundle import BundledMethod, Module, model
from tracing.sandbox import TRACE_API

__all__ = list(TRACE_API["opto.trace"])  # Module and model are codearcade's own, re-exported


class ExecutionError(Exception):
    """An exception raised inside a bundled method, as Trace reports it (the original is its ``__cause__``)."""

    def __init__(self, exception: BaseException):
        self.exception = exception
        super().__init__(f"({type(exception).__name__}) {exception}")


class TraceBundledMethod(BundledMethod):
    """A method bundled with Trace's ``bundle``: codearcade's parameter and capture, Trace's ``ExecutionError``."""

    def __init__(self, fn: Callable, trainable: bool, catch_execution_error: bool):
        super().__init__(fn, trainable)
        self.catch_execution_error = catch_execution_error

    def __get__(self, instance: Any, owner: type | None = None) -> Any:
        if instance is None or not self.catch_execution_error:
            return super().__get__(instance, owner)
        parameter = self.parameter

        def call(*args: Any, **kwargs: Any) -> Any:
            # BundledMethod's call, inlined: wrapping it in a second closure made a policy call ~1.4x slower
            try:
                recorder = capture.ACTIVE
                if recorder is None:
                    return parameter.fn(instance, *args, **kwargs)
                return recorder.call(parameter, instance, args, kwargs)
            except ExecutionError:
                raise  # from a bundled method this one called
            except Exception as exc:  # noqa: BLE001 - Trace reports any error of a bundled call this way
                # the original traceback goes along, so the failing policy line is still the one reported
                raise ExecutionError(exc).with_traceback(exc.__traceback__) from exc

        return call


def bundle(description: str | None = None, traceable_code: bool = False, _process_inputs: bool = True,
           trainable: bool = False, catch_execution_error: bool = True, allow_external_dependencies: bool = False,
           overwrite_python_recursion: bool = False, **_newer_options: Any) -> Callable[[Callable], BundledMethod]:
    """Trace's ``bundle``: mark a policy method as a traced operation; ``trainable=True`` lets the optimizer
    rewrite its code. The other parameters are Trace's and change nothing here but ``catch_execution_error``."""

    def decorate(fn: Callable) -> BundledMethod:
        if isinstance(fn, BundledMethod):
            return fn
        return TraceBundledMethod(fn, bool(trainable), bool(catch_execution_error))

    return decorate


class Node:
    """Trace's node class. Values stay plain here (see the module docstring): nothing is an instance of it."""


def node(data: Any, name: str | None = None, trainable: bool = False, description: str | None = None,
         constraint: str | None = None, **_newer_options: Any) -> Any:
    """Trace's ``node``: here ``data`` itself. A trainable value is refused, with what to do instead."""
    if trainable:
        raise ValueError("node(..., trainable=True) is not supported: codearcade optimizes the code of bundled "
                         "methods, not values; put the value in a @bundle(trainable=True) method")
    return data


class _Graph:
    """Trace's global graph of nodes, of which codearcade keeps none (calls are captured, not linked)."""

    TRACE = True

    def clear(self) -> None:
        """Trace drops the nodes it built; there are none here."""


GRAPH = _Graph()


class stop_tracing:  # noqa: N801 - Trace's name
    """Trace's context manager that pauses graph building; nothing to pause here (capture is the host's)."""

    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None

