"""``codearcade serve``: a budgeted rollout server for one run, over plain HTTP+JSON and MCP (``pipeline/serve/``).

Without ``--mcp``, it serves HTTP on 127.0.0.1 (``--port``; 0 picks a free one) and prints where on stderr; with
``--mcp``, it speaks MCP over stdin/stdout (what Claude Code and Codex CLI start) and prints nothing on stdout but
the protocol; ``--mcp-port`` serves MCP's streamable HTTP instead. ``--resume RUN`` opens a run a stopped or
killed server left (its budget as its committed submissions spent); ``--finalize RUN`` ends one (validation and
held-out pools) and prints the result. When the budget is spent, the run is finalized at once. docs/serve.md.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Callable

from pipeline.cli.common import (EXIT_OK, CliError, add_name, add_rerun, add_settings, add_store, command_text,
                                 open_store, rerun_target, resolve_run, short_id, show, show_json, warn_if_named)
from pipeline.serve.config import ServeConfig


def add_parser(verbs) -> None:
    """Add ``serve`` and its arguments to the verbs of the top-level parser."""
    p = verbs.add_parser(
        "serve",
        help="a rollout server for a coding agent: submissions against an episode budget, sealed validation and "
             "held-out pools (MCP and HTTP)",
        description="Serve one run to a coding agent (Claude Code, Codex CLI, a script): it reads the task, submits "
        "policy files for episodes on visible training instances within an episode budget, and reads their feedback "
        "and its own play in SQL; every submission is a policy version in the store. At the end every submission "
        "plays a sealed validation pool and the best of them a sealed held-out pool, which only `runs`, `report` and "
        "`audit` show.",
        epilog="examples: codearcade serve --game pong --budget 64 --port 8765   |   "
               "claude mcp add codearcade -- codearcade serve --game pong --mcp   |   "
               "codearcade serve --finalize last",
    )
    add_settings(p, ServeConfig, defaults=True)
    p.add_argument("--port", type=_port, default=None, metavar="N",
                   help="serve HTTP+JSON on 127.0.0.1:N (0: a free port; default: 0 without --mcp, none with it)")
    mcp = p.add_mutually_exclusive_group()
    mcp.add_argument("--mcp", action="store_true", help="speak MCP over stdin and stdout (for an agent that starts "
                     "the server itself)")
    mcp.add_argument("--mcp-port", type=_port, default=None, metavar="N",
                     help="serve MCP's streamable HTTP on 127.0.0.1:N (path /mcp) instead of stdio")
    p.add_argument("--workspace", default=".", metavar="DIR",
                   help="the directory whose files a submission may name by path (default: this one)")
    p.add_argument("--resume", default=None, metavar="RUN", help="serve a served run again (one a stopped or killed "
                   "server left), its budget as its committed submissions spent")
    p.add_argument("--finalize", default=None, metavar="RUN", help="end a served run now: play the validation and "
                   "held-out pools, print the result and exit")
    p.add_argument("--json", action="store_true", help="with --finalize: print the result as JSON")
    add_name(p, "served run")
    add_rerun(p)
    add_store(p)
    p.set_defaults(handler=run)


def _say(text: str) -> None:
    show(text, file=sys.stderr, flush=True)  # stdout may be the MCP transport


def _port(text: str) -> int:
    """A ``--port`` value: a TCP port number (0: a free one)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a port number is 0-65535, not {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port number is 0-65535, not {port}")
    return port


def _check_ports_free(args: argparse.Namespace) -> None:
    """CliError for a port another process listens on, before a run is made or opened for it."""
    import socket

    for flag, port in (("--port", args.port), ("--mcp-port", args.mcp_port)):
        if not port:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the HTTP server binds it
            try:
                probe.bind(("127.0.0.1", port))
            except OSError as exc:
                raise CliError(f"{flag} {port}: 127.0.0.1:{port} cannot be served ({exc.strerror}); give another "
                               f"port, or 0 for a free one") from None


def run(args: argparse.Namespace) -> int:
    from pipeline.serve.protocol import KIND, ServeRun, create_run
    from store.locks import run_lock
    from store.writer import finish_run, mark_run_running

    if args.json and args.finalize is None:
        raise CliError("--json goes with --finalize (a server's answers are JSON already)")
    rerun = workspace = None
    if args.finalize is None:  # every flag checked before a run is made or opened: a refusal leaves no run behind
        _check_ports_free(args)
        workspace = os.path.abspath(args.workspace)
        if not os.path.isdir(workspace):
            what = "not a directory" if os.path.exists(workspace) else "no such directory"
            raise CliError(f"--workspace {args.workspace}: {what}; give the directory whose files submissions name")
        rerun = rerun_target(args.rerun)
    store = open_store(args)
    if args.finalize is not None:
        return _finalize(store, resolve_run(store, args.finalize, kinds=(KIND,), verb="serve --finalize",
                                         unsubmitted=True), args)
    if args.resume is not None:
        run_id = resolve_run(store, args.resume, kinds=(KIND,), verb="serve --resume", unsubmitted=True)
    else:
        config = ServeConfig(**{name: getattr(args, name) for name in ServeConfig.__dataclass_fields__
                                if hasattr(args, name)})  # a setting without a flag keeps its default
        warn_if_named(store, args.name)
        run_id = create_run(store, config, name=args.name)
    with run_lock(store.path, run_id):
        served = ServeRun(store, run_id, workspace=workspace, on_episode=None if args.mcp else _episode_line,
                          rerun=rerun,
                          on_finalized=lambda: _say(f"run {short_id(store, run_id)} finalized: "
                                                    f"`{command_text(store, 'audit', short_id(store, run_id))}` "
                                                    "shows its validation and held-out scores"))
        if args.resume is not None and served.finalized:  # it would serve a budget of 0 and refuse every submit
            raise CliError(f"run {short_id(store, run_id)} is finalized: "
                           f"`{command_text(store, 'audit', short_id(store, run_id))}` shows its result; serve a new "
                           "run to go on")
        if args.resume is not None:
            with store.write() as con:
                mark_run_running(con, run_id)
        b = served.budget()
        _say(f"run {short_id(store, run_id)} served: {served.game.name}, budget {b['remaining']} of {b['budget']} "
             f"episodes left; store {store.path}")
        try:
            _serve(served, args)
        except KeyboardInterrupt:
            pass
        finally:
            served.stop()  # a submission playing now is given back, before the run is marked and the zygotes go
            if not served.finalized:
                with store.write() as con:
                    finish_run(con, run_id, "interrupted")
                _say(_stopped_line(store, run_id))
    return EXIT_OK


def _stopped_line(store, run_id: str) -> str:
    """What a stopped server says of its run: how to go on with it, and, without a submission, that ``last`` passes
    over it (``store/runs.py``) and that there is nothing to finalize (``serve --finalize`` refuses such a run)."""
    from store.runs import unsubmitted

    short = short_id(store, run_id)
    resume = f"`{command_text(store, 'serve', '--resume', short)}` serves it again"
    with store.read() as con:
        empty = unsubmitted(con, run_id)
    if empty:
        return f"run {short} stopped before any submission, so `last` passes over it; {resume}"
    return f"run {short} stopped: {resume}, `{command_text(store, 'serve', '--finalize', short)}` ends it"


def _episode_line(episode: dict) -> None:
    _say(f"  submission {episode['iteration']}  instance {episode['episode_index']}  return "
         f"{episode['return']:g}  {episode['length']} steps  {episode['end_reason']}")


def _serve(served, args: argparse.Namespace) -> None:
    from pipeline.serve.http import start_http
    from pipeline.stopping import wait_for_stop

    port = args.port if args.port is not None else (None if args.mcp or args.mcp_port is not None else 0)
    if port is not None:
        server, _ = start_http(served, port)
        _say(f"HTTP+JSON on http://127.0.0.1:{server.server_address[1]}/ (POST /task, /submit, /feedback, /budget, "
             "/sql, /finalize); Ctrl-C stops it")
    if args.mcp or args.mcp_port is not None:
        from pipeline.serve.tools import bound_stdin_lines, build_server, serve_stdio, serve_streamable_http

        mcp = build_server(served)
        if args.mcp_port is not None:
            serve_streamable_http(mcp, args.mcp_port,
                                  lambda port: _say(f"MCP (streamable HTTP) on http://127.0.0.1:{port}/mcp"))
        else:
            # the SDK reads a message whole, however long: it reads the agent's lines through a bounded relay
            lines, stop_reading = bound_stdin_lines()
            try:
                _in_a_thread(lambda: serve_stdio(mcp, lines))  # returns when the agent closes stdin
            finally:  # stopped by Ctrl-C or SIGTERM: the SDK's reader thread sees stdin end, so the process can exit
                stop_reading()
        return
    wait_for_stop()  # until Ctrl-C or SIGTERM (also one that landed where Python swallows it)


def _in_a_thread(serve: Callable[[], None]) -> None:
    """``serve()`` (the MCP SDK's event loop over stdio) in a thread of its own, while this, the main thread, waits
    for it or for Ctrl-C and SIGTERM: raised in the main thread (the only one Python raises them in), they landed in
    the event loop's tasks, and asyncio printed a traceback of 300 lines ("unhandled exception during asyncio.run()
    shutdown", 1 in 8 presses) on the person's terminal. What ``serve`` raises is raised here."""
    import threading

    from pipeline.stopping import wait_for_stop

    failed: list[BaseException] = []

    def run() -> None:
        try:
            serve()
        except BaseException as exc:  # noqa: BLE001 - raised in the main thread below
            failed.append(exc)

    thread = threading.Thread(target=run, name="codearcade-mcp-stdio", daemon=True)
    thread.start()
    wait_for_stop(lambda timeout: (thread.join(timeout), not thread.is_alive())[1])
    if failed:
        raise failed[0]


def _finalize(store, run_id: str, args: argparse.Namespace) -> int:
    from pipeline.serve.protocol import ServeRun
    from store.locks import run_lock
    from store.readers import audits

    with run_lock(store.path, run_id):
        served = ServeRun(store, run_id)
        short = short_id(store, run_id)
        if served.finalized:  # nothing is played again: what it printed is the result its finalize recorded
            _say(f"run {short} was finalized before: its result as recorded")
        else:
            if not served.submissions:  # refused before anything plays, naming the run and how to go on with it
                raise CliError(f"run {short} holds no submission: there is nothing to finalize; "
                               f"`{command_text(store, 'serve', '--resume', short)}` serves it again")
            _say(f"run {short}: playing the validation and held-out pools")
            try:
                served.finalize()
            except KeyboardInterrupt:  # the command's handler says "interrupted"; this says how to go on
                _say(f"run {short} is not finalized: `{command_text(store, 'serve', '--finalize', short)}` "
                     "plays its pools again")
                raise
    with store.read() as con:
        rows = audits(con, run_id)
    if args.json:
        show_json({"run_id": run_id, "audits": rows}, default=str)
    else:
        for line in served_lines(rows):
            show(line)
    return EXIT_OK


def served_lines(rows: list[dict]) -> list[str]:
    """What a person reads of a served run's finalize (its ``audits`` rows): a line per submission on the validation
    pool, the best marked, then the held-out pool's line for the best and the starter, and the overfit verdict."""
    from store.statistics import MEAN_METHOD, interval_text

    def shown(r: dict) -> str:
        if r["score"] is None:
            return f"forfeit ({r['forfeit']})"
        return interval_text(r["score"], r["score_low"], r["score_high"], len(r["seeds"]), MEAN_METHOD)

    def training(r: dict) -> str:
        if r["tuning_score"] is not None:
            return format(r["tuning_score"], "g")
        # every submission played its training instances: no score there is a forfeit; the starter never plays
        return "not played" if r["role"] == "starter" else "forfeited"

    best = next((r for r in rows if r["role"] == "best"), None)
    out = []
    for r in sorted((r for r in rows if r["protocol"] == "validation"), key=lambda r: r["iteration"]):
        mark = "  <- best by validation" if best is not None and best["policy_version_id"] == r["policy_version_id"] \
            else ""
        out.append(f"validation  submission {r['iteration']}: {shown(r)} on {len(r['seeds'])} sealed games; "
                   f"training {training(r)}{mark}")
    for role in ("best", "starter"):
        r = next((r for r in rows if r["role"] == role), None)
        if r is not None:
            name = f"best (submission {r['iteration']})" if role == "best" else "starter"
            out.append(f"held-out    {name}: {shown(r)} on {len(r['seeds'])} sealed games (standard protocol); "
                       f"training {training(r)}")
    if best is not None and best["overfit"]:
        out.append("held-out    OVERFIT: less than half of the best submission's gain over the starting policy holds "
                   "up on the held-out games")
    return out
