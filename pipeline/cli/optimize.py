"""``codearcade optimize``: the optimization loop from the command line, a dry run that prices it, and ``--resume``."""

from __future__ import annotations

import argparse
import os
import sys
from typing import Callable

from pipeline.cli.common import (EXIT_EPISODE_FAILED, EXIT_INTERRUPTED, EXIT_OK, CliError, add_name, add_rerun,
                                 add_settings, add_store, open_store, rerun_target, resolve_run, short_id,
                                 command_text, shorten_run_ids, show, show_json, warn_if_named)
from pipeline.optimizer.config import FLAG_GROUPS, OptimizeConfig
from pipeline.settings import declarations, flag_of
from store.scores import score_text
from viewers.safe_text import terminal_text


def add_parser(verbs) -> None:
    """Add ``optimize`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "optimize",
        help="improve a policy with an LLM (the paper's loop), every step stored",
        description="Run the optimization loop: iteration 0 evaluates the starting policy; each further iteration "
        "builds a prompt from the store, asks the LLM for new code, validates it, and evaluates the result. "
        "Without --model a small local model (SmolLM2-135M) is started: it exercises the pipeline offline but "
        "cannot really improve code.",
    )
    add_settings(p, OptimizeConfig, FLAG_GROUPS)
    p.add_argument("--resume", metavar="RUN", help="continue a run that was interrupted, failed or stopped by a "
                   "budget (last, last~N, -N, its label, its id or a unique prefix); budgets, limits, "
                   "--model/--api-base and a larger --iterations may be given again")
    add_name(p, "run (with --resume: its new label)")
    p.add_argument("--dry-run", action="store_true",
                   help="evaluate the starting policy into a temporary store, build the first prompt, and print its "
                   "tokens and the estimated cost of one update and of the whole run; calls no model")
    p.add_argument("--show-prompt", action="store_true", help="with --dry-run: print the prompt too")
    p.add_argument("--stream", action="store_true",
                   help="stream each reply, showing the tokens as they arrive (the result is the same)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    add_rerun(p)
    add_store(p)
    p.set_defaults(handler=run)


def _print_iteration(item) -> None:
    tokens = f"prompt {item.prompt_tokens} tok" if item.prompt_tokens else ""
    # the detail quotes a rejected candidate's exception: its escape sequences go before it is cut to fit
    note = f"  ({terminal_text(item.detail)})" if item.detail and item.update_status != "accepted" else ""
    back = "  rolled back" if item.rolled_back else ""
    if item.pool:
        back += f"  [{item.pool}]"
    if item.repairs:  # the update as the model finally made it: say how many repair turns it took
        back += f"  after {item.repairs} repair{'s' if item.repairs > 1 else ''}"
    if item.candidates > 1:
        tokens = f"best of {item.candidates} candidates  " + tokens
    if item.standard_score is not None:
        tokens = f"standard protocol {score_text(item.standard_score)}  " + tokens
    score = f"{item.score:>8.1f}" if item.score is not None else f"{'forfeit':>8}"
    best = f"{item.best_score:>8.1f}" if item.best_score is not None else f"{'forfeit':>8}"
    forfeit = ""
    if item.forfeit:  # the partial score is what the policy had when it stopped: shown, never taken as its score
        forfeit = f"  ({terminal_text(item.forfeit)}; {score_text(item.forfeit_score)} when it stopped)"
    show(f"iteration {item.iteration:>3}  score {score}  best {best} (it {item.best_iteration})"
         f"  update {item.update_status:<9} {tokens}{back}{note[:160]}{forfeit[:120]}{_model_shares(item.models)}",
         flush=True)


def _model_shares(models) -> str:
    """An ensemble's models on the progress line: each one's share of the calls so far and its spend."""
    total = sum(calls for _, calls, _ in models)
    if not models or not total:
        return ""
    from viewers.tables import money

    return "  models " + ", ".join(f"{terminal_text(name)} {calls / total:.0%}"
                                   + (f" ${money(cost)}" if cost is not None else " (no price)")
                                   for name, calls, cost in models)


OPTIMIZE_OPTIONS = tuple(n for n, (_, s) in declarations(OptimizeConfig).items() if s.cli)
"""The ``optimize`` flags that are :class:`~pipeline.optimizer.config.OptimizeConfig` fields (declared there)."""


def _llm_waiting(stream=None):
    """The optimizer's ``waiting`` hook: while an LLM call is in flight, a terminal shows for how long it has
    waited and, when the reply is streamed, how much of it has arrived (one line, redrawn each second); a log
    gets one line per call. It yields the callback the client feeds streamed text to."""
    import threading
    import time
    from contextlib import contextmanager

    stream = stream or sys.stderr

    @contextmanager
    def waiting(iteration: int, label: str):
        label = terminal_text(label)
        started = time.monotonic()
        received = {"pieces": 0, "chars": 0}

        def on_text(piece: str) -> None:
            received["pieces"] += 1
            received["chars"] += len(piece)

        if not stream.isatty():
            show(f"iteration {iteration}: waiting for {label}", file=stream, flush=True)
            yield on_text
            return
        stop = threading.Event()

        def line() -> str:
            text = f"iteration {iteration}: waiting for {label} ... {time.monotonic() - started:.0f} s"
            if received["pieces"]:
                text += f", receiving: {received['pieces']:,} tokens ({received['chars']:,} characters)"
            return text

        def tick() -> None:
            while not stop.wait(0.5):
                stream.write("\r\033[K" + line())
                stream.flush()

        ticker = threading.Thread(target=tick, name="codearcade-llm-wait", daemon=True)
        ticker.start()
        try:
            yield on_text
        finally:
            stop.set()
            ticker.join()
            stream.write("\r\033[K")
            stream.flush()

    return waiting


def run(args: argparse.Namespace) -> int:
    given = {k: getattr(args, k) for k in OPTIMIZE_OPTIONS if getattr(args, k) is not None}
    from pipeline.optimizer.ensemble import split_model_flags

    try:  # --model given several times: an ensemble (pipeline/optimizer/ensemble.py)
        given = split_model_flags(given)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if given.get("model") and not args.dry_run:
        from pipeline.llm.providers import check_ensemble_credentials  # no litellm import: said at once

        models = given.get("models") or [{"model": given["model"], "api_base": given.get("api_base")}]
        check_ensemble_credentials(models)
    if args.show_prompt and not args.dry_run:
        raise CliError("--show-prompt goes with --dry-run")
    from pipeline.optimizer.config import model_defaults

    store = open_store(args, announce=False)  # the start line names the store and why it is that one
    start = None
    if args.resume is not None and not args.resume.strip():
        raise CliError("--resume: give the run to continue (`codearcade runs` lists them)")
    if args.resume:
        if args.dry_run:
            raise CliError("--dry-run starts a new run; it cannot go with --resume")
        from pipeline.optimizer.loop import plan_resume

        plan = plan_resume(store, resolve_run(store, args.resume, kinds=("optimize",), verb="optimize --resume"),
                           given)
        short = short_id(store, plan.run_id)
        from store.locks import run_is_live

        if run_is_live(store.path, plan.run_id):  # said now: its start line read "resumed" before the refusal
            raise CliError(f"run {short} is being worked on by another process; wait for it to finish (or stop "
                           "it) first")
        if plan.nothing_to_do:
            note = shorten_run_ids(plan.nothing_to_do, {plan.run_id: short})
            if args.json:
                show_json({"run_id": plan.run_id, "short_id": short, "status": plan.status, "error": None,
                           "iterations": [], "note": note})
            else:
                show(note)
            return EXIT_OK
        config, run_id = plan.config, plan.run_id
        if config.model and "model" not in given:
            from pipeline.llm.providers import check_ensemble_credentials

            check_ensemble_credentials(config.models or [{"model": config.model, "api_base": config.api_base}])
    else:
        given.setdefault("workers", os.cpu_count() or 1)
        config, run_id = OptimizeConfig(**model_defaults(given)), None
        from pipeline.optimizer.config import validate_config

        validate_config(config)  # a bad setting is one line before any model starts (the offline one takes seconds)
        if not args.dry_run:  # and so is a bad policy file or game: a typo costs what it costs in `eval`
            from pipeline.optimizer.task import resolve_start

            start = resolve_start(config)
    if args.dry_run:
        return _dry_run(config, args)
    from pipeline.llm.providers import check_reachable, implied_server

    servers = {config.api_base: "--api-base"} if config.api_base else {}  # each server the run calls: as named
    for entry in config.models or [{"model": config.model, "api_base": config.api_base}]:
        if entry["api_base"]:
            servers.setdefault(entry["api_base"], f"the api_base of --model {entry['model']}")
        elif entry["model"] and (implied := implied_server(entry["model"])) is not None:
            servers.setdefault(*implied)  # --model ollama_chat/NAME alone: litellm's own default server
    for base, named in servers.items():  # a server that does not answer: one line now, not a failed call after
        check_reachable(base, given_as=named)  # iteration 0
    started = {} if run_id is None else {"run_id": run_id, "short": short}
    try:
        return _optimize(args, store, config, run_id, started, start)
    except KeyboardInterrupt:
        if "run_id" not in started:
            show("codearcade: interrupted before the run was made; nothing was stored", file=sys.stderr)
        else:
            show(f"codearcade: interrupted: run {started['short']} is stored up to its last whole iteration; "
                 f"continue it with `{_resume_command(store, started['short'])}`", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED


def _larger_budget(config, setting: str | None) -> tuple[str, ...]:
    """The flag and a value twice the spent one of the budget ``setting`` that stopped a run (its command runs as
    printed; it said ``--max-...``, which the parser refused); none where a larger one would not help."""
    spent = getattr(config, setting) if setting is not None else None
    if spent is None:
        return ()
    return flag_of(OptimizeConfig, setting), f"{spent * 2:g}" if isinstance(spent, float) else str(spent * 2)


def _resume_command(store, run: str, *more: str) -> str:
    return command_text(store, "optimize", "--resume", run, *more)


def _optimize(args: argparse.Namespace, store, config, run_id: str | None, started: dict[str, str],
              start=None) -> int:
    """Start (or resume) the run, print its start line, run the loop, print its end; ``started`` gets the run's id
    as soon as it exists (for the interrupt message); ``start``: the new run's starting policy and game, checked
    before the model started (``pipeline.optimizer.task.resolve_start``)."""
    from pipeline.llm.client import open_client
    from pipeline.optimizer.config import fit_to_model
    from pipeline.optimizer.loop import new_run, optimize
    from pipeline.stopping import uninterrupted
    from store.readers import get_run
    from store.writer import set_run_name

    say = (lambda line: show(line, file=sys.stderr, flush=True)) if args.json else \
        (lambda line: show(line, flush=True))
    offline = config.model is None
    client, server, cap = open_client(config.model, config.api_base, config.temperature, config.max_tokens,
                                      config.seed, stream=args.stream, models=config.models,
                                      notice=lambda line: show(f"codearcade: {line}", file=sys.stderr))
    recordings = None
    try:
        with new_run(store, client) as made:  # stopped before the loop takes it over: ended as the loop would
            fit_to_model(config, cap)
            rerun = rerun_target(args.rerun)
            resumed = run_id is not None
            with uninterrupted():  # a press as the run is made lands once its id is here, to be printed
                if run_id is None:  # made here, so that its id is printed before iteration 0 plays
                    run_id = made.start(config, client.label, start=start)
                started["run_id"] = started["short"] = run_id
            if args.name is not None:
                warn_if_named(store, args.name, run_id)
                with store.write() as con:
                    set_run_name(con, run_id, args.name)
            started["short"] = short = short_id(store, run_id)
            with store.read() as con:
                game = get_run(con, run_id)["game"]
            label = f" '{args.name}'" if args.name else ""
            say(f"run {short}{label} {'resumed' if resumed else 'started'}: optimize {game}, model {client.label}"
                f"{' (offline default)' if offline else ''}; {store.location.describe()}")
            on_iteration, recordings = _run_recordings(store, rerun, None if args.json else _print_iteration)
            result = optimize(config, store, client, resume=run_id, on_iteration=on_iteration,
                              log=lambda line: show(line, file=sys.stderr), rerun=rerun, waiting=_llm_waiting())
    finally:
        if server is not None:
            server.stop()
        if recordings is not None:
            recordings.close()
    error = shorten_run_ids(result.error, {run_id: short}) if result.error else None
    if args.json:
        show_json({
            "run_id": result.run_id, "short_id": short, "name": args.name, "status": result.status,
            "error": result.error,
            "iterations": [dict(iteration=i.iteration, policy_version_id=i.policy_version_id, score=i.score,
                                best_score=i.best_score, update_status=i.update_status, rolled_back=i.rolled_back,
                                forfeit=i.forfeit)
                           for i in result.iterations],
        })
    else:
        # a run that did not finish has its error said once, on stderr below, with how to continue it
        said_below = result.status not in ("finished", "budget")
        show(f"run {short} {result.status}" + (f": {error}" if error and not said_below else ""))
        for line in result.audit.lines() if result.audit is not None else []:
            show(line)
    if result.status == "budget":
        show(f"codearcade: run {short} stopped by its budget; continue it with a larger one: "
             f"`{_resume_command(store, short, *_larger_budget(config, result.budget))}`", file=sys.stderr)
        return EXIT_OK
    if result.status != "finished":
        played_all = any(i.iteration >= config.iterations for i in result.iterations)
        more = ("--iterations", str(config.iterations + max(1, config.iterations // 2))) if played_all else ()
        show(f"codearcade: run {short} {result.status}: {error}; fix the cause, then continue it "
             f"with `{_resume_command(store, short, *more)}`", file=sys.stderr)
        return EXIT_EPISODE_FAILED
    return EXIT_OK


def _dry_run(config, args: argparse.Namespace) -> int:
    from pipeline.optimizer.estimate import estimate_run

    report = estimate_run(config, progress_log=lambda line: show(line, file=sys.stderr))
    if args.json:
        show_json(report.as_dict(include_prompt=args.show_prompt))
        return EXIT_OK
    if args.show_prompt:
        for message in report.prompt.messages:  # the prompt quotes the policy's outputs and errors
            show(f"----- {message['role']} -----")
            show(message["content"], multiline=True)
        show("-----")
    for line in report.lines():
        show(line)
    return EXIT_OK


def _run_recordings(store, target: str | None, then: Callable | None):
    """With ``--rerun``: an on_iteration callback that also has the run's Rerun recording rebuilt, in a separate
    process, after every iteration; and the updater to close at the end (None without ``--rerun``)."""
    if target is None:
        return then, None
    from viewers.rerun_sinks import RunRecordingUpdater

    updater = RunRecordingUpdater(store.path, target)

    def on_iteration(item) -> None:
        if then is not None:
            then(item)
        updater.update(item.run_id)

    return on_iteration, updater
