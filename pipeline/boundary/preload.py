"""Imported once by the zygote (``pipeline/boundary/zygote.py``), the process that forks policy workers, so each worker
starts warm.

Importing the rollout stack (gymnasium, ALE, OCAtari's extractors) takes about 1.5 s and pyarrow's first
array about 0.25 s; paying both once in the zygote instead of in every worker is what makes a fresh worker
per episode cheap. The validation code (``pipeline/play/validate.py``) and the Arrow IPC writer are loaded here too.
"""

import pyarrow as pa

from pipeline.play import validate  # noqa: F401
from pipeline.play.rollout import run_episode  # noqa: F401  (the import is the point)
from pipeline.boundary.wire import arrow_frame
from tracing.steps import StepLog

arrow_frame(StepLog().table())  # pyarrow initialises its kernels (and the IPC writer) lazily on first use
pa.ipc  # noqa: B018
