"""Tracing: policies as Python classes whose bundled methods are trainable code parameters.

Policies import this module in the paper's style (``import tracing as trace``) and use :func:`bundle`,
:func:`model` and :class:`Module`; files written for Microsoft's Trace (``import opto.trace as trace``) run
unchanged, their imports answered by ``trace_api`` (see ``tracing/sandbox.py``). The rest (``capture``,
``sandbox``, ``policy_file``, ``metrics``) is for codearcade itself: node capture, guarded execution and
policy-file handling.
"""

from tracing.bundle import BundledMethod, Module, TrainableCode, bundle, model

__all__ = ["Module", "bundle", "model", "BundledMethod", "TrainableCode"]
