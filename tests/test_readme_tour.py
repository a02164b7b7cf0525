"""The README's ten-line tour runs as printed, in order (#23: every command the README shows runs as printed).

The tour is read from README.md itself, so a change to it is tested as it is written. It follows a main job: here
a short optimization of Pong by a scripted model behind real HTTP (the offline model would take minutes and
cannot write code), in a project whose ``games/`` and ``tests/`` are the repository's, with the store named by
``$CODEARCADE_STORE`` as a user would set it once. Each command runs through the real console script; `view
--serve-web` serves until a real SIGINT, as the tour says.
"""

from __future__ import annotations

import os
import queue
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from store import Store
from tests.conftest import COMPETENT_REPLY, ROOT, json_reply
from tests.scripted_llm import ScriptedModel

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")


def tour() -> list[list[str]]:
    """The commands of README.md's tour, each as its words (comments and the venv's activation left out)."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## A ten-line tour", 1)[1]
    block = section.split("```bash\n", 1)[1].split("```", 1)[0]
    commands = [shlex.split(line, comments=True) for line in block.splitlines()]
    return [words for words in commands if words and words[0] != "source"]


def test_the_tour_is_ten_codearcade_commands():
    commands = tour()
    assert len(commands) == 10 and all(words[0] == "codearcade" for words in commands), commands


@pytest.mark.slow
def test_the_readme_tour_runs_as_printed(tmp_path):
    project = tmp_path / "project"
    project.mkdir()
    for folder in ("games", "tests"):  # the tour names the repository's example policies by relative paths
        (project / folder).symlink_to(ROOT / folder)
    store = Store(tmp_path / "codearcade.duckdb")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_API_KEY")}
    env.update(CODEARCADE_STORE=str(store.path), LITELLM_LOCAL_MODEL_COST_MAP="True", OMP_WAIT_POLICY="PASSIVE",
               XDG_DATA_HOME=str(tmp_path / "xdg"))

    def run(words: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
        return subprocess.run([EXE, *words[1:]], cwd=project, env=env, capture_output=True, text=True,
                              timeout=timeout, stdin=subprocess.DEVNULL)

    # the main job's shape: one optimization (its replies: a competent rewrite, then nothing to change)
    with ScriptedModel([COMPETENT_REPLY, json_reply({}, "nothing to change")], tmp_path / "model") as model:
        made = run(["codearcade", "optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                    "--iterations", "2", "--eval-max-steps", "300", "--rollout-steps", "60"])
        assert made.returncode == 0, made.stdout + made.stderr
        (run_id,) = [r[0] for r in store.query("SELECT run_id FROM runs")]
        said: dict[str, subprocess.CompletedProcess] = {}
        for words in tour():
            verb = words[1]
            if "--serve-web" in words:
                said[verb] = serve_until_interrupted(words, project, env)
                continue
            done = run(words)
            assert done.returncode == 0, f"{shlex.join(words)}\n{done.stdout}{done.stderr}"
            said[verb] = done

    runs = said["runs"].stdout.splitlines()
    assert run_id.startswith(runs[2].split()[0]), runs
    curve = said["sql"].stdout.splitlines()
    assert [line.split()[0] for line in curve[2:]] == ["0", "1", "2", "(3"], curve
    assert (project / "reports" / run_id / "README.md").is_file()
    assert re.match(r"run \S+ \(pong\), policy version", said["blame"].stdout)
    assert "open http://127.0.0.1:" in said["view"].stdout
    assert store.query("SELECT max(iteration), any_value(status) FROM iterations JOIN runs USING (run_id) "
                       "WHERE run_id = ?", [run_id]) == [(3, "finished")]
    replayed = said["replay"].stdout.splitlines()  # the resumed run again from its stored replies, no divergence
    assert re.match(r"replay of \S+ as \S+: finished", replayed[0]), replayed
    assert [(line.split()[0], line.split()[1]) for line in replayed[2:]] == [(str(i), "same") for i in range(4)]
    assert re.search(r"^mean return \S+ .*n=3\b", said["eval"].stdout, re.M), said["eval"].stdout
    assert re.search(r"first divergent step: \d+ \(A chose", said["compare"].stdout), said["compare"].stdout
    assert said["doctor"].stdout.splitlines()[-1] == "ok: no damage found"


def serve_until_interrupted(words: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run a serving command until it prints its URL and the line that says Ctrl-C stops it, then press Ctrl-C."""
    # Its own process group, as a terminal's shell starts it (Ctrl-C is live in it however the suite was started:
    # tests/conftest.py's pytest_configure)
    proc = subprocess.Popen([EXE, *words[1:]], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, stdin=subprocess.DEVNULL, process_group=0)
    lines: queue.Queue = queue.Queue()

    def read_lines() -> None:  # in a thread: the wait for a line below has a deadline, a read does not
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=read_lines, daemon=True).start()
    said = []
    try:
        deadline = time.monotonic() + 120
        while not (said and (said[-1] is None or "Ctrl-C" in said[-1])):
            try:  # the line that says how to stop it, within two minutes (a blocking read waited for ever)
                said.append(lines.get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                break
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C at a terminal does: the whole group
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            raise AssertionError(f"{words} still ran 120 s after Ctrl-C; it had said {said!r}, and on stderr "
                                 f"{proc.stderr.read()!r}") from None
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    while said[-1:] != [None]:  # the rest of what it printed, up to the end of its output
        said.append(lines.get(timeout=30))
    lines_said = [line for line in said if line is not None]
    out = "".join(lines_said)
    assert proc.returncode in (0, 130), out + err
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
