"""Tracing: policies as Python classes whose bundled methods are trainable code parameters.

Policies import this module in the paper's style (``import tracing as trace``) and use :func:`bundle`,
:func:`model` and :class:`Module`. The rest (``capture``, ``sandbox``, ``policy_file``, ``metrics``) is
for codearcade itself: node capture, guarded execution and policy-file handling.
"""

from tracing.bundle import BundledMethod, Module, TrainableCode, bundle, model

__all__ = ["Module", "bundle", "model", "BundledMethod", "TrainableCode"]
