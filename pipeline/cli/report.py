"""``codearcade report RUN``: a run's plots and Markdown summary (``viewers/report.py``), with the command line that
reproduces the run.
"""

from __future__ import annotations

import argparse
from typing import Any

from pipeline.cli.common import EXIT_OK, add_run, add_store, open_store, resolve_run, show


def add_parser(verbs) -> None:
    """Add ``report`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "report",
        help="write PNG plots and a Markdown summary of a run",
        description="Write a report of one run: score per iteration with the best so far (return per episode "
        "for eval runs), code size and complexity per iteration, LLM tokens per iteration, as PNG files, and "
        "README.md showing them with the run's settings and a table of its iterations.",
    )
    add_run(p)
    p.add_argument("--out", metavar="DIR", help="output directory (default: ./reports/RUN_ID)")
    add_store(p)
    p.set_defaults(handler=run)


# Flags of `codearcade optimize` whose name is not the config field's with dashes.
_FLAG_NAMES = {"call_time_limit_s": "--call-time-limit", "max_cost_usd": "--max-cost",
               "max_wall_minutes": "--max-wall", "episode_time_limit_s": None, "workers": None, "policy": None,
               "game": "--game", "rollback": None}


def reproduce_command(run: dict[str, Any], config: dict[str, Any]) -> str:
    """The ``codearcade`` command line that starts a run with ``run``'s settings (defaults left out)."""
    import shlex

    if run["kind"] == "eval":
        parts = ["codearcade", "eval", config.get("policy") or "POLICY.py", "--game", run["game"]]
        for key, flag, default in (("episodes", "--episodes", 1), ("max_steps", "--max-steps", 4000),
                                   ("seed", "--seed", 0), ("sticky", "--sticky", 0.0),
                                   ("noop_max", "--noop-max", 0)):
            if config.get(key) not in (None, default):
                parts += [flag, str(config[key])]
        if config.get("trace"):
            parts.append("--trace")
        return shlex.join(parts)
    from pipeline.optimizer.config import OptimizeConfig

    defaults = OptimizeConfig()
    parts = ["codearcade", "optimize"] + ([config["policy"]] if config.get("policy") else [])
    parts += ["--game", run["game"]]
    for key in OptimizeConfig.__dataclass_fields__:
        flag = _FLAG_NAMES.get(key, "--" + key.replace("_", "-"))
        value = config.get(key)
        if flag is None or key == "game" or value is None or value == getattr(defaults, key):
            continue
        parts += [flag, f"{value:g}" if isinstance(value, float) else str(value)]
    if config.get("rollback") is False:
        parts.append("--no-rollback")
    return shlex.join(parts)


def run(args: argparse.Namespace) -> int:
    from pipeline.llm.providers import price
    from viewers.report import write_report

    store = open_store(args)
    path = write_report(store, resolve_run(store, args.run_id), args.out, reproduce=reproduce_command, price=price)
    show(path)
    return EXIT_OK
