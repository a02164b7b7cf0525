"""Ctrl-C as a terminal sends it: SIGINT to the whole process group (the command, its zygotes, game hosts and
policy processes, its model server), at random moments of `eval` and `optimize`, never a traceback and never a
lost or failed run.

DuckDB's client turns a SIGINT that arrives during a query into ``RuntimeError('Query interrupted')``; the store
gives it back as the KeyboardInterrupt it was (``store/db.py``), so the run is marked ``interrupted`` and
resumable and the command exits 130 whatever it was doing (creating the store, migrating it, writing steps).

By default a few presses per verb, at moments drawn from strata of its first seconds; ``pytest --soak`` presses
a hundred times across the verbs (about 10 minutes).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from pipeline.cli import main
from store import Store
from tests.conftest import COMPETENT_REPLY, EXAMPLES, POLICIES, ROOT

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
PRESSES = 3
SOAK_PRESSES = 50
SPAN_S = (0.3, 9.0)
"""Where a press may land: from the command's imports to its episodes, writes and (optimize) first LLM call."""


def _press(argv: list[str], delay: float | None, cwd, sent: int = signal.SIGINT, nohup: bool = False,
           wait_s: float = 300, alone: bool = False, command: tuple[str, ...] = (EXE,)) -> subprocess.CompletedProcess:
    """Run ``codearcade argv`` as a terminal's shell does (its own process group, Ctrl-C live), press Ctrl-C after
    ``delay`` seconds (to the group; None: the command presses itself), and return how it ended. ``nohup``: started
    with SIGINT ignored, as ``nohup`` and CI start commands, and stopped with ``sent`` (SIGTERM) instead; ``alone``:
    ``sent`` to the command's process alone, as ``kill PID`` and ``timeout`` send it."""
    interrupt = signal.SIG_IGN if nohup else signal.SIG_DFL
    proc = subprocess.Popen([*command, *argv], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL, process_group=0, env={**os.environ, "PYTHONFAULTHANDLER": "1"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, interrupt))
    try:
        if delay is not None:
            time.sleep(delay)
        if delay is not None and proc.poll() is None:
            (os.kill if alone else os.killpg)(proc.pid, sent)
        try:
            out, err = proc.communicate(timeout=wait_s)
        except subprocess.TimeoutExpired:  # stuck: where each of its threads waits (faulthandler), and what is left
            os.kill(proc.pid, signal.SIGABRT)
            time.sleep(2)
            left = _left_running(proc.pid)
            os.killpg(proc.pid, signal.SIGKILL)
            err = proc.communicate()[1]
            raise AssertionError(f"{proc.args} had not ended {wait_s} s after the press; its group held {left}; "
                                 f"its stderr ends:\n{err[-8000:]}") from None
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    done.group = proc.pid  # the group it led: what it started is in it
    return done


def _delays(rng: random.Random, presses: int) -> list[float]:
    low, high = SPAN_S
    edges = [low + (high - low) * i / presses for i in range(presses + 1)]
    return [rng.uniform(a, b) for a, b in zip(edges, edges[1:])]


def _left_running(group: int) -> list[str]:
    """The processes of process group ``group`` still alive (zombies aside: they hold nothing), as 'pid name'."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = open(f"/proc/{entry}/stat").read()
        except OSError:
            continue
        name, rest = stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:].split()
        if int(rest[2]) == group and rest[0] != "Z":  # fields after the name: state, ppid, pgrp
            found.append(f"{entry} {name}")
    return found


def _nothing_left(group: int, said: str) -> None:
    """Every process the command started has ended: its zygotes, game hosts, policy processes and servers."""
    deadline = time.monotonic() + 60  # generous: the check is that they end, not how fast
    while (left := _left_running(group)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not left, f"still running after the command ended: {left}\n{said}"


def _statuses(store: Store) -> set[str]:
    """The runs' statuses as the store itself holds them: every run a press stopped is marked there by the process
    that ran it (a run stopped between its creation and its loop was left 'running', shown interrupted by `runs`
    only because no process held it: ``tests/faults/test_a_stopped_run_is_ended.py``)."""
    return {status for (status,) in store.query("SELECT status FROM runs")}


def _check(done: subprocess.CompletedProcess, store: Store, cwd) -> None:
    said = f"{done.args}\n{done.stderr[-3000:]}"
    _nothing_left(done.group, said)
    assert done.returncode in (0, 130), said
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr, said
    if done.returncode == 130:
        assert done.stderr.strip().splitlines()[-1].startswith("codearcade: interrupted"), said
    if store.exists():
        statuses = _statuses(store)
        assert statuses <= {"finished", "interrupted"}, (statuses, said)
        # in this process (a `codearcade doctor` of its own cost ~2 s of CPU a press, its imports): the same reading
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["doctor", "--store", str(store.path), "--json"])
        assert code == 0 and json.loads(out.getvalue())["ok"], out.getvalue() + err.getvalue()


@pytest.mark.slow
@pytest.mark.parametrize("verb", ["eval", "optimize"])
def test_ctrl_c_to_the_process_group_interrupts_cleanly(verb, tmp_path, scripted, soak):
    rng = random.Random(f"ctrl-c-{verb}")
    model = scripted([COMPETENT_REPLY]) if verb == "optimize" else None
    presses = SOAK_PRESSES if soak else PRESSES
    for k, delay in enumerate(_delays(rng, presses)):
        store = Store(tmp_path / f"s{k}.duckdb")
        if verb == "eval":
            argv = ["eval", str(EXAMPLES / "breakout.py"), "--episodes", "4", "--max-steps", "2000", "--trace",
                    "--store", str(store.path)]
        else:
            argv = ["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                    "--iterations", "2", "--eval-max-steps", "1500", "--rollout-steps", "100", "--audit-episodes",
                    "0", "--store", str(store.path)]
        done = _press(argv, delay, ROOT)
        _check(done, store, ROOT)
        if verb == "optimize" and store.exists() and store.query("SELECT count(*) FROM runs WHERE status = "
                                                                 "'interrupted'")[0][0]:
            (run_id,) = store.query("SELECT run_id FROM runs")[0]
            resumed = subprocess.run([EXE, "optimize", "--resume", run_id, "--store", str(store.path)], cwd=ROOT,
                                     capture_output=True, text=True, timeout=600)
            assert resumed.returncode == 0, resumed.stderr[-3000:]
            assert store.query("SELECT status FROM runs") == [("finished",)]


@pytest.fixture(scope="module")
def optimized(tmp_path_factory):
    """A store holding one finished optimize run (the scripted model's competent reply): what `audit` and `view`
    act on; each press works on a copy of it."""
    from tests.scripted_llm import ScriptedModel

    where = tmp_path_factory.mktemp("ctrl-c")
    store = Store(where / "optimized.duckdb")
    model = ScriptedModel([COMPETENT_REPLY], where / "model").start()
    try:
        made = subprocess.run([EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base",
                               model.api_base, "--iterations", "1", "--eval-max-steps", "300", "--rollout-steps", "50",
                               "--audit-episodes", "0", "--rng-key", "ctrl-c", "--store", str(store.path)], cwd=ROOT,
                              capture_output=True, text=True, timeout=600)
    finally:
        model.stop()
    assert made.returncode == 0, made.stderr[-3000:]
    return store


def _copy(store: Store, path) -> Store:
    import shutil

    shutil.copyfile(store.path, path)
    return Store(path)


def _verb_argv(verb: str, k: int, tmp_path, optimized: Store, model) -> tuple[list[str], Store]:
    """The command a press lands on, and its store: each a few seconds of real work (episodes, writes, a server)."""
    if verb in ("audit", "view"):
        store = _copy(optimized, tmp_path / f"s{k}.duckdb")
        argv = (["audit", "last", "--episodes", "3", "--workers", "2"] if verb == "audit" else
                ["view", "last", "--serve-web"])
        return [*argv, "--store", str(store.path)], store
    store = Store(tmp_path / f"s{k}.duckdb")
    if verb == "compare":
        return ["compare", str(EXAMPLES / "pong.py"), str(POLICIES / "pong_competent.py"), "--episodes", "2",
                "--max-steps", "1500", "--store", str(store.path)], store
    experiments = tmp_path / f"batch{k}.toml"
    experiments.write_text(textwrap.dedent(f"""
        name = "ctrl-c-{k}"
        [defaults]
        iterations = 1
        eval_max_steps = 300
        rollout_steps = 50
        audit_episodes = 0
        rng_key = "ctrl-c"
        model = "{model.model}"
        api_base = "{model.api_base}"
        [matrix]
        game = ["pong", "breakout"]
        seed = [0, 1]
    """))
    return ["batch", str(experiments), "--store", str(store.path)], store


@pytest.mark.slow
@pytest.mark.parametrize("verb", ["batch", "audit", "compare", "view"])
def test_ctrl_c_to_the_process_group_of_the_other_verbs(verb, tmp_path, scripted, optimized, soak):
    """batch, audit, compare and view --serve-web: the same as eval and optimize, and nothing they started left
    running (zygotes, game hosts, policy processes, Rerun's server)."""
    rng = random.Random(f"ctrl-c-{verb}")
    model = scripted([COMPETENT_REPLY]) if verb == "batch" else None
    presses = SOAK_PRESSES // 2 if soak else PRESSES
    for k, delay in enumerate(_delays(rng, presses)):
        argv, store = _verb_argv(verb, k, tmp_path, optimized, model)
        done = _press(argv, delay, ROOT)
        _check(done, store, ROOT)
        # a batch's runs get the press too: each run's log says "interrupted" in a line, never a traceback (7 of 11
        # presses left one in every running run's log, from its imports or its episodes)
        for log in tmp_path.glob(f"s{k}.duckdb.*.log.runs/*.log"):
            assert "Traceback" not in log.read_text(errors="replace"), (log, log.read_text(errors="replace")[-2000:])


PRESSED_IN_A_FORK_HOOK = textwrap.dedent("""
    import os, signal, sys, time
    from pipeline.cli import main

    pressed = []

    def press():  # the terminal's Ctrl-C, to the group, as the command's at-fork hooks run after it forked
        if not pressed:
            pressed.append(True)
            os.killpg(0, signal.SIGINT)
            time.sleep(1)  # the handler runs in here: Python ignores what it raises ("Exception ignored in ...")

    os.register_at_fork(after_in_parent=press)
    sys.argv[0] = "codearcade"
    sys.exit(main())
""")


@pytest.mark.slow
@pytest.mark.parametrize("verb", ["batch", "view"])
def test_a_ctrl_c_that_python_swallows_in_a_fork_still_stops_the_command(verb, tmp_path, scripted, optimized):
    """A press that lands in an at-fork hook (logging's lock, as `view --serve-web` starts Rerun's server and a batch
    starts a run's process, both with a ``preexec_fn``) is one Python must ignore: it printed "Exception ignored in:
    <function _releaseLock>" and a traceback (CI, 1 of 1,666). Now nothing is printed but the line, and the command
    stops all the same: a batch does not go on starting its queued runs with Ctrl-C ignored."""
    model = scripted([COMPETENT_REPLY]) if verb == "batch" else None
    argv, store = _verb_argv(verb, 0, tmp_path, optimized, model)
    if verb == "batch":
        argv += ["--workers", "1"]  # one run at a time: the others wait in its queue
    done = _press(argv, None, ROOT, command=(sys.executable, "-c", PRESSED_IN_A_FORK_HOOK))
    _check(done, store, ROOT)
    assert done.returncode == 130, done.stderr[-3000:]
    if verb == "batch":  # stopped as its first run started: none of the queued ones was started after the press
        assert len(list(tmp_path.glob("s0.duckdb.*.log.runs/*.log"))) == 1, done.stderr[-3000:]


@pytest.mark.slow
@pytest.mark.parametrize("alone", [False, True], ids=["to the group", "to the command alone"])
@pytest.mark.parametrize("verb", ["eval", "optimize", "batch", "view"])
def test_sigterm_stops_a_command_as_ctrl_c_does(verb, alone, tmp_path, scripted, optimized):
    """docs/cli.md: a command stops on SIGTERM as on Ctrl-C. It did not: it died at once (exit 143, nothing said),
    its run left 'running' in the store (shown interrupted only because no process held it). Now, whether SIGTERM
    reaches the group (a command under nohup or CI, Ctrl-C ignored) or the command alone (``kill PID``,
    ``timeout``: a batch passes it on to its runs), it ends as interrupted: exit 130, the line, every run marked in
    the store itself, nothing left running, no traceback."""
    model = scripted([COMPETENT_REPLY]) if verb in ("batch", "optimize") else None
    if verb == "eval":
        store = Store(tmp_path / "s.duckdb")
        argv = ["eval", str(EXAMPLES / "breakout.py"), "--episodes", "4", "--max-steps", "2000", "--trace",
                "--store", str(store.path)]
    elif verb == "optimize":
        store = Store(tmp_path / "s.duckdb")
        argv = ["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base, "--iterations",
                "3", "--eval-max-steps", "2000", "--rollout-steps", "100", "--audit-episodes", "0", "--store",
                str(store.path)]
    else:
        argv, store = _verb_argv(verb, 0, tmp_path, optimized, model)
    done = _press(argv, 4.0, ROOT, sent=signal.SIGTERM, nohup=not alone, alone=alone)
    said = f"{done.args}\n{done.stderr[-3000:]}"
    _nothing_left(done.group, said)
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr, said
    assert done.returncode in (0, 130), said
    if done.returncode == 130:
        assert done.stderr.strip().splitlines()[-1].startswith("codearcade: interrupted"), said
    if store.exists():
        stored = _statuses(store)
        # a message in text: pytest cuts a tuple's repr short (CI's failure said only the first 120 characters)
        assert stored <= {"finished", "interrupted"}, f"{stored}\n{said}\n{_run_logs(tmp_path)}"


def _run_logs(tmp_path) -> str:
    """The ends of a batch's run logs under ``tmp_path``: where a run that outlived the wind-down was stuck (its
    stacks, written on the batch's SIGABRT)."""
    return "\n".join(f"--- {path.name}\n{path.read_text(errors='replace')[-4000:]}"
                     for path in sorted(tmp_path.glob("*.log.runs/*.log")))


@pytest.mark.slow
@pytest.mark.parametrize("phase", ["read", "write"])
def test_a_ctrl_c_while_the_store_opens_leaves_it_usable(store, phase):
    """A press at a random moment of opening the store (attaching the file to the process's DuckDB instance, in
    store/hub.py), a hundred times: each is a KeyboardInterrupt, and the store opens again afterwards, as the command
    marking its run interrupted needs. (A press between DuckDB's ATTACH and the hub's note of it left the file
    attached unnoted: the next open failed with 'database ... already exists'.)"""
    script = textwrap.dedent("""
        import os, random, signal, sys, threading, time
        from store import Store

        signal.signal(signal.SIGINT, signal.default_int_handler)
        store, phase = Store(sys.argv[1]), sys.argv[2]
        with store.write():
            pass
        rng = random.Random(f"opening-{phase}")
        caught = 0
        for _ in range(100):
            timer = threading.Timer(rng.uniform(0.0, 0.03), os.kill, (os.getpid(), signal.SIGINT))
            try:
                timer.start()
                while True:  # opens and queries until the press lands (a few dozen opens)
                    with getattr(store, phase)() as con:
                        con.execute("SELECT count(*) FROM runs").fetchall()
            except KeyboardInterrupt:
                caught += 1
            finally:
                timer.cancel()
        with store.write() as con:
            print(caught, con.execute("SELECT count(*) FROM runs").fetchone()[0])
    """)
    done = subprocess.run([sys.executable, "-c", script, str(store.path), phase], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.split() == ["100", "0"], done.stdout + done.stderr[-3000:]


@pytest.mark.slow
def test_a_ctrl_c_during_a_query_is_a_keyboard_interrupt_and_its_transaction_is_rolled_back(store):
    """The mechanism, at the moment a press is hardest to hit from outside: a SIGINT while DuckDB runs a query
    reaches the caller as KeyboardInterrupt (not DuckDB's RuntimeError), and the write it cut left nothing. In a
    process of its own, whose main thread runs the query as a command's does (a pytest worker may not)."""
    script = textwrap.dedent("""
        import os, signal, sys, threading
        from store import Store
        from store.writer import insert_run

        signal.signal(signal.SIGINT, signal.default_int_handler)  # as a command has it (this one's parent may not)
        store = Store(sys.argv[1])
        with store.write():  # attached and checked, as a command's store is by the time it plays and writes
            pass
        def press(done):  # Ctrl-C, and again each second until the phase ends, as a person would press it
            while not done.wait(0.3 if not press.count else 1.0):
                press.count += 1
                os.kill(os.getpid(), signal.SIGINT)

        for phase in ("read", "write"):
            # pressed while the query runs: the presses start once the store is open and the write is made (DuckDB
            # looks for a press between its tasks, which a loaded machine makes long: one press may land late)
            done, press.count = threading.Event(), 0
            presser = threading.Thread(target=press, args=(done,))
            try:
                with getattr(store, phase)() as con:
                    if phase == "write":
                        insert_run(con, "01CUT", "eval", "pong", {}, "# policy\\n", "v" * 16, {})
                    presser.start()
                    # a read runs on DuckDB's worker threads, and DuckDB looks for a press only when it ends (a
                    # 3e10-row read took 96 s to stop): this read is a few seconds' work; a write (one thread) stops
                    # at the press
                    rows = 1_500_000_000 if phase == "read" else 30_000_000_000
                    con.execute(f"SELECT count(*) FROM range({rows}) t(i) WHERE i % 7 = 3").fetchall()
                print(phase, "finished")
            except KeyboardInterrupt:
                print(phase, "KeyboardInterrupt")
            except BaseException as exc:
                print(phase, type(exc).__name__, exc)
            finally:
                done.set()
                if presser.is_alive():
                    presser.join()
    """)
    with store.write() as con:
        before = con.execute("SELECT count(*) FROM runs").fetchone()[0]
    done = subprocess.run([sys.executable, "-c", script, str(store.path)], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)  # uninterrupted, the query would take many minutes
    assert done.stdout.splitlines() == ["read KeyboardInterrupt", "write KeyboardInterrupt"], done.stdout + done.stderr
    assert store.query("SELECT count(*) FROM runs") == [(before,)], "the interrupted write left nothing"


@pytest.mark.slow
@pytest.mark.parametrize("query", ["SELECT count(*) FROM range(30000000000) t(i) WHERE i % 7 = 3",
                                   "SELECT count(mean_ci([i::DOUBLE, 1.0, 2.0])) FROM range(100000000) t(i)"],
                         ids=["DuckDB's own work", "a Python function of codearcade's in the query"])
def test_ctrl_c_during_a_persons_query_ends_it_as_interrupted(store, query):
    """``codearcade sql`` runs a person's query on a connection of its own, outside ``Store.read()``, so DuckDB's
    "Query interrupted" reached the command as a traceback and exit 1 (7 of 7 presses). And while DuckDB's threads
    ran one of the interval functions, a press waited for the query's end (minutes; 4 of 5 presses here), by when
    it had been ignored. It ends as interrupted now (130), at once, at any of three moments of a long query: the
    wakeup file descriptor tells a watching thread, which interrupts the query."""
    with store.write():
        pass
    for delay in (1.0, 2.5, 4.0):
        done = _press(["sql", query, "--store", str(store.path)], delay, ROOT, wait_s=60)
        said = f"{done.args}\n{done.stderr[-3000:]}"
        assert done.returncode == 130 and "Traceback" not in done.stderr, said
        assert done.stderr.strip().splitlines()[-1] == "codearcade: interrupted", said


def test_a_ctrl_c_a_library_wrapped_in_its_own_error_ends_the_command_as_interrupted():
    """Libraries catch the KeyboardInterrupt a press raises inside them and raise an error of their own: pydantic's
    SchemaError while litellm builds a model (seen once in a soak of optimize), DuckDB's error of a Python function
    in a query. Whatever error ends a command after a press is the press's: exit 130, "interrupted", no traceback.
    Without a press, the same error is the command's error as ever."""
    script = textwrap.dedent("""
        import os, signal, sys
        from pipeline import cli
        from pipeline.cli import runs

        def wrapped(args):
            try:
                if sys.argv[1] == "pressed":
                    os.kill(os.getpid(), signal.SIGINT)
                    signal.pause()
            except KeyboardInterrupt as exc:
                raise RuntimeError("Error building validator: KeyboardInterrupt") from exc
            raise RuntimeError("a failure of its own")

        runs.run = wrapped
        sys.exit(cli.main(["runs"]))
    """)
    for case in ("pressed", "not pressed"):
        done = subprocess.run([sys.executable, "-c", script, case], cwd=ROOT, capture_output=True, text=True,
                              timeout=120)
        if case == "pressed":
            assert done.returncode == 130 and done.stderr.strip() == "codearcade: interrupted", done.stderr
        else:
            assert done.returncode == 1 and "RuntimeError: a failure of its own" in done.stderr, done.stderr


def test_a_ctrl_c_while_the_zygotes_close_at_exit_kills_them_without_a_traceback(monkeypatch):
    """A batch's run pressed as it ended: the press landed in the atexit handler's wait for its zygote, and the run's
    log got "Exception ignored" and a traceback (a CI run). The handler now kills what is left, and says nothing."""
    import os

    from pipeline.boundary import zygotes

    killed = []

    class Pressed:  # a zygote whose end is waited for, and the wait cut by a press
        class proc:
            @staticmethod
            def kill():
                killed.append(True)

        def let_go(self):
            pass

        def wait_gone(self):
            raise KeyboardInterrupt

    monkeypatch.setattr(zygotes, "_zygotes", {"policy": Pressed(), "game": Pressed()})
    monkeypatch.setattr(zygotes, "_zygotes_pid", os.getpid())
    zygotes.stop_zygote()  # returns, not raises
    assert killed == [True, True]


def test_a_batch_run_says_nothing_of_a_press_that_lands_in_its_exit_handlers():
    """Whatever exit handler or finalizer a press lands in as a batch's run ends, the run's log gets no "Exception
    ignored" and traceback: the worker, run as a program, passes such a KeyboardInterrupt over (its line
    ``interrupted`` said it). Checked by an exit handler that raises it, registered before the worker runs."""
    program = ("import atexit, runpy, sys\n"
               "def pressed():\n    raise KeyboardInterrupt\n"
               "atexit.register(pressed)\n"
               "sys.argv = ['worker', '{}']\n"
               "try:\n    runpy.run_module('pipeline.jobs.worker', run_name='__main__')\n"
               "except BaseException:\n    pass\n")
    done = subprocess.run([sys.executable, "-c", program], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert "Exception ignored" not in done.stderr and "KeyboardInterrupt" not in done.stderr, done.stderr
    bare = subprocess.run([sys.executable, "-c", program.replace("pipeline.jobs.worker", "json.tool")], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert "Exception ignored" in bare.stderr, "without the worker's hook Python prints it"


@pytest.mark.slow
@pytest.mark.parametrize("verb", ["eval", "optimize"])
def test_a_command_that_ignores_ctrl_c_plays_through_one_to_its_group(verb, tmp_path, scripted):
    """A command started with Ctrl-C ignored (nohup, CI, ``codearcade eval p.py &`` in a script) goes on through a
    Ctrl-C to its process group, and so do the processes it started: its game hosts and policy processes died of
    it, and their games were stored as the policies' crashes, forfeits for good (``no score``, exit 1; an
    optimize run's audit a forfeit). Presses at moments drawn across the command's span: it ends as it would have
    without them, every game played out."""
    rng = random.Random(f"ignored-{verb}")
    model = scripted([COMPETENT_REPLY] * 4) if verb == "optimize" else None
    for k, delay in enumerate(_delays(rng, PRESSES)):
        store = Store(tmp_path / f"s{k}.duckdb")
        if verb == "eval":
            argv = ["eval", str(POLICIES / "pong_competent.py"), "--episodes", "3", "--max-steps", "3000", "--store",
                    str(store.path)]
        else:
            argv = ["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                    "--iterations", "1", "--eval-max-steps", "1500", "--rollout-steps", "100", "--audit-episodes",
                    "1", "--store", str(store.path)]
        done = _press(argv, delay, ROOT, sent=signal.SIGINT, nohup=True)
        said = f"{done.args} pressed at {delay:.1f} s\n{done.stderr[-3000:]}"
        _nothing_left(done.group, said)
        assert done.returncode == 0, said
        assert _statuses(store) == {"finished"}, said
        ended = store.query("SELECT end_reason, count(*) FROM episodes GROUP BY ALL ORDER BY ALL")
        assert {reason for reason, _ in ended} <= {"truncated", "terminated"}, (ended, said)


_GARBAGE = ("import gc, os, signal, sys\n"
            "class Held:  # in a cycle, freed by the collector alone: it says so if it is\n"
            "    def __del__(self, write=os.write):\n"
            "        write(2, b'collected at exit\\n')\n"
            "def garbage():\n"
            "    gc.disable()  # no collection before the exit's\n"
            "    held = Held()\n"
            "    held.me = held\n")


def _pressed_as_it_begins(where: str, prelude: str, at_the_press: str, timeout: float) -> subprocess.CompletedProcess:
    """A command's process (``codearcade runs``) or a batch's run process, pressed as its work begins: ``prelude``
    runs first, ``at_the_press`` (a statement) as it is pressed."""
    if where == "command":
        program = (prelude + "import os, signal, sys\nfrom pipeline import cli\nfrom pipeline.cli import runs\n"
                   f"def pressed(args):\n    {at_the_press}\n    os.kill(os.getpid(), signal.SIGINT)\n"
                   "    signal.pause()\nruns.run = pressed\nsys.argv = ['codearcade', 'runs']\nsys.exit(cli.main())\n")
    else:  # the run's process, as the batch starts it
        program = (prelude + "import json, runpy, sys\n"
                   f"def pressed(text):\n    {at_the_press}\n    raise KeyboardInterrupt\n"
                   "json.loads = pressed\nsys.argv = ['worker', '{}']\n"
                   "runpy.run_module('pipeline.jobs.worker', run_name='__main__')\n")
    return subprocess.run([sys.executable, "-c", program], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("where", ["command", "batch run"])
def test_an_interrupted_process_ends_without_collecting_its_garbage(where):
    """An optimize pressed in its episodes said `interrupted` within 0.1 s, then spent 2.3-3.0 s (of 4 presses)
    ending: the interpreter's last garbage collection, over what the stopped episodes and iteration left (~490,000
    objects), and a batch waited that long for each of its runs. The process is ending: nothing of it needs
    collecting (exit handlers still run: the zygotes are stopped), and it now ends in 0.8 s. Checked by its effect:
    a cycle made before the press is never collected."""
    done = _pressed_as_it_begins(where, _GARBAGE, "garbage()", timeout=120)
    assert done.returncode == 130, done.stdout + done.stderr
    assert "interrupted" in done.stdout + done.stderr and "collected at exit" not in done.stderr, done.stderr


_IMPORT_LOCK_HELD_AT_EXIT = (
    "import _imp, atexit, threading\n"
    "class ImportsAsItIsDropped:  # as litellm's HTTP handler does\n"
    "    def __del__(self):\n"
    "        import tabnanny\n"
    "def at_the_last_exit_handler():  # registered first, so it runs last\n"
    "    dropped = ImportsAsItIsDropped()\n"
    "    dropped.me = dropped  # in a cycle: the teardown's collection finalizes it\n"
    "    held = threading.Event()\n"
    "    def hold():  # as a daemon thread the teardown froze inside an import\n"
    "        _imp.acquire_lock()\n"
    "        held.set()\n"
    "        threading.Event().wait()\n"
    "    threading.Thread(target=hold, daemon=True).start()\n"
    "    held.wait()\n"
    "atexit.register(at_the_last_exit_handler)\n")


@pytest.mark.parametrize("where", ["command", "batch run"])
def test_an_interrupted_process_ends_though_a_daemon_thread_holds_the_import_lock(where):
    """A batch of two runs pressed as they waited for their model (``kill -INT`` of the batch) waited out its 60-s
    wind-down in 2 of 13 tries beside a busy machine: one run had said `interrupted` and hung. Its stack: in Python's
    teardown, litellm's HTTP handler being dropped imports a module and waits for the import lock, which a daemon
    thread frozen by the teardown holds for good. A command's process and a run's now end once their exit handlers
    have run, before the teardown. Checked by its effect: a daemon thread holds the import lock as the exit handlers
    end, an object imports as it is dropped in the teardown, and the process still ends."""
    done = _pressed_as_it_begins(where, _IMPORT_LOCK_HELD_AT_EXIT, "pass", timeout=60)
    assert done.returncode == 130, done.stdout + done.stderr
    assert "interrupted" in done.stdout + done.stderr and "Traceback" not in done.stderr, done.stderr


@pytest.mark.slow
def test_a_press_python_swallowed_still_stops_the_episodes(tmp_path):
    """A press whose KeyboardInterrupt is raised inside a finalizer is swallowed by Python ("Exception ignored in
    ..."), and the signals are ignored from then on: the episodes played on to their end. Seen as a batch of two
    runs pressed in their episodes that took 34.7 s to exit: one run played its last iteration out and finished (a
    run's log hides the ignored exception). The episodes' loop now looks for such a press each time it waits, and
    the command ends as interrupted. Here the press lands in a finalizer as the 20th message of the games is read."""
    store, swallowed = tmp_path / "s.duckdb", tmp_path / "swallowed"
    program = textwrap.dedent(f"""
        import os, signal, sys
        from pipeline import cli
        from pipeline.boundary import wire

        class Swallows:
            def __del__(self):
                try:  # the handler runs in here (os.kill runs it), and Python ignores what it raises
                    os.kill(os.getpid(), signal.SIGINT)
                    for _ in range(100_000):
                        pass
                except KeyboardInterrupt:
                    open({str(swallowed)!r}, "w").close()
                    raise

        parse, read = wire.parse_message, [0]

        def parse_message(payload):
            read[0] += 1
            if read[0] == 20:
                Swallows()  # made and dropped: its finalizer runs now
            return parse(payload)

        wire.parse_message = parse_message
        sys.argv = ["codearcade", "eval", {str(POLICIES / "pong_competent.py")!r}, "--episodes", "3", "--max-steps",
                    "100000", "--store", {str(store)!r}]
        sys.exit(cli.main())
    """)
    done = subprocess.run([sys.executable, "-c", program], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert swallowed.exists(), "the press was not swallowed: the test tests nothing"
    assert done.returncode == 130, done.stderr[-3000:]
    assert "Exception ignored" not in done.stderr and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert done.stderr.strip().splitlines()[-1].startswith("codearcade: interrupted"), done.stderr[-3000:]
    assert Store(store).query("SELECT status FROM runs") == [("interrupted",)]
    assert Store(store).query("SELECT count(*) FROM episodes")[0][0] < 3
