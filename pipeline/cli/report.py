"""``codearcade report RUN``: a run's plots and Markdown summary (``viewers/report.py``), with the command line that
reproduces the run.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from pipeline.cli.common import EXIT_OK, add_run, add_store, check_output, open_store, resolve_run, show


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


def reproduce_command(run: dict[str, Any], config: Any) -> str:
    """The ``codearcade`` command line that starts a run with ``run``'s settings (defaults left out): each
    setting's flag as its declaration names it (``pipeline/settings.py``). Settings the store holds that are not
    what their setting takes (a store is anyone's file) make no command: a comment saying which one instead."""
    from pipeline.settings import recorded_problem

    if run["kind"] == "eval":
        from pipeline.play.config import EvalConfig

        kind: type = EvalConfig
    elif run["kind"] == "serve":
        from pipeline.serve.config import ServeConfig

        kind = ServeConfig
    else:
        from pipeline.optimizer.config import OptimizeConfig

        kind = OptimizeConfig
    served = config.get("serve") or {} if isinstance(config, dict) and run["kind"] == "serve" else config
    problem = recorded_problem(kind, served)
    if problem is None and not isinstance(run["game"], str):
        problem = "the run names no game"
    if problem is not None:
        return f"# no command reproduces this run: its recorded settings cannot be read ({problem})"
    if run["kind"] == "eval":
        parts = ["codearcade", "eval", config.get("policy") or "POLICY.py", "--game", run["game"]]
        return _shell_line(parts + _flags(kind, config))
    if run["kind"] == "serve":  # a served run: its own settings, recorded under "serve"
        parts = ["codearcade", "serve"] + ([served["policy"]] if served.get("policy") else [])
        return _shell_line(parts + ["--game", run["game"]] + _flags(kind, served))
    parts = ["codearcade", "optimize"] + ([config["policy"]] if config.get("policy") else [])
    return _shell_line(parts + ["--game", run["game"]] + _flags(kind, config))


def _shell_line(words: list[str]) -> str:
    """``words`` as bash reads them back: each quoted as ``shlex`` does, but a word holding a character that is not
    printable (a control, a bidi override: a file's name may hold them) as ANSI-C ``$'...'`` with that character as
    an escape, so that the line names the same file and shows nothing a terminal or a report would act on."""
    import shlex

    def word(text: str) -> str:
        if text.isprintable():
            return shlex.quote(text)
        return "$'" + "".join(
            "\\\\" if c == "\\" else "\\'" if c == "'" else c if c.isprintable() else
            f"\\x{ord(c):02x}" if ord(c) < 0x80 else f"\\u{ord(c):04x}" if ord(c) < 0x10000 else f"\\U{ord(c):08x}"
            for c in text) + "'"

    return " ".join(word(w) for w in words)


def _flags(config_class: type, config: dict[str, Any]) -> list[str]:
    """The flags that give the settings of a stored ``config`` that differ from their defaults: every setting with
    a flag that reproduces a run (not the game, given first, nor the machine's own, like worker counts)."""
    from pipeline.settings import declarations

    parts: list[str] = []
    for name, (f, s) in declarations(config_class).items():
        value = config.get(name)
        if name in ("model", "api_base") and config.get("models"):  # an ensemble: --model per entry
            from pipeline.optimizer.ensemble import entry_flag, parse_model_entry

            parts += [w for e in config["models"] for w in ("--model", entry_flag(parse_model_entry(e)))] \
                if name == "model" else []
            continue
        if not s.flags(name) or name == "game" or not s.reproduce or value is None or value == f.default:
            continue
        switch = [w.flag for w in s.switches if w.value == value]
        if s.switches:
            parts += switch[:1]  # a value no switch sets (a batch's own) has no flag
        else:
            parts += [s.flags(name)[0], f"{value:g}" if isinstance(value, float) else str(value)]
    return parts


def run(args: argparse.Namespace) -> int:
    from pipeline.llm.providers import price
    from viewers.report import write_report

    if args.out:
        check_output(args.out, directory=True)
    store = open_store(args)
    run_id = resolve_run(store, args.run_id, verb="report")
    path = write_report(store, run_id, args.out, reproduce=reproduce_command, price=price,
                        progress=lambda stage: show(f"codearcade report: {stage}", file=sys.stderr, flush=True))
    show(path)
    return EXIT_OK
