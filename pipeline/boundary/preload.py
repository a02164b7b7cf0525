"""Warms a zygote (``pipeline/boundary/zygote.py``), the process that forks workers, so each worker starts warm.

:func:`warm` imports the modules of the zygote's tasks once: the game zygote's host task brings the rollout stack
(gymnasium, ALE, OCAtari's extractors: about 1.5 s); the policy zygote's tasks bring only the tracing layer, numpy
and the validation code, and :func:`warm` then checks that nothing pulled in the emulator stack
(:data:`~pipeline.boundary.confine.EMULATOR_PACKAGES`: a policy process must have no emulator in memory, and
cannot read one from disk either). It also makes pyarrow's first array and IPC stream (about 0.25 s). Paying
these once in the zygote instead of in every worker is what makes a fresh worker per episode cheap.
"""

import importlib
import sys
from typing import Iterable

import pyarrow as pa

from pipeline.boundary.confine import EMULATOR_PACKAGES
from pipeline.boundary.wire import arrow_frame
from tracing.capture import NodeRecorder


def warm(modules: Iterable[str], no_emulator: bool = False) -> None:
    """Import ``modules`` (by name: they are the tasks', some above this package) and initialise pyarrow; with
    ``no_emulator``, raise ImportError if that loaded any of :data:`EMULATOR_PACKAGES`."""
    for name in modules:
        importlib.import_module(name)
    arrow_frame(NodeRecorder().table())  # pyarrow initialises its kernels (and the IPC writer) lazily on first use
    pa.ipc  # noqa: B018
    loaded = sorted({name.split(".")[0] for name in sys.modules} & set(EMULATOR_PACKAGES))
    if no_emulator and loaded:
        raise ImportError(f"the policy zygote must not load {', '.join(loaded)}")
