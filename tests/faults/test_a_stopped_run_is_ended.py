"""A stopped run is ended in the store itself: stopped before its loop took it over, or as it was being ended.

``start_run`` writes a new run as 'running'; the loop marks it finished, failed or interrupted when it ends. What a
command does in between (print the run's start line, name it, open its Rerun recordings, load its state, take its
lock) was outside both: a SIGTERM there (CI saw one, 4 s into `optimize`, on a loaded machine) left the row
'running' for good, shown interrupted only while no process held the run. Each way a run is started (the CLI, a
batch's run, the Python API, a replay) is stopped here at each step of that stretch, by a Ctrl-C, a SIGTERM and an
error, and its row read back: interrupted (resumable) or failed, never 'running'.

The write that ends a run (its status, an evaluation's last episodes) could itself be cut: a Ctrl-C (CI's
soak of presses to `compare`) that landed in it rolled it back, and a run whose games were all played was left
'running'. That write now runs to its end and the press is raised after it (``pipeline.stopping.uninterrupted``).
"""

from __future__ import annotations

import os
import signal
from dataclasses import asdict

import pytest

from pipeline.cli import main
from pipeline.stopping import Terminated
from store import Store
from tests.conftest import COMPETENT_REPLY, POLICIES

STOPS = {"a Ctrl-C": (KeyboardInterrupt, "interrupted"), "a SIGTERM": (Terminated, "interrupted"),
         "an error": (OSError, "failed")}
"""What stops the command, and the status its run must be left with."""

STEPS = [("pipeline.cli.optimize", "_run_recordings"), ("pipeline.optimizer.loop", "load_state"),
         ("pipeline.optimizer.loop", "run_lock"), ("pipeline.optimizer.loop", "TokenCounter")]
"""Where between the run's creation and its loop the stop lands (each, the first thing that step calls)."""


def _stop_at(monkeypatch, module: str, name: str, stop: type[BaseException]) -> None:
    def stopped(*args, **kwargs):
        raise stop("stopped here by the test")

    monkeypatch.setattr(f"{module}.{name}", stopped)


def _rows(store: Store) -> list[tuple[str, str, str | None]]:
    return store.query("SELECT kind, status, error FROM runs ORDER BY created_at")


def _check(rows, kind: str, status: str) -> None:
    assert [(k, s) for k, s, _ in rows] == [(kind, status)], rows
    error = rows[0][2]
    assert error and (("interrupted by the user" in error) if status == "interrupted" else "OSError" in error), rows


@pytest.mark.parametrize("stop", STOPS, ids=list(STOPS))
@pytest.mark.parametrize("step", STEPS, ids=[name for _, name in STEPS])
def test_optimize_stopped_before_its_loop_leaves_no_run_running(step, stop, tmp_path, scripted, monkeypatch):
    model = scripted([COMPETENT_REPLY])
    store = Store(tmp_path / "s.duckdb")
    raised, status = STOPS[stop]
    _stop_at(monkeypatch, *step, raised)
    argv = ["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base, "--iterations", "1",
            "--eval-max-steps", "100", "--rollout-steps", "20", "--audit-episodes", "0", "--store", str(store.path)]
    if raised is OSError:
        with pytest.raises(OSError, match="stopped here by the test"):
            main(argv)
    else:
        assert main(argv) == 130
    _check(_rows(store), "optimize", status)
    assert model.requests() == [], "the loop never started: no call was made"


@pytest.mark.parametrize("stop", STOPS, ids=list(STOPS))
@pytest.mark.parametrize("way", ["a batch's run", "the Python API", "a replay"])
def test_every_way_of_starting_a_run_ends_it_when_stopped_before_its_loop(way, stop, tmp_path, scripted, monkeypatch):
    from pipeline.jobs.worker import _optimize
    from pipeline.llm.client import open_client
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.loop import optimize, start_run
    from pipeline.optimizer.replay import replay

    model = scripted([COMPETENT_REPLY])
    store = Store(tmp_path / "s.duckdb")
    config = OptimizeConfig(game="pong", model=model.model, api_base=model.api_base, iterations=1,
                            eval_max_steps=100, rollout_steps=20, audit_episodes=0)
    original = start_run(config, store, model.model) if way == "a replay" else None
    raised, status = STOPS[stop]
    _stop_at(monkeypatch, "pipeline.optimizer.replay" if way == "a replay" else "pipeline.optimizer.loop", "load_state",
             raised)
    with pytest.raises(raised, match="stopped here by the test"):
        if way == "a batch's run":
            _optimize({"config": asdict(config), "batch": "b", "batch_key": "k"}, store)
        elif way == "the Python API":
            client, server, _ = open_client(model.model, model.api_base, 0.0, 256, None)
            optimize(config, store, client)
        else:
            replay(store, original)
    rows = _rows(store)
    if way == "a replay":  # the original, as it was; the replay run ended
        assert rows[0][:2] == ("optimize", "running"), rows
        rows = rows[1:]
    _check(rows, {"a replay": "replay"}.get(way, "optimize"), status)


@pytest.mark.parametrize("sent", [signal.SIGINT, signal.SIGTERM], ids=["a Ctrl-C", "a SIGTERM"])
@pytest.mark.parametrize("verb", ["eval", "optimize"])
def test_a_stop_that_lands_in_the_write_that_ends_a_run_waits_for_it(verb, sent, tmp_path, scripted, monkeypatch):
    module = "pipeline.play.evaluate" if verb == "eval" else "pipeline.optimizer.loop"
    ending = getattr(__import__(module, fromlist=["finish_run"]), "finish_run")
    landed = []

    def stopped_while_ending(*args, **kwargs):
        landed.append(True)
        os.kill(os.getpid(), sent)  # its handler runs at the next line of Python: in the transaction
        return ending(*args, **kwargs)

    monkeypatch.setattr(f"{module}.finish_run", stopped_while_ending)
    store = Store(tmp_path / "s.duckdb")
    if verb == "eval":
        argv = ["eval", str(POLICIES / "pong_competent.py"), "--episodes", "2", "--max-steps", "60"]
    else:
        model = scripted([COMPETENT_REPLY])
        argv = ["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base, "--iterations",
                "0", "--eval-max-steps", "60", "--audit-episodes", "0"]
    assert main([*argv, "--store", str(store.path)]) == 130, "the press still stops the command"
    assert landed == [True]
    assert store.query("SELECT kind, status FROM runs") == [(verb, "finished")]
    assert store.query("SELECT count(*) FROM episodes WHERE kind = 'eval'") == [(2 if verb == "eval" else 1,)]


def test_uninterrupted_holds_a_stop_to_the_end_of_the_outermost_block_and_no_further():
    from pipeline.stopping import stop_once, uninterrupted

    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}

    def install() -> None:
        for signum in before:
            signal.signal(signum, stop_once)

    try:
        for signum, raised in [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, Terminated)]:
            install()
            done = []
            with pytest.raises(raised) as stop:
                with uninterrupted():
                    with uninterrupted():
                        os.kill(os.getpid(), signum)
                        done.append("inner")
                    done.append("outer")
            assert done == ["inner", "outer"] and type(stop.value) is raised
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN, "a second press is ignored while it winds down"
            with uninterrupted():  # nothing held over
                pass
        # a block that fails keeps its error, and the stop is not raised later by another block
        install()
        with pytest.raises(ValueError, match="its own"):
            with uninterrupted():
                os.kill(os.getpid(), signal.SIGINT)
                raise ValueError("its own")
        with uninterrupted():
            pass
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


def test_a_stopped_commands_press_does_not_stop_what_its_caller_runs_next():
    """The press that stopped a command is looked at again by the long waits of what follows (a swallowed one:
    :func:`pipeline.stopping.raise_if_stopped`), but only while the signals are still ignored: a caller in the same
    process (a test, a script) that put its handlers back was stopped by it in its next batch or evaluation (a test
    process of the suite ended "node down: keyboard-interrupt")."""
    from pipeline.stopping import raise_if_stopped, stop_once, stop_pending

    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        for signum in before:
            signal.signal(signum, stop_once)
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            sum(range(1000))  # the handler runs here
        assert stop_pending(), "while the command winds down, its press stands"
        with pytest.raises(KeyboardInterrupt):
            raise_if_stopped()
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)
    assert not stop_pending()
    raise_if_stopped()  # the caller goes on


def test_only_a_swallowed_press_goes_unsaid():
    """``quiet_swallowed_interrupts``: a KeyboardInterrupt Python had to ignore (a finalizer's) is not printed; any
    other error it ignores still is, by the hook that was there before."""
    import subprocess
    import sys
    import textwrap

    program = textwrap.dedent("""
        from pipeline.stopping import quiet_swallowed_interrupts

        class Raises:
            def __init__(self, error):
                self.error = error

            def __del__(self):
                raise self.error

        quiet_swallowed_interrupts()
        Raises(KeyboardInterrupt())
        Raises(ValueError("a finalizer's own error"))
        print("went on")
    """)
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout == "went on\n", done.stderr
    assert "a finalizer's own error" in done.stderr and "KeyboardInterrupt" not in done.stderr, done.stderr


def test_a_press_python_swallows_in_a_fork_still_ends_a_wait_for_ever():
    """A Ctrl-C whose handler ran in an at-fork hook (``store.hub``'s, as ``view --serve-web`` started Rerun's
    server) raised its KeyboardInterrupt there, where Python prints "Exception ignored" and goes on; the signals
    were ignored from then on, and the command served for good (a soak of presses hung it). ``wait_for_stop``
    raises the stop all the same, at once."""
    import subprocess
    import sys
    import textwrap

    program = textwrap.dedent("""
        import os, signal, sys, time
        from pipeline.stopping import stop_on_signals, stop_once, wait_for_stop

        stop_on_signals(stop_once)
        armed = [True]

        def before():
            if armed.pop() if armed else False:
                os.kill(os.getpid(), signal.SIGINT)
                sum(range(1000))  # the handler runs here, in the hook: its interrupt is swallowed

        os.register_at_fork(before=before)
        pid = os.fork()
        if pid == 0:
            os._exit(0)
        os.waitpid(pid, 0)
        print("went on past the press", flush=True)
        started = time.monotonic()
        try:
            wait_for_stop(lambda timeout: time.monotonic() - started > 20)
        except KeyboardInterrupt:
            print("stopped after %.1f s" % (time.monotonic() - started), flush=True)
            sys.exit(130)
        sys.exit(1)
    """)
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=120,
                          cwd=str(POLICIES.parents[1]))
    assert done.returncode == 130, done.stdout + done.stderr
    assert "went on past the press" in done.stdout and "Exception ignored" in done.stderr
    assert float(done.stdout.split("stopped after ")[1].split()[0]) < 2


@pytest.mark.parametrize("sent", [signal.SIGINT, signal.SIGTERM], ids=["a Ctrl-C", "a SIGTERM"])
@pytest.mark.parametrize("way", ["the command line", "a batch's run", "the Python API", "a replay"])
def test_a_stop_that_lands_as_the_run_is_made_ends_it(way, sent, tmp_path, scripted, monkeypatch):
    """A SIGTERM to `optimize`'s group landed just after the run's row was committed, before its id reached the
    code that ends a run cut short: "interrupted before the run was made; nothing was stored", and the store held
    the run 'running' (CI). The making of the run now holds a stop until its id is known."""
    from pipeline.jobs.worker import _optimize
    from pipeline.llm.client import open_client
    from pipeline.optimizer import loop
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.replay import replay
    from pipeline.stopping import stop_once

    model = scripted([COMPETENT_REPLY])
    store = Store(tmp_path / "s.duckdb")
    config = OptimizeConfig(game="pong", model=model.model, api_base=model.api_base, iterations=1,
                            eval_max_steps=100, rollout_steps=20, audit_episodes=0)
    original = loop.start_run(config, store, model.model) if way == "a replay" else None
    made = loop.start_run

    def made_then_stopped(*args, **kwargs):
        run_id = made(*args, **kwargs)
        os.kill(os.getpid(), sent)  # its handler runs at the next line of Python: before the id is returned
        return run_id

    monkeypatch.setattr("pipeline.optimizer.loop.start_run", made_then_stopped)  # every way makes its run there
    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        if way == "the command line":
            assert main(["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                         "--iterations", "1", "--eval-max-steps", "100", "--rollout-steps", "20", "--audit-episodes",
                         "0", "--store", str(store.path)]) == 130
        else:
            for signum in before:  # as the command line and a batch's run process install it
                signal.signal(signum, stop_once)
            with pytest.raises(KeyboardInterrupt):
                if way == "a batch's run":
                    _optimize({"config": asdict(config), "batch": "b", "batch_key": "k"}, store)
                elif way == "the Python API":
                    optimize_client, _, _ = open_client(model.model, model.api_base, 0.0, 256, None)
                    loop.optimize(config, store, optimize_client)
                else:
                    replay(store, original)
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)
    rows = _rows(store)[1:] if way == "a replay" else _rows(store)
    _check(rows, "replay" if way == "a replay" else "optimize", "interrupted")
