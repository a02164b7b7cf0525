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

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from store import Store
from tests.conftest import COMPETENT_REPLY, EXAMPLES, ROOT

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
PRESSES = 3
SOAK_PRESSES = 50
SPAN_S = (0.3, 9.0)
"""Where a press may land: from the command's imports to its episodes, writes and (optimize) first LLM call."""


def _press(argv: list[str], delay: float, cwd) -> subprocess.CompletedProcess:
    """Run ``codearcade argv`` as a terminal's shell does (its own process group, Ctrl-C live), press Ctrl-C after
    ``delay`` seconds (to the group), and return how it ended."""
    proc = subprocess.Popen([EXE, *argv], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL, process_group=0,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        time.sleep(delay)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _delays(rng: random.Random, presses: int) -> list[float]:
    low, high = SPAN_S
    edges = [low + (high - low) * i / presses for i in range(presses + 1)]
    return [rng.uniform(a, b) for a, b in zip(edges, edges[1:])]


def _check(done: subprocess.CompletedProcess, store: Store, cwd) -> None:
    said = f"{done.args}\n{done.stderr[-3000:]}"
    assert done.returncode in (0, 130), said
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr, said
    if done.returncode == 130:
        assert done.stderr.strip().splitlines()[-1].startswith("codearcade: interrupted"), said
    if store.exists():
        statuses = {status for (status,) in store.query("SELECT status FROM runs")}
        assert statuses <= {"finished", "interrupted"}, (statuses, said)
        doctor = subprocess.run([EXE, "doctor", "--store", str(store.path), "--json"], cwd=cwd, capture_output=True,
                                text=True, timeout=120)
        assert doctor.returncode == 0 and json.loads(doctor.stdout)["ok"], doctor.stdout + doctor.stderr


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
        for phase in ("read", "write"):
            timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
            timer.start()
            try:
                with getattr(store, phase)() as con:
                    if phase == "write":
                        insert_run(con, "01CUT", "eval", "pong", {}, "# policy\\n", "v" * 16, {})
                    con.execute("SELECT count(*) FROM range(30000000000) t(i) WHERE i % 7 = 3").fetchall()
                print(phase, "finished")
            except KeyboardInterrupt:
                print(phase, "KeyboardInterrupt")
            except BaseException as exc:
                print(phase, type(exc).__name__, exc)
            finally:
                timer.cancel()
    """)
    with store.write() as con:
        before = con.execute("SELECT count(*) FROM runs").fetchone()[0]
    done = subprocess.run([sys.executable, "-c", script, str(store.path)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)  # uninterrupted, the query would take minutes
    assert done.stdout.splitlines() == ["read KeyboardInterrupt", "write KeyboardInterrupt"], done.stdout + done.stderr
    assert store.query("SELECT count(*) FROM runs") == [(before,)], "the interrupted write left nothing"
