"""Imported once by the process that forks episode workers, so each worker starts warm.

Importing the rollout stack (gymnasium, ALE, OCAtari's extractors) takes about 1.5 s and pyarrow's first
array about 0.25 s; paying both here instead of in every worker process is what makes per-episode
processes cheap.
"""

from pipeline.rollout import run_episode  # noqa: F401  (the import is the point)
from tracing.steps import StepLog

StepLog().table()  # pyarrow initialises its kernels lazily on first use
