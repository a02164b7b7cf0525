"""``codearcade audit RUN``: the held-out audit of a stored run (``pipeline/optimizer/audit.py``), played again.

A run is audited when it finishes (``--audit-episodes``, default 3); this plays the audit of any stored
optimization run on demand (a run made before audits existed, one that stopped early, or with more games) and
replaces the run's earlier audit.
"""

from __future__ import annotations

import argparse
import sys

from pipeline.cli.common import EXIT_OK, add_run, add_store, open_store, positive_int, resolve_run, show, show_json


def add_parser(verbs) -> None:
    """Add ``audit`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "audit",
        help="play a run's best version and its starting policy on held-out seeds the loop never saw",
        description="The held-out audit of an optimization run: its best version and its starting policy play N "
        "games each on the audit seeds (1,000,000 and up: never played by the loop, never shown to the model), "
        "under the standard protocol (sticky actions 0.25, up to 30 no-op starts) and under the run's own. The "
        "scores (with 95%% intervals) are stored beside the tuning scores (table audits; runs, report) and the run "
        "is flagged overfit when less than half of its best version's gain over the starter holds up.",
        epilog="examples: codearcade audit last   |   codearcade audit my-run --episodes 10 --json",
    )
    add_run(p)
    p.add_argument("--episodes", type=positive_int, metavar="N",
                   help="games per version and protocol (default: the run's --audit-episodes, or 3)")
    p.add_argument("--workers", type=positive_int, metavar="N", help="episodes played at once (default: the run's)")
    p.add_argument("--json", action="store_true", help="print the audit's rows as JSON")
    add_store(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.optimizer.audit import audit_run

    store = open_store(args)
    run_id = resolve_run(store, args.run_id)
    result = audit_run(store, run_id, episodes=args.episodes, workers=args.workers, on_demand=True)
    if args.json:
        show_json({"run_id": run_id, "overfit": result.overfit, "audits": result.rows}, default=str)
    else:
        if not result.rows:
            show(f"run {run_id} has no iteration to audit", file=sys.stderr)
        for line in result.lines():
            show(line)
    return EXIT_OK
