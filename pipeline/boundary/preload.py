"""Warms the zygote (``pipeline/boundary/zygote.py``), the process that forks policy workers, so each worker
starts warm.

:func:`warm` imports the modules of the zygote's tasks once: the episode task brings the rollout stack
(gymnasium, ALE, OCAtari's extractors: about 1.5 s), the check tasks the validation code. It also makes
pyarrow's first array and IPC stream (about 0.25 s). Paying both once in the zygote instead of in every worker
is what makes a fresh worker per episode cheap.
"""

import importlib
from typing import Iterable

import pyarrow as pa

from pipeline.boundary.wire import arrow_frame
from tracing.steps import StepLog


def warm(modules: Iterable[str]) -> None:
    """Import ``modules`` (by name: they are the tasks', above this package) and initialise pyarrow."""
    for name in modules:
        importlib.import_module(name)
    arrow_frame(StepLog().table())  # pyarrow initialises its kernels (and the IPC writer) lazily on first use
    pa.ipc  # noqa: B018
