"""Policy versions as stored: a row of ``policy_versions`` with sources, parent and code metrics."""

from __future__ import annotations

from typing import Any

from tracing.metrics import function_metrics, policy_metrics
from tracing.policy_file import PolicyInfo


def policy_version_row(
    info: PolicyInfo,
    run_id: str,
    iteration: int,
    produced_by: str,
    validation: str = "accepted",
    validation_error: str | None = None,
    parent_id: str | None = None,
    llm_call_id: str | None = None,
) -> dict[str, Any]:
    """The row for ``store.writer.insert_policy_version`` (sources go to blobs there)."""
    functions = []
    for method in info.methods:
        m = function_metrics(method.source)
        functions.append(dict(name=method.name, source=method.source, trainable=method.trainable, **m.as_dict()))
    metrics = policy_metrics(info.text)
    return dict(
        policy_version_id=info.version_id,
        run_id=run_id,
        iteration=iteration,
        parent_id=parent_id,
        llm_call_id=llm_call_id,
        source=info.text,
        produced_by=produced_by,
        validation=validation,
        validation_error=validation_error,
        functions=functions,
        **metrics.as_dict(),
    )
