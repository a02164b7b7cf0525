"""``codearcade serve`` through its real protocol: a server process on 127.0.0.1 spoken to over plain HTTP+JSON, and
the scripted agent of ``examples/serve_agent.py`` over MCP (stdio, the official SDK's client), end to end.

What must hold: the budget is exact under concurrent submissions (a refused or malformed request costs nothing);
no training, validation or held-out seed appears in any response of a whole run; a submission that attacks is
contained as in ``eval`` and ``optimize`` (the same boundary) and the server goes on; a killed server's run
resumes with its budget as its committed submissions spent; the scripted agent improves the Pong starter, and its
run reads in ``runs``, ``report``, ``audit``, ``blame`` and ``view``.
"""

from __future__ import annotations

import concurrent.futures
import http.client
import json
import os
import random
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from pipeline.boundary.policy import (MAX_ANSWER, MAX_PRINTED_BYTES, PRINTED_TEXT_BYTES, PrintedText,
                                     printed_text)
from pipeline.cli import main
from store import Store
from tests.conftest import POLICIES, ROOT, pong_policy
from tests.faults.test_boundary import ESCAPE, SPAWN

pytestmark = pytest.mark.slow

ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "LITELLM_LOCAL_MODEL_COST_MAP": "True"}
HTTP_LINE = re.compile(r"HTTP\+JSON on http://127\.0\.0\.1:(\d+)/")


class Server:
    """``codearcade serve`` in a process of its own, its stderr collected by a thread (so it never blocks)."""

    def __init__(self, store: Path, *args: str, own_group: bool = False):
        self.proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "serve", "--port", "0", "--store",
                                      str(store), *args], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, process_group=0 if own_group else None)
        self.lines: list[str] = []
        self.responses: list[str] = []
        port = None
        for line in self.proc.stderr:
            self.lines.append(line)
            found = HTTP_LINE.search(line)
            if found:
                port = int(found.group(1))
                break
        assert port is not None, "".join(self.lines)
        self.url = f"http://127.0.0.1:{port}"
        threading.Thread(target=lambda: self.lines.extend(self.proc.stderr), daemon=True).start()

    def post(self, operation: str, body: bytes | dict | None = None) -> tuple[int, dict]:
        data = body if isinstance(body, bytes) else json.dumps(body or {}).encode()
        request = urllib.request.Request(f"{self.url}/{operation}", data=data, method="POST",
                                         headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=600) as answer:
                text, status = answer.read().decode(), answer.status
        except urllib.error.HTTPError as err:
            text, status = err.read().decode(), err.code
        self.responses.append(text)
        return status, json.loads(text)

    def stop(self, sig: int = signal.SIGINT) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=120)


@pytest.fixture
def servers():
    started: list[Server] = []
    yield started
    for server in started:
        server.stop(signal.SIGKILL)


def _run_id(store: Path) -> str:
    return Store(store).query("SELECT run_id FROM runs ORDER BY created_at DESC LIMIT 1")[0][0]


def _seeds(store: Path, run_id: str) -> set[int]:
    """Every seed of the run: its training instances (config), its episodes', its validation and held-out pools."""
    s = Store(store)
    config = json.loads(s.query("SELECT config FROM runs WHERE run_id = ?", [run_id])[0][0])
    seeds = set(config["serve"]["train_seeds"])
    seeds |= {r[0] for r in s.query("SELECT DISTINCT seed FROM episodes WHERE run_id = ?", [run_id])}
    seeds |= {seed for r in s.query("SELECT seeds FROM audits WHERE run_id = ?", [run_id]) for seed in r[0]}
    return seeds


def _leaks(texts: list[str], seeds: set[int]) -> list[tuple[int, str]]:
    """Each seed written as a whole number in a response (not inside a longer number or a decimal's digits)."""
    return [(seed, text[:200]) for seed in seeds for text in texts
            if re.search(rf"(?<![\d.]){seed}(?![\d.])", text)]


def test_a_whole_run_over_http_spends_its_budget_exactly_and_shows_no_seed(tmp_path, servers):
    store = tmp_path / "s.duckdb"
    server = Server(store, "--game", "pong", "--budget", "6", "--instances", "8", "--per-submission", "2",
                    "--max-steps", "120", "--validation-episodes", "2", "--heldout-episodes", "2")
    servers.append(server)
    status, task = server.post("task")
    assert status == 200 and task["budget"]["remaining"] == 6 and task["instances"] == 8
    starter = task["starter_policy"]
    # a sweep of malformed requests, sent concurrently with eight one-episode submissions: only six can play
    malformed = [b"{not json", {"instances": [0]}, {"policy": starter}, {"policy": starter, "instances": []},
                 {"policy": starter, "instances": [8]}, {"policy": starter, "instances": [-1]},
                 {"policy": starter, "instances": [1, 1]}, {"policy": starter, "instances": [0, 1, 2]},
                 {"policy": starter, "instances": ["0"]}, {"policy": starter, "instances": [True]},
                 {"policy": "def broken(:\n", "instances": [0]}, {"policy": "x = 1\n", "instances": [0]},
                 {"policy": starter, "instances": [0], "parent": 99}, {"policy": starter, "instances": [0], "x": 1},
                 {"policy": starter, "path": "policy.py", "instances": [0]}]
    results: list[tuple[str, int, dict]] = []

    def send(kind: str, operation: str, body) -> None:
        status, answer = server.post(operation, body)
        results.append((kind, status, answer))

    threads = [threading.Thread(target=send, args=("submit", "submit", {"policy": starter, "instances": [i]}))
               for i in range(8)]
    threads += [threading.Thread(target=send, args=("malformed", "submit", body)) for body in malformed]
    threads += [threading.Thread(target=send, args=("malformed", "nonsense", {}))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == len(threads), "every request was answered (none reset)"
    played = [a for kind, status, a in results if kind == "submit" and status == 200]
    refused = [a for kind, status, a in results if kind == "submit" and status != 200]
    assert len(played) == 6, results
    assert all("budget" in a["error"] for a in refused) and len(refused) == 2
    assert all(status in (400, 404) for kind, status, _ in results if kind == "malformed"), results
    assert sorted(a["submission"] for a in played) == [1, 2, 3, 4, 5, 6]
    status, budget = server.post("budget")
    assert budget == {"budget": 6, "spent": 6, "in_play": 0, "remaining": 0, "finalized": True}
    s = Store(store)
    run_id = _run_id(store)
    assert s.query("SELECT count(*) FROM episodes WHERE run_id = ? AND kind = 'train'", [run_id])[0][0] == 6
    assert s.query("SELECT kind, status FROM runs WHERE run_id = ?", [run_id])[0] == ("serve", "finished")
    roles = {r[0]: r[1] for r in s.query("SELECT role, protocol FROM audits WHERE run_id = ?", [run_id])}
    assert roles["best"] == "standard" and sum(p == "validation" for p in roles.values()) == 1  # one version
    # every other read the agent has, each over every submission
    for n in range(1, 7):
        status, feedback = server.post("feedback", {"submission": n, "steps": 200})
        assert status == 200 and feedback["trace"]["steps"], feedback
    for query in ["SELECT * FROM episodes", "SELECT * FROM submissions", "SELECT * FROM steps LIMIT 400",
                  "SELECT * FROM nodes LIMIT 400", "SELECT seed FROM episodes", "SELECT * FROM runs",
                  "SELECT * FROM audits", "SELECT * FROM read_parquet('/etc/passwd')",
                  f"ATTACH '{store}' AS other", "SELECT count(*) FROM range(1000000000000)"]:
        server.post("sql", {"query": query})
    status, rows = server.post("sql", {"query": "SELECT count(*), min(submission) FROM episodes"})
    assert rows.get("rows") == [[6, 1]], rows  # only this run's training episodes
    status, again = server.post("submit", {"policy": starter, "instances": [7]})
    assert status == 400 and "finalized" in again["error"]
    assert server.post("finalize")[0] == 400  # finalized already
    seeds = _seeds(store, run_id)
    assert len(seeds) == 8 + 2 + 2
    assert _leaks(server.responses, seeds) == []
    # the policies' random streams are keyed by a secret, not by the run id the agent is told (with that key, a
    # policy's draws would give each game's seed away)
    key = json.loads(s.query("SELECT config FROM runs WHERE run_id = ?", [run_id])[0][0])["rng_key"]
    assert key != run_id and run_id in server.responses[0] and not [t for t in server.responses if key in t]
    sealed = [r[0] for r in s.query("SELECT episode_id FROM episodes WHERE run_id = ? AND kind <> 'train'", [run_id])]
    # validation: one version (every submission is the starter's text), 2 games; held out: it is the best and the
    # starter, so it plays the pool once
    assert len(sealed) == 2 + 2 and not [e for e in sealed for text in server.responses if e in text]


ATTACK = ESCAPE + SPAWN + """
mods['builtins'].open('{write}', 'w').write('x')
return 0
"""
"""The sandbox tests' escape (``tests/faults/test_boundary.py``): three ways to start a process, then a file written
outside the scratch (the policy's end: a PermissionError)."""


def test_an_attacking_submission_is_contained_and_the_server_goes_on(tmp_path, servers, capsys, monkeypatch):
    store = tmp_path / "s.duckdb"
    sentinels = [tmp_path / f"escaped-{i}" for i in range(4)]
    # pools of 2 games, not the default 5: the looping submission burns its 2 s time limit in each of its games
    server = Server(store, "--game", "pong", "--budget", "5", "--max-steps", "60", "--call-time-limit", "2",
                    "--validation-episodes", "2", "--heldout-episodes", "2")
    servers.append(server)
    attack = pong_policy(ATTACK.format(system=sentinels[0], spawn=sentinels[1], fork=sentinels[2],
                                       write=sentinels[3]))
    # what eval makes of the same file (the path optimize plays too): the server must end its episodes the same way
    (tmp_path / "attack.py").write_text(attack)
    assert main(["eval", str(tmp_path / "attack.py"), "--max-steps", "60", "--call-time-limit", "2", "--store",
                 str(tmp_path / "eval.duckdb"), "--json"]) == 1
    evaluated = json.loads(capsys.readouterr().out)["episodes"][0]
    # caught by the source checks before anything plays: refused, and it costs nothing
    status, answer = server.post("submit", {"policy": pong_policy(f"open('{sentinels[3]}', 'w')\nreturn 0"),
                                            "instances": [0]})
    assert status == 400 and "open" in answer["error"]
    assert server.post("budget")[1]["spent"] == 0
    status, answer = server.post("submit", {"policy": attack, "instances": [0, 1]})
    assert status == 200, answer
    assert all(e["end_reason"] == evaluated["end_reason"] == "policy_error" for e in answer["episodes"]), answer
    assert all(e["error"] == evaluated["error"] for e in answer["episodes"]), (answer, evaluated)
    assert answer["score"] is None and answer["forfeit"]  # a forfeit: never ranked
    assert answer["budget"]["spent"] == 2  # failures cost their episodes
    loop = pong_policy("while True:\n    pass")
    status, answer = server.post("submit", {"policy": loop, "instances": [2]})
    assert status == 200 and answer["episodes"][0]["end_reason"] == "timeout"
    status, task = server.post("task")
    status, answer = server.post("submit", {"policy": task["starter_policy"], "instances": [3]})
    assert status == 200 and answer["episodes"][0]["end_reason"] == "truncated"
    assert [p.exists() for p in sentinels] == [False] * 4
    status, feedback = server.post("feedback", {"submission": 1})
    assert feedback["forfeit"] and feedback["trace"]["steps"][-1]["outcome"].endswith("(the policy failed)")
    # Ctrl-C stops the server (the run interrupted, resumable); the person finalizes it: the attack plays the
    # validation pool too, contained again, and the forfeiting submissions can never be the best
    server.stop(signal.SIGINT)
    assert server.proc.returncode == 0 and "serve --resume" in "".join(server.lines)
    run_id = _run_id(store)
    assert Store(store).query("SELECT status FROM runs WHERE run_id = ?", [run_id])[0][0] == "interrupted"
    # the commands it printed run as printed, from anywhere: they name the store given (they left it out, and
    # found no run in the per-user store)
    printed = re.findall(r"`(codearcade serve [^`]*)`", "".join(server.lines))
    assert [shlex.split(c)[2] for c in printed] == ["--resume", "--finalize"], server.lines
    assert all(shlex.split(c)[-2:] == ["--store", os.path.abspath(store)] for c in printed), printed
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(shlex.split(printed[1])[1:]) == 0
    said = capsys.readouterr().out
    assert "validation  submission 3:" in said and "<- best by validation" in said.split("submission 3:")[1]
    assert "validation  submission 1: forfeit" in said and "held-out    best (submission 3)" in said
    lines = {line.split(":")[0]: line for line in said.splitlines()}
    # submission 1 played its training and forfeited it; the starter never plays training (it said "not played"
    # for both)
    assert lines["validation  submission 1"].endswith("training forfeited"), said
    assert lines["held-out    starter"].endswith("training not played"), said
    # a finalized run is not served again (it served a budget of 0 that refused every submission)
    assert main(["serve", "--resume", run_id, "--port", "0", "--store", str(store)]) == 2
    (audit,) = re.findall(r"is finalized: `(codearcade audit [^`]*)`", capsys.readouterr().err)
    assert main(shlex.split(audit)[1:]) == 0 and "<- best by validation" in capsys.readouterr().out
    assert main(["serve", "--game", "pong", "--json", "--store", str(store)]) == 2
    assert "--json goes with --finalize" in capsys.readouterr().err
    assert main(["report", run_id, "--out", str(tmp_path / "report"), "--store", str(store)]) == 0
    readme = (tmp_path / "report" / "README.md").read_text()
    assert "a served run draws its training games anew" in readme and "plays the same episodes" not in readme
    assert [p.exists() for p in sentinels] == [False] * 4


def _peak_rss_mb(pid: int) -> float:
    """The process's peak resident memory (``VmHWM``), in MB."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(r"VmHWM:\s+(\d+) kB", status).group(1)) / 1024


def test_concurrent_large_submissions_are_parsed_one_at_a_time_and_a_closed_run_parses_none(tmp_path, servers):
    """Policy text is parsed in the server too, once a worker has vetted it (~1 KB of parse tree a character of
    degenerate code), and a text vetted before skips the worker. Eight concurrent submissions of one 190,000
    character text (refused for their GAME: they cost nothing and come as often as an agent likes) held their
    parse trees at once; parsed one at a time the server's peak grows by about one. A submission the budget cannot
    take is refused before its text is parsed."""
    store = tmp_path / "s.duckdb"
    server = Server(store, "--game", "pong", "--budget", "1", "--max-steps", "30")
    servers.append(server)
    filler = "0,\n" * 63_000  # a statement per line: the costliest text per character to parse
    policy = pong_policy("return 0").replace('GAME = "pong"', 'GAME = "breakout"') + filler
    assert 180_000 < len(policy) < 200_000
    assert server.post("submit", {"policy": policy, "instances": [0]})[0] == 400  # vetted once: then each
    # request of the same text skips the worker and goes straight to the server's own parse
    policies = [policy] * 8
    before = _peak_rss_mb(server.proc.pid)
    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(lambda p: server.post("submit", {"policy": p, "instances": [0]}), policies))
    assert all(status == 400 and "GAME is breakout" in answer["error"] for status, answer in answers), \
        [(status, str(answer)[:300]) for status, answer in answers]
    grown = _peak_rss_mb(server.proc.pid) - before
    assert grown < 400, f"the server's peak grew by {grown:.0f} MB for eight submissions"
    status, task = server.post("task")
    status, answer = server.post("submit", {"policy": task["starter_policy"], "instances": [0]})
    assert status == 200 and answer["budget"]["spent"] == 1, answer
    before = _peak_rss_mb(server.proc.pid)
    spent = [pong_policy("return 1") + filler] * 4
    with concurrent.futures.ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(lambda p: server.post("submit", {"policy": p, "instances": [1]}), spent))
    assert all(status == 400 and answer["error"] in ("budget: 1 episodes asked, 0 left",
                                                     "the run is finalized: it takes no more submissions")
               for status, answer in answers), answers
    assert _peak_rss_mb(server.proc.pid) - before < 50, "refused before its text was parsed"


@pytest.mark.parametrize("printed", [
    "'MARKER-plain'",  # ASCII
    "'MARKER-é€😀'",  # every UTF-8 width
    "'MARKER-\\x01\\x1b[31m'",  # control characters: 6 bytes each as JSON
])
def test_a_submission_s_feedback_shows_what_its_policy_printed_within_bounds(tmp_path, servers, printed):
    # issue 42: the feedback holds the policy's own stdout. A policy that prints a marker finds it in its
    # feedback, as the submission answers it and as `feedback` reads it back from the store; one that prints 200 MB
    # an episode (4 MiB a step) gets the first 4 KiB of each episode and a count of the rest, and the server never
    # holds it
    store = tmp_path / "s.duckdb"
    server = Server(store, "--game", "pong", "--budget", "6", "--max-steps", "50", "--per-submission", "2")
    servers.append(server)
    marker = pong_policy(f"print({printed})\nreturn 0")
    status, answer = server.post("submit", {"policy": marker, "instances": [0, 1]})
    assert status == 200 and [e["end_reason"] for e in answer["episodes"]] == ["truncated"] * 2, answer
    stored = server.post("feedback", {"submission": 1})[1]["feedback"]
    for text in (answer["feedback"], stored):
        assert "#Printed" in text and "instance 0:" in text and "instance 1:" in text, text
        assert text.count("MARKER-") == 2 * 50, text  # every step's line of both episodes
        assert "not kept" not in text
    quiet = server.post("submit", {"policy": pong_policy("return 0"), "instances": [2]})[1]
    assert "#Printed" not in quiet["feedback"], quiet  # nothing printed, nothing said
    before = _peak_rss_mb(server.proc.pid)
    flood = pong_policy("print('MARKER-' + 'x' * 2**22)\nreturn 0")
    status, answer = server.post("submit", {"policy": flood, "instances": [3, 4]})
    assert status == 200 and [e["end_reason"] for e in answer["episodes"]] == ["truncated"] * 2, answer
    after = _peak_rss_mb(server.proc.pid)
    stored = server.post("feedback", {"submission": 3})[1]["feedback"]
    for text in (answer["feedback"], stored):
        printed_part = text.split("#Printed", 1)[1]
        assert text.count("MARKER-") == 2 and len(printed_part.encode()) < 8_192 + 1_000, len(printed_part)
        # each episode keeps its first 4 KiB (ASCII: 4,096 characters) and counts the characters past them
        assert f"{50 * (len('MARKER-') + 2**22 + 1) - 4_096:,} more characters printed, not kept" in text, text
    # 400 MB printed, and the server held none of it: its peak grew by less than 80 MB (scipy, imported when the
    # first interval of a score is computed, takes ~60 MB: it may come now)
    assert after - before < 80, (before, after)
    assert len(Store(store).query("SELECT text FROM feedback WHERE iteration = 3")[0][0]) < 8_192 + 2_000


def test_what_a_policy_prints_is_bounded_on_both_sides_of_the_boundary():
    # the policy process's side (its sys.stdout): whatever it writes, in pieces of any size and UTF-8 width, it
    # holds the first 4 KiB, a prefix of what was written, counts the rest, and its done frame fits what the host
    # reads (a control character is 6 bytes as JSON)
    rng = random.Random(42)
    alphabet = ["a", "é", "€", "😀", "\x01", "\ud800", "\n"]
    for _ in range(300):
        out = PrintedText()
        written = "".join(rng.choice(alphabet) * rng.choice([1, 7, 300, 5_000]) for _ in range(rng.randint(0, 12)))
        cuts = sorted(rng.sample(range(len(written) + 1), min(3, len(written) + 1)))
        for start, stop in zip([0, *cuts], [*cuts, len(written)]):
            out.write(written[start:stop])
        fields = out.take()
        kept = fields["printed"]
        assert len(kept.encode("utf-8", "replace")) <= MAX_PRINTED_BYTES
        assert written.encode("utf-8", "replace").startswith(kept.encode("utf-8", "replace"))
        assert fields["printed_dropped"] == len(written) - len(kept)
        done = json.dumps({"kind": "done", "nodes": True, **fields}, allow_nan=False, separators=(",", ":"))
        assert len(done.encode()) <= MAX_ANSWER
        assert out.take() == {"printed": "", "printed_dropped": 0}  # each episode afresh
    # the host's side: a done message forged by a process past the Python layer, already within MAX_ANSWER
    forged = [{}, {"printed": None}, {"printed": 7}, {"printed": ["x"]}, {"printed": "\x01" * 30_000},
              {"printed": "😀" * 8_000, "printed_dropped": 10**30}, {"printed": "x", "printed_dropped": True},
              {"printed": "x", "printed_dropped": -5}, {"printed": "x", "printed_dropped": "many"}]
    for message in forged:
        text = printed_text(message)
        assert text is None or len(text.encode("utf-8", "replace")) <= PRINTED_TEXT_BYTES, message


def test_a_killed_server_resumes_its_run_with_the_budget_intact(tmp_path, servers, capsys):
    store = tmp_path / "s.duckdb"
    first = Server(store, "--game", "pong", "--budget", "6", "--max-steps", "100", "--validation-episodes", "1",
                   "--heldout-episodes", "1")
    servers.append(first)
    status, task = first.post("task")
    assert first.post("submit", {"policy": task["starter_policy"], "instances": [0, 1]})[0] == 200
    # a submission in flight when the server is killed: whether it committed or not, the budget must agree
    def submit_until_killed():
        try:
            first.post("submit", {"policy": task["starter_policy"], "instances": [2, 3]})
        except (ConnectionError, http.client.HTTPException, urllib.error.URLError):
            pass  # the kill closes its connection: what the store holds is what the test checks

    threading.Thread(target=submit_until_killed, daemon=True).start()
    first.stop(signal.SIGKILL)
    run_id = _run_id(store)
    committed = Store(store).query("SELECT coalesce(sum(len(eval_episode_ids)), 0) FROM candidates WHERE run_id = ? "
                                   "AND iteration >= 1", [run_id])[0][0]
    assert committed in (2, 4)
    # another run on the same store meanwhile: many agents may serve different runs of one store at once
    other = Server(store, "--game", "pong", "--budget", "1", "--max-steps", "50", "--validation-episodes", "1",
                   "--heldout-episodes", "1")
    servers.append(other)
    second = Server(store, "--resume", run_id)
    servers.append(second)
    status, budget = second.post("budget")
    assert budget["spent"] == committed and budget["remaining"] == 6 - committed
    status, mine = second.post("sql", {"query": "SELECT count(*) FROM episodes"})
    assert mine["rows"] == [[committed]]  # a killed submission's episodes are not the agent's
    statuses = [other.post("submit", {"policy": task["starter_policy"], "instances": [0]})[0]]
    while (left := second.post("budget")[1]["remaining"]) > 0:
        status, answer = second.post("submit", {"policy": task["starter_policy"], "instances": list(range(min(2, left)))})
        assert status == 200, answer
    assert statuses == [200]
    s = Store(store)
    assert s.query("SELECT coalesce(sum(len(eval_episode_ids)), 0) FROM candidates WHERE run_id = ? AND "
                   "iteration >= 1", [run_id])[0][0] == 6
    assert s.query("SELECT status FROM runs WHERE run_id = ?", [run_id])[0][0] == "finished"
    iterations = [r[0] for r in s.query("SELECT iteration FROM iterations WHERE run_id = ? ORDER BY 1", [run_id])]
    assert iterations == list(range(len(iterations)))  # a submission per number, the starter 0, no gap
    second.stop()
    other.stop()
    assert main(["doctor", "--store", str(store)]) == 0  # whatever the kill cut off, the store is whole


def test_the_scripted_agent_improves_the_pong_starter_over_mcp(tmp_path, capsys):
    store = tmp_path / "agent.duckdb"
    done = subprocess.run([sys.executable, "examples/serve_agent.py", "--store", str(store), "--", "--budget", "16",
                           "--per-submission", "4", "--max-steps", "600", "--validation-episodes", "2",
                           "--heldout-episodes", "3"], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=900,
                          check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    run_id = done.stdout.strip().splitlines()[-1].split()[-1]
    s = Store(store)
    scores = dict(s.query("SELECT iteration, score FROM candidates WHERE run_id = ? AND iteration >= 1", [run_id]))
    assert len(scores) == 4 and max(scores.values()) > scores[1] + 5  # submission 1 is the starter
    audits = {r[0]: r[1] for r in s.query("SELECT role, score FROM audits WHERE run_id = ? AND protocol = 'standard'",
                                          [run_id])}
    assert audits["best"] > audits["starter"] + 5  # held out: tracking against a random paddle
    lineage = s.query("SELECT iteration, parent_id FROM policy_versions WHERE run_id = ? AND produced_by = 'agent' "
                      "ORDER BY iteration", [run_id])
    assert all(parent is not None for _, parent in lineage)
    # it reads like an optimize run
    assert main(["runs", "--store", str(store), "--json"]) == 0
    runs = json.loads(capsys.readouterr().out)
    assert runs[0]["kind"] == "serve" and runs[0]["audit_score"] == audits["best"]
    assert main(["runs", "--store", str(store)]) == 0
    table = capsys.readouterr().out.splitlines()  # the loop's strategy, feedback, seed are not the served run's
    assert "feedback" not in table[0] and " seed " not in table[0] and "staged" not in table[-1], table
    assert "strategy" not in table[0] and "greedy" not in table[-1], table
    assert main(["audit", "last", "--store", str(store)]) == 0
    said = capsys.readouterr().out
    assert "<- best by validation" in said and "held-out    best (submission" in said
    assert main(["blame", "last", "--store", str(store)]) == 0
    chosen = s.query("SELECT policy_version_id, iteration FROM audits WHERE run_id = ? AND role = 'best'", [run_id])[0]
    blamed = capsys.readouterr().out  # the best by validation, each line with the submission that wrote it
    assert f"policy version {chosen[0]} (iteration {chosen[1]}" in blamed and "def select_action" in blamed
    assert main(["report", "last", "--store", str(store), "--out", str(tmp_path / "report")]) == 0
    readme = (tmp_path / "report" / "README.md").read_text()
    assert "serve run" in readme and "validation" in readme and "codearcade serve --game pong" in readme
    assert main(["view", "last", "--store", str(store), "--save", str(tmp_path / "run.rrd")]) == 0
    assert (tmp_path / "run.rrd").stat().st_size > 0


def test_over_mcp_a_refused_request_is_a_tool_error_that_costs_nothing(tmp_path):
    from mcp import Client
    from mcp.client.stdio import StdioServerParameters

    outside = tmp_path / "outside.py"
    workspace = tmp_path / "workspace"
    workspace.mkdir()

    async def session() -> dict:
        params = StdioServerParameters(
            command=sys.executable, args=["-m", "pipeline.cli", "serve", "--mcp", "--game", "pong", "--budget", "3",
                                          "--max-steps", "60", "--store", str(tmp_path / "m.duckdb"), "--workspace",
                                          str(workspace)], cwd=str(ROOT), env=ENV)
        async with Client(params, read_timeout_seconds=600) as client:
            seen = {"tools": sorted(t.name for t in (await client.list_tools()).tools)}
            starter = (await client.call_tool("task", {})).structured_content["starter_policy"]
            outside.write_text(starter)
            (workspace / "mine.py").write_text(starter)
            refused = [await client.call_tool("submit", arguments) for arguments in (
                {"policy": "def broken(:\n", "instances": [0]}, {"policy": starter, "instances": [0, 1, 2, 3]},
                {"path": "../outside.py", "instances": [0]}, {"path": str(outside), "instances": [0]},
                {"path": "missing.py", "instances": [0]}, {"instances": [0]})]
            seen["refused"] = [(r.is_error, r.content[0].text) for r in refused]
            seen["budget"] = (await client.call_tool("budget", {})).structured_content
            seen["played"] = (await client.call_tool("submit", {"path": "mine.py", "instances": [2]})).structured_content
            seen["sql"] = (await client.call_tool("sql", {"query": "SELECT instance FROM episodes"})).structured_content
            return seen

    import asyncio

    seen = asyncio.run(session())
    assert seen["tools"] == ["budget", "feedback", "finalize", "sql", "submit", "task"]
    assert all(is_error for is_error, _ in seen["refused"]), seen["refused"]
    assert "budget" in seen["refused"][1][1] and "workspace" in seen["refused"][2][1]
    assert seen["budget"]["spent"] == 0 and seen["budget"]["remaining"] == 3
    assert seen["played"]["episodes"][0]["instance"] == 2 and seen["played"]["budget"]["spent"] == 1
    assert seen["sql"]["rows"] == [[2]]


def _mcp_over_http(tmp_path) -> tuple[subprocess.Popen, str]:
    """``serve --mcp-port 0`` with a budget of 2 episodes, and the URL it says it serves once it says it (the
    process is the caller's to stop)."""
    serve = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "serve", "--game", "pong", "--mcp-port", "0",
                              "--budget", "2", "--store", str(tmp_path / "m.duckdb")], cwd=ROOT, env=ENV,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said = []
    for line in serve.stderr:
        said.append(line)
        if "MCP (streamable HTTP) on" in line:
            break
    found = re.findall(r"(http://127\.0\.0\.1:\d+/mcp)", "".join(said))
    if len(found) != 1:
        serve.kill()
        serve.wait()
        raise AssertionError(said)
    return serve, found[0]


def test_over_mcp_streamable_http_on_a_free_port_the_port_said_is_the_port_served(tmp_path):
    """``serve --mcp-port 0`` (what a busy port's error suggests) said ``http://127.0.0.1:0/mcp`` and served on a
    port it never named. The URL it says now is where an MCP client reaches the run's tools; Ctrl-C stops it."""
    import asyncio

    from mcp import Client

    serve, url = _mcp_over_http(tmp_path)
    try:
        assert not url.endswith(":0/mcp"), url

        async def session() -> dict:
            async with Client(url, read_timeout_seconds=120) as client:
                return (await client.call_tool("task", {})).structured_content

        task = asyncio.run(session())
        assert task["game"] == "pong" and task["budget"]["remaining"] == 2, task
    finally:
        serve.send_signal(signal.SIGINT)
        serve.wait(timeout=120)
    assert serve.returncode == 0


@pytest.mark.slow
def test_over_mcp_streamable_http_idle_and_trickling_connections_are_bounded_and_closed(tmp_path):
    """uvicorn's defaults held every connection that sent nothing, or headers promising a body never sent: 1,100
    took ``serve --mcp-port`` down (out of file descriptors, under ``ulimit -n 1024``), 4,000 held 400 MB. Now the
    HTTP transport's bounds hold there too: past MAX_CONNECTIONS a connection is closed as it opens, one that has
    not sent a whole request within REQUEST_TIMEOUT_S is closed, and then an MCP client is served."""
    import asyncio
    import socket

    from mcp import Client

    from pipeline.serve.http import MAX_CONNECTIONS, REQUEST_TIMEOUT_S

    serve, url = _mcp_over_http(tmp_path)
    held: list[socket.socket] = []
    try:
        port = int(url.split(":")[2].split("/")[0])
        fds = len(os.listdir(f"/proc/{serve.pid}/fd"))
        for k in range(6 * MAX_CONNECTIONS):
            conn = socket.create_connection(("127.0.0.1", port), timeout=30)
            if k % 2:  # a request whose body never comes
                conn.sendall(b"POST /mcp HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100000\r\n\r\n{")
            held.append(conn)
        time.sleep(2)
        assert len(os.listdir(f"/proc/{serve.pid}/fd")) <= fds + MAX_CONNECTIONS + 8, "connections past the bound"
        started = time.monotonic()
        for conn in held:  # each is closed by the server: at once past the bound, else at the deadline
            conn.settimeout(max(1.0, REQUEST_TIMEOUT_S + 20 - (time.monotonic() - started)))
            try:
                assert conn.recv(65536) == b"", "closed by the server, unanswered"
            except ConnectionResetError:  # closed past the bound with our bytes unread
                pass
        assert time.monotonic() - started < REQUEST_TIMEOUT_S + 20

        async def session() -> dict:
            async with Client(url, read_timeout_seconds=120) as client:
                return (await client.call_tool("budget", {})).structured_content

        assert asyncio.run(session())["remaining"] == 2
        # sessions are bounded too (the SDK's 10,000 held 366 MB, and the port against every other client)
        from pipeline.serve.tools import MAX_SESSIONS

        def initialize() -> int:
            body = json.dumps({"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {
                "protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "t", "version": "1"}}})
            request = urllib.request.Request(url, data=body.encode(), method="POST", headers={
                "Content-Type": "application/json", "Accept": "application/json, text/event-stream"})
            try:
                with urllib.request.urlopen(request, timeout=60) as answer:
                    return answer.status
            except urllib.error.HTTPError as refused:
                return refused.code

        answers = [initialize() for _ in range(MAX_SESSIONS + 4)]
        assert answers.count(200) <= MAX_SESSIONS and answers[-1] == 503, answers
        assert serve.poll() is None, "the server is up"
    finally:
        for conn in held:
            conn.close()
        serve.send_signal(signal.SIGINT)
        serve.wait(timeout=120)
    assert serve.returncode == 0


def test_a_run_without_submissions_cannot_be_finalized(tmp_path, capsys):
    from pipeline.serve.config import ServeConfig
    from pipeline.serve.protocol import RequestError, ServeRun, create_run

    store = Store(tmp_path / "s.duckdb")
    run_id = create_run(store, ServeConfig(game="pong", budget=2))
    with pytest.raises(RequestError, match="nothing to finalize"):
        ServeRun(store, run_id).finalize()
    capsys.readouterr()
    assert main(["serve", "--finalize", run_id, "--store", str(store.path)]) == 2
    err = capsys.readouterr().err
    # one line, the refusal: not "playing the validation and held-out pools" first, which nothing then plays
    assert "nothing to finalize" in err and "playing" not in err, err
    assert not ServeRun(store, run_id).finalized and main(["doctor", "--store", str(store.path)]) == 0


def test_a_submission_given_back_takes_the_games_it_finished_with_it(tmp_path):
    """A submission the server's stop cut is given back: "it is not stored and cost nothing". Yet the games it had
    finished before the stop were in the store (written as they ended), counted by ``runs`` and read by SQL, with
    no submission naming them. The stop here comes as the first game ends, so the second never starts."""
    from pipeline.serve.config import ServeConfig
    from pipeline.serve.protocol import RequestError, ServeRun, create_run

    store = Store(tmp_path / "s.duckdb")
    run_id = create_run(store, ServeConfig(game="pong", budget=4, max_steps=200))
    served = ServeRun(store, run_id)
    served.on_episode = lambda episode: served.stopping.set()
    with pytest.raises(RequestError, match="stopped while this submission played: it is not stored"):
        served.submit(instances=[0, 1], policy=(ROOT / "games" / "scaffolds" / "pong.py").read_text())
    left = store.query("SELECT count(*) FROM episodes WHERE run_id = ? AND iteration > 0", [run_id])[0][0]
    steps = store.query("SELECT count(*) FROM steps s JOIN episodes e USING (episode_id) "
                        "WHERE e.run_id = ? AND e.iteration > 0", [run_id])[0][0]
    assert (left, steps) == (0, 0)
    assert ServeRun(store, run_id).budget()["spent"] == 0


@pytest.fixture(scope="module")
def any_store(tmp_path_factory) -> Path:
    """A store holding one short evaluation (the agent's SQL reads only its own copies of a run's tables)."""
    path = tmp_path_factory.mktemp("sql") / "s.duckdb"
    assert main(["eval", str(ROOT / "games" / "scaffolds" / "pong.py"), "--episodes", "1", "--max-steps", "10",
                 "--store", str(path)]) == 0
    return path


@pytest.mark.parametrize("value_chars, rows", [(10, 3), (10, 5_000), (900, 2_000), (40_000, 30), (3_000_000, 3)])
def test_the_agents_sql_answer_is_bounded_in_rows_and_bytes_and_a_prefix_of_the_result(any_store, value_chars,
                                                                                          rows):
    """A query of 5 x 100 MB values answered 500 MB and held the server at 1.4 GB. Now each answer is a prefix
    of the result, at most MAX rows and bytes of JSON, and says when it left rows out."""
    from store.serve import visible_query

    max_rows, max_bytes = 500, 100_000
    sql = f"SELECT i, repeat('x', {value_chars}) AS v FROM range({rows}) t(i) ORDER BY i"
    answer = visible_query(Store(any_store), "no-run", sql, max_rows, max_bytes)
    shown = answer["rows"]
    assert [r[0] for r in shown] == list(range(len(shown))), "the first rows, in order"
    assert len(shown) <= max_rows and len(json.dumps(shown, allow_nan=False)) <= max_bytes
    fits = min(rows, max_rows, max_bytes // (value_chars + 20))  # ~20 bytes of JSON around each value
    assert len(shown) >= fits * 0.9, (len(shown), fits)
    assert answer["truncated"] == (len(shown) < rows)
    assert ("note" in answer) == (len(shown) < min(rows, max_rows)), answer.get("note")


def test_the_agents_sql_is_standard_json_refuses_writes_and_names_its_time_limit(any_store):
    from store.serve import visible_query
    from store.views import QueryError

    store = Store(any_store)
    answer = visible_query(store, "no-run", "SELECT 'nan'::DOUBLE, 'inf'::DOUBLE, ['-inf'::DOUBLE, 1.5], 2.0, "
                           "DATE '2026-12-05', 'ab' || chr(0) || '\u00e9'", 500, 100_000)
    assert answer["rows"] == [[None, None, [None, 1.5], 2.0, "2026-12-05", "ab\x00\u00e9"]]
    json.dumps(answer, allow_nan=False)  # what a strict JSON parser takes
    for statement in ("DELETE FROM episodes", "UPDATE episodes SET length = 0", "CREATE TABLE t (i INT)",
                      "INSERT INTO submissions VALUES (1)", "SET threads = 8"):
        with pytest.raises(QueryError, match="sql is read-only"):
            visible_query(store, "no-run", statement, 500, 100_000)
    with pytest.raises(QueryError, match="ran past its limit of 0.5 s"):
        visible_query(store, "no-run", "SELECT count(*) FROM range(1000000000000000)", 500, 100_000,
                      time_limit_s=0.5)
    with pytest.raises(QueryError, match="Could not convert string 'x' to UUID"):
        visible_query(store, "no-run", "SELECT 'x'::UUID", 500, 100_000)
    # a lone surrogate (JSON's "\ud800"): DuckDB's parser raised TypeError, a 500 and a traceback on the terminal
    for query in ("SELECT '\ud800'", "\udfff", "SELECT 1 -- \ud83d"):
        with pytest.raises(QueryError, match="not valid Unicode"):
            visible_query(store, "no-run", query, 500, 100_000)


def _raw(port: int, request: bytes, wait_s: float = 5.0) -> bytes:
    """What the server answers to ``request`` written as it is, until it closes the connection or ``wait_s`` pass."""
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=wait_s) as s:
        s.sendall(request)
        got = b""
        try:
            while chunk := s.recv(65536):
                got += chunk
        except TimeoutError:
            pass
        return got


def test_the_http_transport_answers_every_request_in_json_and_lets_go_of_stalled_or_gone_clients(tmp_path,
                                                                                                 monkeypatch,
                                                                                                 capfd):
    """A chunked body was taken for an empty one ('missing instances'), the standard library's own refusals came
    as HTML pages, a client that announced a body and sent 2 bytes held its connection for good, and a client
    that hung up put a traceback on the server's stderr."""
    import socket

    from pipeline.serve import http
    from pipeline.serve.config import ServeConfig
    from pipeline.serve.protocol import ServeRun, create_run

    assert http._Handler.timeout == http.REQUEST_TIMEOUT_S <= 60  # then shortened, so that the test need not wait
    monkeypatch.setattr(http._Handler, "timeout", 1.0)
    store = Store(tmp_path / "s.duckdb")
    run = ServeRun(store, create_run(store, ServeConfig(game="pong", budget=2)))
    server, thread = http.start_http(run)
    port = server.server_address[1]
    try:
        body = b'{"instances": [0], "path": "policy.py"}'
        answers = {
            "chunked": _raw(port, b"POST /submit HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n"
                                  + f"{len(body):x}\r\n".encode() + body + b"\r\n0\r\n\r\n"),
            "PUT": _raw(port, b"PUT /budget HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n"),
            "garbage": _raw(port, b"GARBAGE\x01 / NONSENSE/9\r\n\r\n"),
            "stalled": _raw(port, b"POST /budget HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\n{}"),
        }
        for name, answer in answers.items():
            head, _, payload = answer.partition(b"\r\n\r\n")
            if name == "stalled":  # closed by the server once its timeout passed (no answer is owed)
                assert answer == b"" or head.startswith(b"HTTP/1.1 4"), answer
                continue
            assert head.startswith(b"HTTP/1.1 4") or head.startswith(b"HTTP/1.1 5"), (name, answer)
            assert b"application/json" in head and "error" in json.loads(payload), (name, answer)
        assert b" 411 " in answers["chunked"].split(b"\r\n")[0]
        for _ in range(3):  # a client that asks and hangs up at once
            with socket.create_connection(("127.0.0.1", port)) as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")  # RST
                s.sendall(b"POST /sql HTTP/1.1\r\nHost: x\r\nContent-Length: 40\r\n\r\n"
                          b'{"query": "SELECT * FROM range(500)"}   ')
        status, budget = 0, None
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/budget", timeout=10) as answer:
            status, budget = answer.status, json.loads(answer.read())
        assert status == 200 and budget["spent"] == 0, "the server goes on"
    finally:
        server.shutdown()
        server.server_close()
    assert "Traceback" not in capfd.readouterr().err


_SQL_PEAK = """
import json, sys
sys.path.insert(0, sys.argv[2])
from store import Store
from store.serve import visible_query
from store.views import QueryError
def peak():
    with open("/proc/self/status") as f:
        return next(int(l.split()[1]) for l in f if l.startswith("VmHWM:")) / 1024
store = Store(sys.argv[3])
visible_query(store, "r", "SELECT count(*) FROM steps", max_rows=500, max_bytes=1_000_000)  # imports, a first read
before = peak()
try:
    answer = visible_query(store, "r", sys.argv[1], max_rows=500, max_bytes=1_000_000)
    said = {"rows": len(answer["rows"]), "note": answer.get("note")}
except QueryError as exc:
    said = {"refused": str(exc)}
print(json.dumps({"grown": peak() - before, **said}))
"""


@pytest.mark.parametrize("query", [
    "SELECT list_transform(range(0, 2000000), lambda x: {'a': x}) AS r",  # 1,454 MB, then 485 MB in the server
    "SELECT range(0, 10000000) AS r",  # 855 MB
    "SELECT repeat('a', 100000000) FROM range(5)",  # ~0.9 GB
    "SELECT list(range) FROM range(100000000)",
    "SELECT string_agg(repeat('x', 1000), ',') FROM range(2000000)",
    "SELECT count(*) FROM range(3000) a, range(3000) b, (SELECT list(range) l FROM range(1000000)) c",
])
def test_what_the_agents_query_builds_is_never_the_servers(any_store, query):
    """Queries of under 100 bytes that make DuckDB build hundreds of MB or more: they once grew the server by that
    much (one value of 2 million structs: 1,454 MB, then 485 MB of DuckDB's own; ``range(0, 10000000)``: 855 MB).
    The query now runs in a process of its own whose data segment is capped, so the server (here the process that
    calls ``visible_query``) grows by the answer alone, and the agent hears either a bounded answer or that the query
    needed more memory than a query may use."""
    done = subprocess.run([sys.executable, "-c", _SQL_PEAK, query, str(ROOT), str(any_store)], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    answer = json.loads(done.stdout)
    assert answer["grown"] < 60, answer
    if "refused" in answer:
        assert answer["refused"].startswith("the query needed more memory than its process may have"), answer
    else:
        assert answer["rows"] <= 1, answer


def test_a_workspace_file_is_read_as_every_policy_file_is(tmp_path):
    """A submission by ``path`` reads its file as ``eval`` reads one: within MAX_POLICY_CHARS, UTF-8 (a byte-order
    mark skipped), line ends as Python reads them; a refusal names the file as the agent named it."""
    from pipeline.serve.config import ServeConfig
    from pipeline.serve.protocol import RequestError, ServeRun, create_run

    store = Store(tmp_path / "s.duckdb")
    workspace = tmp_path / "workspace"
    workspace.mkdir()
    served = ServeRun(store, create_run(store, ServeConfig(game="pong", budget=2)), workspace=workspace)
    (workspace / "windows.py").write_bytes(b"\xef\xbb\xbfclass Policy:\r\n    pass\r\n")
    assert served._workspace_file("windows.py") == "class Policy:\n    pass\n"
    (workspace / "latin1.py").write_bytes(b"# caf\xe9\n")
    with pytest.raises(RequestError, match=r"^path: workspace file 'latin1.py' is not UTF-8 text$"):
        served._workspace_file("latin1.py")
    (workspace / "long.py").write_text("#" * 200_001)
    with pytest.raises(RequestError, match=r"^path: workspace file 'long.py' is longer than 200,000 characters"):
        served._workspace_file("long.py")
    assert str(workspace) not in str(pytest.raises(RequestError, served._workspace_file, "long.py").value)


@pytest.mark.parametrize("after_s", [0.5, 2.0, 4.0])
def test_ctrl_c_while_a_submission_plays_gives_it_back(tmp_path, capsys, after_s):
    """Ctrl-C at a terminal reaches the server and its workers (the whole process group) while a submission plays:
    the handler's thread went on under the stopping server, printed tracebacks (a closed zygote socket, a dict
    changed during iteration at exit), and the submission was stored as forfeited games, charged to the budget.
    Now the server gives it back: the agent's answer says so (never a 500), nothing is charged, no traceback; a
    submission that finished before the press keeps its result and its cost."""
    from pipeline.serve.protocol import ServeRun
    from tests.conftest import POLICIES

    store = tmp_path / "s.duckdb"
    server = Server(store, "--game", "pong", "--max-steps", "1500", "--workers", "2", "--budget", "8",
                    own_group=True)
    answer: dict = {}

    def submit() -> None:
        try:
            answer["got"] = server.post("submit", {"policy": (POLICIES / "pong_competent.py").read_text(),
                                                   "instances": [0, 1, 2, 3]})
        except OSError as exc:  # the server ended before it answered
            answer["lost"] = exc

    asking = threading.Thread(target=submit, daemon=True)
    asking.start()
    time.sleep(after_s)
    os.killpg(server.proc.pid, signal.SIGINT)
    server.proc.wait(timeout=180)
    asking.join(timeout=60)
    said = "".join(server.lines)
    assert server.proc.returncode == 0 and "Traceback" not in said and "Exception ignored" not in said, said
    status = answer["got"][0] if "got" in answer else None
    assert status in (200, 400, 503, None), answer
    run_id = _run_id(store)
    assert ServeRun(Store(store), run_id).budget()["spent"] == (4 if status == 200 else 0), (answer, said)
    capsys.readouterr()
    code = main(["doctor", "--store", str(store), "--json"])  # in this process: a `codearcade doctor` cost ~2 s CPU
    doctor = capsys.readouterr().out
    assert code == 0 and json.loads(doctor)["ok"], doctor


@pytest.mark.slow
@pytest.mark.parametrize("during", ["a submission", "finalize"])
def test_ctrl_c_stops_the_server_at_once_and_a_cut_finalize_leaves_the_run_open(tmp_path, during):
    """A reviewer's Ctrl-C while 8 games of a submission played: games the zygote started after the press played
    to their end, and the server stopped a minute later (its wait's own limit). While the run was being finalized:
    the validation game playing then was stored `crashed` (the press reached its worker), the submission read as
    forfeited, and the run as finished. Now no game starts after the press, the server stops in seconds, and a cut
    finalize audits nothing and leaves the run open (interrupted), to be finalized later."""
    from tests.conftest import POLICIES

    store = tmp_path / "s.duckdb"
    server = Server(store, "--game", "pong", "--max-steps", "3000", "--workers", "2", "--budget", "12",
                    "--validation-episodes", "6", "--heldout-episodes", "2", own_group=True)
    # ~3 ms a step: 8 games of 3,000 steps on 2 workers play for a minute and more
    policy = (POLICIES / "pong_competent.py").read_text().replace(
        '        player = obs.get("Player")\n', '        sum(range(30_000))\n        player = obs.get("Player")\n', 1)
    if during == "finalize":
        assert server.post("submit", {"policy": policy, "instances": [0]})[0] == 200
    asking = threading.Thread(target=lambda: server.post(*(("finalize", {}) if during == "finalize" else
                                                           ("submit", {"policy": policy,
                                                                       "instances": list(range(8))}))),
                              daemon=True)
    asking.start()
    time.sleep(3.0)
    pressed = time.monotonic()
    os.killpg(server.proc.pid, signal.SIGINT)
    server.proc.wait(timeout=180)
    stopped_in = time.monotonic() - pressed
    said = "".join(server.lines)
    assert server.proc.returncode == 0 and "Traceback" not in said, said
    assert stopped_in < 30, f"the server stopped {stopped_in:.0f} s after Ctrl-C"  # it waited 60 s
    s = Store(store)
    (status,) = s.query("SELECT status FROM runs")[0]
    assert status == "interrupted", said
    assert s.query("SELECT count(*) FROM audits") == [(0,)], "a cut finalize audits nothing"


def test_the_http_transport_refuses_pages_and_rebound_names_and_bounds_what_clients_hold(tmp_path, monkeypatch,
                                                                                         capfd):
    """A reviewer's hostile agent and web page: `GET /finalize` from an <img> finalized the run, a page's POST with
    a foreign Origin or Host got answers, 2,000 held connections took the server to 3.7 GB, a request trickled a
    byte every 10 s was served after 70 s, 200,000 `[` got a traceback and no answer, and a submission whose GAME
    held escape sequences put them raw on the server's terminal. Each now by its effect: the run not finalized and
    nothing spent, the 503 of the connection past the cap at once, the trickled connection closed at its deadline,
    a JSON 400, and no ESC byte on stderr."""
    import socket
    import time

    from pipeline.serve import http
    from pipeline.serve.config import ServeConfig
    from pipeline.serve.protocol import ServeRun, create_run

    monkeypatch.setattr(http._Handler, "timeout", 1.0)  # the whole request's deadline, shortened for the test
    monkeypatch.setattr(http, "MAX_CONNECTIONS", 3)
    store = Store(tmp_path / "s.duckdb")
    run = ServeRun(store, create_run(store, ServeConfig(game="pong", budget=2)))
    server, thread = http.start_http(run)
    port = server.server_address[1]

    def status(answer: bytes) -> int:
        return int(answer.split(b" ", 2)[1]) if answer.startswith(b"HTTP/1.1 ") else 0

    try:
        here = f"Host: 127.0.0.1:{port}\r\n".encode()
        answers = {
            "GET /finalize": _raw(port, b"GET /finalize HTTP/1.1\r\n" + here
                                  + b"Referer: http://evil.example/\r\n\r\n"),
            "foreign Host": _raw(port, b"POST /budget HTTP/1.1\r\nHost: evil.example\r\nContent-Length: 2\r\n\r\n{}"),
            "foreign Origin": _raw(port, b"POST /finalize HTTP/1.1\r\n" + here + b"Origin: http://evil.example\r\n"
                                   b"Content-Type: text/plain\r\nContent-Length: 2\r\n\r\n{}"),
            "deep JSON": _raw(port, b"POST /budget HTTP/1.1\r\n" + here + b"Content-Length: 200000\r\n\r\n"
                              + b"[" * 200_000),
            # a foreign one second: the check read the first
            "second Host": _raw(port, b"POST /finalize HTTP/1.1\r\n" + here + b"Host: evil.example\r\n"
                                b"Content-Length: 2\r\n\r\n{}"),
            "second Origin": _raw(port, b"POST /finalize HTTP/1.1\r\n" + here + f"Origin: http://127.0.0.1:{port}"
                                  "\r\nOrigin: http://evil.example\r\nContent-Length: 2\r\n\r\n{}".encode()),
        }
        assert {name: status(answer) for name, answer in answers.items()} == {
            "GET /finalize": 405, "foreign Host": 403, "foreign Origin": 403, "deep JSON": 400, "second Host": 403,
            "second Origin": 403}, answers
        assert all("error" in json.loads(answer.partition(b"\r\n\r\n")[2]) for answer in answers.values())
        assert not run.finalized and run.budget()["spent"] == 0
        # the connections past the cap: 503 at once, and the server serves again once they are gone
        held = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]
        began = time.monotonic()
        assert status(_raw(port, b"GET /budget HTTP/1.1\r\n" + here + b"\r\n")) == 503
        assert time.monotonic() - began < 5
        for connection in held:
            connection.close()
        # a request trickled a byte at a time: closed at its deadline (1 s here), not served at its end
        with socket.create_connection(("127.0.0.1", port), timeout=10) as trickled:
            began, closed_after = time.monotonic(), None
            for byte in b"POST /budget HTTP/1.1\r\nContent-Length: 2\r\n\r\n{}":
                try:
                    trickled.send(bytes([byte]))
                except OSError:
                    closed_after = time.monotonic() - began
                    break
                time.sleep(0.3)
                trickled.setblocking(False)
                try:
                    if trickled.recv(1) == b"":
                        closed_after = time.monotonic() - began
                        break
                except BlockingIOError:
                    pass
                finally:
                    trickled.setblocking(True)
            assert closed_after is not None and closed_after < 8, closed_after  # sent whole, it takes 14 s
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/budget", timeout=10) as answer:
            assert answer.status == 200
        # an agent's text in a failure the server prints: made safe for the terminal
        scaffold = (ROOT / "games" / "scaffolds" / "pong.py").read_text()
        hostile = scaffold.replace('GAME = "pong"', 'GAME = "\\x1b]0;PWNED\\x07\\x1b[2Jnope"')
        data = json.dumps({"instances": [0], "policy": hostile}).encode()
        answer = _raw(port, b"POST /submit HTTP/1.1\r\n" + here + f"Content-Length: {len(data)}\r\n\r\n".encode()
                      + data, wait_s=60)
        assert status(answer) == 400 and "nope" in json.loads(answer.partition(b"\r\n\r\n")[2])["error"], answer
        path = json.dumps({"instances": [0], "path": "\ud800/x"}).encode()  # a lone surrogate: no file's name
        answer = _raw(port, b"POST /submit HTTP/1.1\r\n" + here + f"Content-Length: {len(path)}\r\n\r\n".encode()
                      + path)
        assert status(answer) == 400, answer
        query = json.dumps({"query": "SELECT '\ud800'"}).encode()
        answer = _raw(port, b"POST /sql HTTP/1.1\r\n" + here + f"Content-Length: {len(query)}\r\n\r\n".encode()
                      + query)
        assert status(answer) == 400 and "not valid Unicode" in answer.decode(), answer
        monkeypatch.setattr(run, "budget", lambda: (_ for _ in ()).throw(RuntimeError("\x1b]0;PWNED\x07\x1b[2J")))
        assert status(_raw(port, b"POST /budget HTTP/1.1\r\n" + here + b"Content-Length: 2\r\n\r\n{}")) == 500
    finally:
        server.shutdown()
        server.server_close()
    err = capfd.readouterr().err
    assert "RuntimeError" in err and "\x1b" not in err and "\x07" not in err, err[-2000:]


def test_over_mcp_stdio_a_message_past_its_limit_is_dropped_as_it_arrives(tmp_path):
    """The MCP SDK reads a stdio line whole: 600 MB without a newline took a reviewer's `serve --mcp` to 2.5 GB.
    A line past MAX_MESSAGE_BYTES is now dropped as it arrives: 256 MB of one leave the server's peak memory
    within 64 MB of where it was, and the next message is answered."""
    from pipeline.serve.tools import MAX_MESSAGE_BYTES

    serve = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "serve", "--mcp", "--game", "pong", "--budget",
                              "2", "--store", str(tmp_path / "m.duckdb")], cwd=ROOT, env=ENV, stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)

    def ask(number: int) -> dict:
        serve.stdin.write(json.dumps({"jsonrpc": "2.0", "id": number, "method": "initialize", "params": {
            "protocolVersion": "2025-06-18", "capabilities": {},
            "clientInfo": {"name": "test", "version": "1"}}}).encode() + b"\n")
        serve.stdin.flush()
        return json.loads(serve.stdout.readline())

    try:
        assert ask(1)["id"] == 1
        before = _peak_rss_mb(serve.pid)
        chunk = b"x" * 2**20
        serve.stdin.write(b'{"jsonrpc": "2.0", "id": 2, "method": "ping", "params": {"pad": "')
        for _ in range(256):
            serve.stdin.write(chunk)
        serve.stdin.write(b'"}}\n')
        serve.stdin.flush()
        dropped, = _answers(serve, 1)  # its id is gone with it: answered with JSON-RPC's null
        assert dropped["id"] is None and "longer than the server reads" in dropped["error"]["message"], dropped
        assert ask(3)["id"] == 3, "the server reads on"
        assert 256 * 2**20 > MAX_MESSAGE_BYTES
        peak = _peak_rss_mb(serve.pid)
        assert peak - before < 64, f"the server's peak rose from {before:.0f} MB to {peak:.0f} MB"
    finally:
        serve.stdin.close()
        serve.wait(timeout=60)


def _stdio_serve(store: Path, stderr=subprocess.DEVNULL) -> subprocess.Popen:
    """``codearcade serve --mcp`` over stdio, initialized (the handshake's answer read)."""
    serve = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "serve", "--mcp", "--game", "pong", "--budget",
                              "2", "--store", str(store)], cwd=ROOT, env=ENV, stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=stderr)
    serve.stdin.write(json.dumps({"jsonrpc": "2.0", "id": 0, "method": "initialize", "params": {
        "protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "test", "version": "1"}}}).encode()
        + b'\n{"jsonrpc": "2.0", "method": "notifications/initialized"}\n')
    serve.stdin.flush()
    assert json.loads(serve.stdout.readline())["id"] == 0
    return serve


@pytest.mark.parametrize("playing", [False, True], ids=["idle", "a submission playing"])
@pytest.mark.parametrize("sent", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_over_mcp_stdio_a_server_stopped_while_its_agent_holds_stdin_exits(tmp_path, sent, playing):
    """An agent stops the server it started with SIGTERM (or a person presses Ctrl-C) while it still holds the
    server's stdin: the server marked its run stopped and said so, then never exited (the MCP SDK's reader thread
    waited on stdin for good, and the interpreter's exit on it; 120 s measured, a second Ctrl-C did not end it).
    And the signal, raised in the main thread where the SDK's event loop ran, could land in its tasks: asyncio
    printed a traceback of 300 lines (1 press in 8), or the SDK a warning that it could not answer. Now it exits as
    it said: 0, its two lines (served, stopped) and nothing else, the run interrupted."""
    store = tmp_path / "m.duckdb"
    said = tmp_path / "stderr"
    with open(said, "w") as err:
        serve = _stdio_serve(store, stderr=err)
    try:
        if playing:  # a game of ~4,000 steps: whether it ends before the signal or not, the server must exit
            serve.stdin.write(_tool_call(1, "submit", {"policy": (POLICIES / "pong_competent.py").read_text(),
                                                       "instances": [0]}))
            serve.stdin.flush()
            time.sleep(1.0)
        serve.send_signal(sent)
        assert serve.wait(timeout=60) == 0  # before: still running, stdin open, its run marked interrupted
    finally:
        serve.stdin.close()
        if serve.poll() is None:
            serve.kill()
            serve.wait()
    assert Store(store).query("SELECT status FROM runs") == [("interrupted",)]
    lines = said.read_text().splitlines()
    assert len(lines) == 2 and lines[0].startswith("run ") and lines[1].startswith("run "), said.read_text()


def _tool_call(number: int | str, name: str, arguments: dict) -> bytes:
    return json.dumps({"jsonrpc": "2.0", "id": number, "method": "tools/call",
                       "params": {"name": name, "arguments": arguments}}).encode() + b"\n"


def test_over_mcp_stdio_a_request_the_sdk_cannot_read_is_answered_and_the_server_reads_on(tmp_path):
    """A lone surrogate (the JSON escape "\\ud800", which Python's JSON reads and the MCP SDK's does not) in a
    tool call's argument got no answer over stdio: the SDK dropped the message, and the agent waited for good. It
    is now answered with an error for its id, and so is a request that is JSON but not JSON-RPC; a notification
    so written is set aside as before (nothing waits for it), and the next call is answered."""
    serve = _stdio_serve(tmp_path / "m.duckdb")
    try:
        serve.stdin.write(_tool_call(1, "sql", {"query": "SELECT '\ud800'"})  # json.dumps writes it "\\ud800"
                          + b'{"jsonrpc": "2.0", "method": "notifications/cancelled", "params": {"x": "\\udfff"}}\n'
                          + b'{"jsonrpc": "2.0", "id": "two", "method": "tools/call", "params": [1]}\n'
                          + _tool_call(3, "budget", {}))
        serve.stdin.flush()
        answers = [json.loads(serve.stdout.readline())]
        while answers[-1]["id"] != 3:  # the last one is answered last: read no further (before, 1 was never)
            answers.append(json.loads(serve.stdout.readline()))
        assert [a["id"] for a in answers] == [1, "two", 3], answers
        assert answers[0]["error"]["code"] == -32700 and "lone surrogate" in answers[0]["error"]["message"], answers
        assert answers[1]["error"]["code"] == -32600 and "params" in answers[1]["error"]["message"], answers
        assert answers[2]["result"]["structuredContent"]["remaining"] == 2, answers
    finally:
        serve.stdin.close()
        serve.wait(timeout=60)


def _answers(serve: subprocess.Popen, count: int, wait_s: float = 60.0) -> list[dict]:
    """The server's next ``count`` answers, each byte waited for at most ``wait_s`` (a request left unanswered fails
    the test rather than hanging it). Read from the pipe a byte at a time: ``serve.stdout.readline()`` takes the
    answers behind its line into its buffer, where ``select`` cannot see them (CI waited 60 s for four answers that
    had come)."""
    import select

    answers: list[dict] = []
    line = bytearray()
    while len(answers) < count:
        ready, _, _ = select.select([serve.stdout.fileno()], [], [], wait_s)
        byte = os.read(serve.stdout.fileno(), 1) if ready else b""
        assert byte, f"no answer after {answers}"
        line += byte
        if byte == b"\n":
            answers.append(json.loads(line))
            line.clear()
    return answers


def test_over_mcp_stdio_a_request_whatever_its_id_is_answered_and_a_deep_one_leaves_the_server_serving(tmp_path):
    """A request whose id is 5.5, null, true or a list was taken by the SDK for a notification, one whose id held a
    lone surrogate could not be named: none got an answer, and the agent waited for good. A line nested 50,000 deep
    (100 KB) raised RecursionError where the server looked for its id, and the server died. Each is now answered
    with an error for JSON-RPC's null id (the id the request had cannot be named), and the server reads on."""
    serve = _stdio_serve(tmp_path / "m.duckdb")
    budget = '"method": "tools/call", "params": {"name": "budget", "arguments": {}}'
    try:
        for n, odd in enumerate(['"\\ud800"', "5.5", "null", "true", "[1]", '{"a": 1}']):
            serve.stdin.write(f'{{"jsonrpc": "2.0", "id": {odd}, {budget}}}\n'.encode() + _tool_call(n, "budget", {}))
        serve.stdin.write(b'{"jsonrpc": "2.0", "id": 6, "method": "ping", "params": {"x": ' + b"[" * 5_000
                          + b"]" * 5_000 + b"}}\n" + _tool_call(7, "budget", {}))
        serve.stdin.write(b'{"jsonrpc": "2.0", "id": 8, "method": "ping", "params": {"x": ' + b"[" * 50_000
                          + b"]" * 50_000 + b"}}\n" + _tool_call(9, "budget", {}))
        serve.stdin.flush()
        answers = _answers(serve, 16)
        assert sorted(a["id"] for a in answers if a["id"] is not None) == [0, 1, 2, 3, 4, 5, 7, 9], answers
        refused = [a["error"] for a in answers if a["id"] is None]  # in the order they came: answered as read
        assert len(refused) == 8, answers
        assert "lone surrogate" in refused[0]["message"] and refused[0]["code"] == -32700
        assert all(e["code"] == -32600 and "a string or an integer" in e["message"] for e in refused[1:6]), refused
        assert refused[6]["code"] == -32700 and "more values" in refused[7]["message"], refused
        assert all(a["result"]["structuredContent"]["remaining"] == 2 for a in answers if a["id"] is not None)
    finally:
        serve.stdin.close()
        serve.wait(timeout=60)


def test_over_mcp_stdio_requests_of_4_mib_written_without_reading_the_answers_hold_a_bounded_peak(tmp_path):
    """Over stdio the server holds at most MAX_PENDING_REQUESTS requests unanswered, each a line of at most 4 MiB.
    Measured: 16 or 50 requests of 4 MiB (to a slow tool, a policy of \\uXXXX escapes, a 4 MiB string in an unknown
    argument or in the id) written without reading an answer grew the server's peak by at most ~130 MB. The costliest
    cheap shape: a 4 MiB id, which each answer echoes, so that the answers fill the pipe and the requests stay
    held. 50 of them grow the peak by under 200 MB (with the bound lifted: 262 MB), and all are answered."""
    import select

    serve = _stdio_serve(tmp_path / "m.duckdb")
    try:
        before = _peak_rss_mb(serve.pid)
        budget = {"method": "tools/call", "params": {"name": "budget", "arguments": {}}}

        def write() -> None:
            for n in range(50):
                serve.stdin.write(json.dumps({"jsonrpc": "2.0", "id": f"{n:02d}" + "x" * (4 * 2**20 - 200),
                                              **budget}).encode() + b"\n")
            serve.stdin.write(json.dumps({"jsonrpc": "2.0", "id": "last", **budget}).encode() + b"\n")
            serve.stdin.flush()

        writer = threading.Thread(target=write, daemon=True)
        writer.start()
        writer.join(timeout=5)  # it waits on the full pipe: the server reads no more until it is answered
        # the answers, 4 MiB each but the last request's, read in large pieces (a byte at a time would take
        # minutes), in the order the server ends them (not always the requests'): the short lines are kept
        lines, start, short = 0, b"", []  # start: the first 1,000 bytes of the line being read
        while lines < 51:
            ready, _, _ = select.select([serve.stdout.fileno()], [], [], 60)
            chunk = os.read(serve.stdout.fileno(), 2**20) if ready else b""
            assert chunk, f"{lines} answers, then none"
            *ended, rest = chunk.split(b"\n")
            for piece in ended:
                if len(start + piece) < 1000:
                    short.append(start + piece)
                start = b""
            start = (start + rest)[:1000]
            lines += len(ended)
        grown = _peak_rss_mb(serve.pid) - before
        (answer,) = [json.loads(line) for line in short]
        assert answer["id"] == "last" and answer["result"]["structuredContent"]["remaining"] == 2, answer
        assert grown < 200, f"the server's peak grew by {grown:.0f} MB for 50 requests of 4 MiB"
    finally:
        serve.stdin.close()
        serve.wait(timeout=60)


def test_over_mcp_stdio_a_message_of_more_values_than_the_server_parses_is_refused_unparsed(tmp_path):
    """The SDK parses a line whole into Python objects: 3.5 MB of [{},{},...] (within the 4 MiB a line may hold)
    in a tool call's arguments grew the server's peak by 175 MB, in a notification's params by 281 MB, 3.5 MB of
    small ints by ~85 MB. A message of more than MAX_MESSAGE_VALUES values is now refused before it is parsed,
    with an error (for JSON-RPC's null id: its own is not read), and the peak grows by a few MB."""
    from pipeline.serve.messages import MAX_MESSAGE_VALUES

    serve = _stdio_serve(tmp_path / "m.duckdb")
    dicts = b"[" + b",".join([b"{}"] * 1_150_000) + b"]"
    try:
        before = _peak_rss_mb(serve.pid)
        serve.stdin.write(b'{"jsonrpc": "2.0", "id": 1, "method": "tools/call", "params": {"name": "budget", '
                          b'"arguments": {"pad": ' + dicts + b"}}}\n")
        serve.stdin.write(b'{"jsonrpc": "2.0", "method": "notifications/cancelled", "params": {"requestId": 9, '
                          b'"pad": ' + dicts + b"}}\n")
        serve.stdin.write(_tool_call(2, "submit", {"policy": "x", "instances": [1] * 1_150_000})
                          + _tool_call(3, "submit", {"policy": "x", "instances": [99] * 10}))
        serve.stdin.flush()
        answers = sorted(_answers(serve, 4), key=lambda a: a["id"] is not None)
        grown = _peak_rss_mb(serve.pid) - before
        assert [a["id"] for a in answers] == [None, None, None, 3], answers
        assert all(f"{MAX_MESSAGE_VALUES:,} values" in a["error"]["message"] for a in answers[:3]), answers
        assert "each instance once" in answers[3]["result"]["content"][0]["text"], answers[3]
        assert grown < 32, f"the server's peak grew by {grown:.0f} MB for three messages of 3.5 MB"
    finally:
        serve.stdin.close()
        serve.wait(timeout=60)


def test_over_mcp_streamable_http_a_body_of_more_values_than_the_server_parses_is_refused_unparsed(tmp_path):
    """Over --mcp-port the SDK parsed each body whole too, and kept an ``initialize`` request's session: 16 sessions
    opened with 3.5 MB of [{},{},...] in their params held the server at 1.57 GB (from 214 MB) for their idle
    timeout. Such a body is refused (400, a JSON-RPC error) before it is parsed, one that opens a session past
    64 KiB or any past 4 MiB 413, and the server's peak grows by a few MB; a client is served as ever."""
    import asyncio

    from mcp import Client

    serve, url = _mcp_over_http(tmp_path)
    dicts = b"[" + b",".join([b"{}"] * 1_150_000) + b"]"

    def post(body: bytes, session: str | None = None) -> tuple[int, dict]:
        request = urllib.request.Request(url, data=body, method="POST", headers={
            "Content-Type": "application/json", "Accept": "application/json, text/event-stream",
            **({"Mcp-Session-Id": session, "Mcp-Protocol-Version": "2025-06-18"} if session else {})})
        try:
            with urllib.request.urlopen(request, timeout=60) as answer:
                return answer.status, {"session": answer.headers.get("mcp-session-id")}
        except urllib.error.HTTPError as refused:
            return refused.code, json.loads(refused.read())

    try:
        before = _peak_rss_mb(serve.pid)
        initialize = (b'{"jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {"protocolVersion": '
                      b'"2025-06-18", "capabilities": {}, "clientInfo": {"name": "t", "version": "1"}, "pad": ')
        # one that opens a session: at most 64 KiB (a session kept ~2 x its opening body: 16 sessions opened with
        # 4 MB of a string in their params held +128 MB)
        opened = [post(initialize + dicts + b"}}") for _ in range(2)] + [post(initialize + b'"' + b"x" * 2**20
                                                                              + b'"}}') for _ in range(2)]
        assert all(status == 413 and "before a session is open" in a["error"]["message"] for status, a in opened)
        status, answer = post(initialize + b"0}}")
        assert status == 200 and answer["session"], answer
        call = (b'{"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {"name": "budget", "arguments": '
                b'{"pad": ')
        answers = [post(call + dicts + b"}}}", answer["session"]) for _ in range(4)]
        assert [status for status, _ in answers] == [400] * 4, answers
        assert all("more values than the server parses" in a["error"]["message"] for _, a in answers), answers
        assert post(call + b'"' + b"x" * (4 * 2**20) + b'"}}}', answer["session"])[0] == 413
        grown = _peak_rss_mb(serve.pid) - before
        assert grown < 32, f"the server's peak grew by {grown:.0f} MB for eight bodies of 1-3.5 MB"

        async def session() -> dict:
            async with Client(url, read_timeout_seconds=120) as client:
                return (await client.call_tool("budget", {})).structured_content

        assert asyncio.run(session())["remaining"] == 2
    finally:
        serve.send_signal(signal.SIGINT)
        serve.wait(timeout=120)


def test_over_mcp_streamable_http_the_bodies_held_at_once_are_bounded_in_bytes_clients_gone_or_not(tmp_path):
    """Over --mcp-port each request held its body, parsed (~2-4 x its bytes), for as long as its tool ran, and a
    client that hung up once its request was taken let go of its connection (the bound of 32) but not of the
    request, which the SDK ran on: 80 requests of 4 MiB to a slow tool (SQL waiting its turn, up to 40 s), each
    client gone as its answer began, grew the server's peak by 630 MB, linearly; 32 at once held by their clients,
    by 558 MB. The bodies held at once are now at most MAX_HELD_BYTES, each until its request is answered, its
    client there or not; one past it is answered 503 at once: the peak grows by under ~150 MB, and the server
    answers on."""
    import asyncio
    import socket

    from mcp import Client

    from pipeline.serve.tools import MAX_HELD_BYTES, MAX_MESSAGE_BYTES

    serve, url = _mcp_over_http(tmp_path)
    port = int(url.rsplit(":", 1)[1].split("/")[0])
    try:
        request = urllib.request.Request(url, method="POST", headers={
            "Content-Type": "application/json", "Accept": "application/json, text/event-stream"}, data=json.dumps({
                "jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {"protocolVersion": "2025-06-18",
                                                                              "capabilities": {}, "clientInfo": {
                                                                                  "name": "t", "version": "1"}}})
            .encode())
        with urllib.request.urlopen(request, timeout=60) as answer:
            session = answer.headers["mcp-session-id"]
        slow = "SELECT count(*) FROM range(3000000000) AS t(n) WHERE n % 7 = 3"  # past its 10 s: 2 run at once
        call = json.dumps({"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {
            "name": "sql", "arguments": {"query": slow, "pad": ""}}}).encode()
        body = call.replace(b'"pad": ""', b'"pad": "' + b"x" * (MAX_MESSAGE_BYTES - 4096 - len(call)) + b'"')
        head = (f"POST /mcp HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
                f"Accept: application/json, text/event-stream\r\nMcp-Session-Id: {session}\r\n"
                f"Mcp-Protocol-Version: 2025-06-18\r\nContent-Length: {len(body)}\r\n\r\n").encode()
        before = _peak_rss_mb(serve.pid)
        statuses = []
        for _ in range(50):  # each client hangs up once its answer has begun: its request taken, or refused
            with socket.create_connection(("127.0.0.1", port), timeout=60) as connection:
                connection.sendall(head + body)
                got = b""
                while b"\r\n\r\n" not in got:
                    chunk = connection.recv(4096)
                    assert chunk, got
                    got += chunk
                statuses.append(int(got.split(b" ", 2)[1]))
        grown = _peak_rss_mb(serve.pid) - before
        assert grown < 250, f"the server's peak grew by {grown:.0f} MB for 50 requests of 4 MiB"  # before: +400
        assert set(statuses) == {200, 503}, statuses  # before: all 50 taken
        assert statuses.count(200) < 50 // 2 and MAX_HELD_BYTES < 50 * len(body)

        async def budget() -> dict:
            async with Client(url, read_timeout_seconds=120) as client:
                return (await client.call_tool("budget", {})).structured_content

        assert asyncio.run(budget())["remaining"] == 2
    finally:
        serve.send_signal(signal.SIGINT)
        serve.wait(timeout=120)


def test_over_http_a_body_of_more_values_than_the_server_parses_is_refused_unparsed(tmp_path, servers):
    """The plain HTTP transport parsed each body whole (at most 1 MB): 32 concurrent bodies of [{},{},...] grew the
    server's peak by 437 MB. Such a body is now refused (400) before it is parsed: the peak grows by the bodies'
    bytes, and an honest request is answered as ever."""
    import socket

    from pipeline.serve.messages import MAX_MESSAGE_VALUES

    server = Server(tmp_path / "s.duckdb", "--game", "pong", "--budget", "2")
    servers.append(server)
    body = b'{"policy": "x", "instances": [' + b",".join([b"{}"] * 330_000) + b"]}"
    port = int(server.url.rsplit(":", 1)[1])
    request = f"POST /submit HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: {len(body)}\r\n\r\n".encode() + body
    before = _peak_rss_mb(server.proc.pid)
    held = [socket.create_connection(("127.0.0.1", port), timeout=60) for _ in range(32)]
    try:
        for connection in held:  # all but the last byte: the 32 bodies then arrive whole at once
            connection.sendall(request[:-1])
        time.sleep(1)
        for connection in held:
            connection.sendall(request[-1:])
        answers = []
        for connection in held:
            got = b""
            while b"\r\n\r\n" not in got or len(got.partition(b"\r\n\r\n")[2]) < int(
                    re.search(rb"Content-Length: (\d+)", got).group(1)):
                got += connection.recv(65536) or b"?" * 1000  # closed: what it sent is all there is
            answers.append(got.partition(b"\r\n\r\n"))
    finally:
        for connection in held:
            connection.close()
    grown = _peak_rss_mb(server.proc.pid) - before
    assert grown < 100, f"the server's peak grew by {grown:.0f} MB for 32 bodies of 1 MB"
    assert all(head.startswith(b"HTTP/1.1 400") and f"more than {MAX_MESSAGE_VALUES:,} values".encode() in rest
               for head, _, rest in answers), answers[0]
    assert server.post("budget")[1]["remaining"] == 2


def test_a_messages_values_are_counted_outside_its_strings_in_one_pass():
    """What the transports count before the SDK parses a message: its strings (each one value, however long or
    full of escapes) and the structure outside them. The count stops past its limit, so its work is at most a match
    a string up to the limit, whatever the message holds."""
    from pipeline.serve import messages
    from pipeline.serve.messages import MAX_MESSAGE_VALUES, json_values

    honest = _tool_call(1, "submit", {"policy": (ROOT / "games" / "scaffolds" / "pong.py").read_text() * 20,
                                      "instances": list(range(16))})
    assert json_values(honest) < 50
    assert json_values(b'{"a": "x,{[\\"],[{", "b": [1, 2, {}]}') == 9  # "a", "x,{[\\"],[{", "b"; outside: { , [ , , {
    shapes = {"dicts": b"[" + b"{}," * 1_000_000 + b"{}]", "strings": b"[" + b'"",' * 1_000_000 + b'""]',
              "quotes": b'"' * 3_000_000, "unterminated": b'"\\' * 1_500_000, "escapes": b'"' + b'\\"' * 1_500_000}
    matched = []

    original = messages._STRING_REST

    class Counting:
        def match(self, data, at):
            matched.append(at)
            return original.match(data, at)

    counted = {}
    for name, data in shapes.items():
        matched.clear()
        messages._STRING_REST = Counting()
        try:
            counted[name] = json_values(data)
        finally:
            messages._STRING_REST = original
        assert len(matched) <= MAX_MESSAGE_VALUES + 2, (name, len(matched))
    assert counted["dicts"] > MAX_MESSAGE_VALUES and counted["strings"] > MAX_MESSAGE_VALUES
    assert counted["quotes"] > MAX_MESSAGE_VALUES and counted["unterminated"] == counted["escapes"] == 0


def _cpu_s(pid: int) -> float:
    """The process's CPU time so far (user and system, all its threads), in seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_over_mcp_stdio_blank_lines_cost_the_server_nothing_and_the_call_after_them_is_answered(tmp_path):
    """Over stdio the SDK read the agent's lines one at a time (a worker thread's round trip each) and took each
    blank line for a message: ~300 us of server CPU a line of one byte, so 256 KiB of newlines took 82 s of CPU
    and 1 MiB 293 s, the call written after them answered only then. Blank lines (and the whitespace before a
    message) are now skipped as they arrive, in one match: 1 MiB of them takes ~0.01 s."""
    import select

    serve = _stdio_serve(tmp_path / "m.duckdb")
    try:
        before = _cpu_s(serve.pid)
        written = b"\n" * 2**20 + b" \r\n\t" * 2**14 + b"  " + _tool_call("after", "budget", {})

        def write() -> None:
            try:
                serve.stdin.write(written)
                serve.stdin.flush()
            except BrokenPipeError:  # the server was killed first (it had not answered)
                pass

        threading.Thread(target=write, daemon=True).start()
        ready, _, _ = select.select([serve.stdout.fileno()], [], [], 120)  # before: answered after ~6 min
        assert ready, "no answer after 120 s"
        answer = json.loads(serve.stdout.readline())
        spent = _cpu_s(serve.pid) - before
        assert answer["id"] == "after" and answer["result"]["structuredContent"]["remaining"] == 2, answer
        assert spent < 30, f"the server spent {spent:.1f} s of CPU on 1 MiB of blank lines"
    finally:
        serve.kill()
        serve.wait(timeout=60)


def test_over_mcp_stdio_the_agents_lines_are_read_as_the_sdks_text_stream_reads_them(tmp_path):
    """The lines are read in blocks (a line at a time, each line cost a worker thread's round trip): what each line
    says is what the SDK's own text stream made of it, universal newlines and UTF-8 (replaced where it is not)
    included, across the blocks' edges."""
    import io

    import anyio

    from pipeline.serve import tools

    data = "a\r\nb\rc\n\u00e9\u4e2d\U0001f600 \xff\r".encode("utf-8", "surrogateescape") + b"\xc3\n\r\rlast"
    data = data.replace(b"\xc3\xbf", b"\xff")  # a byte that is not UTF-8
    expected = io.TextIOWrapper(io.BytesIO(data), encoding="utf-8", errors="replace").readlines()

    async def lines(block: int) -> list[str]:
        read_end, write_end = os.pipe()
        os.write(write_end, data)
        os.close(write_end)
        reader = tools._Lines(read_end)
        reader.BLOCK = block
        return [line async for line in reader]

    for block in (1, 2, 3, 7, 65536):
        assert anyio.run(lines, block) == expected, block


def test_a_messages_long_numbers_are_found_outside_its_strings():
    """What the transports look for besides the values: a number (outside strings) longer than an honest message's
    ids and counts. Digits in a string are text; a float, an int, an exponent or a negative zero past
    MAX_NUMBER_CHARS characters is found, in one pass however the message is made."""
    from pipeline.serve.messages import MAX_NUMBER_CHARS, json_long_number

    honest = _tool_call(2**63, "feedback", {"submission": 12, "steps": 40, "x": -1.7976931348623157e+308})
    assert not json_long_number(honest)
    assert not json_long_number(b'{"query": "SELECT ' + b"7" * 4_000_000 + b'"}')
    assert not json_long_number(b"[" + b"7" * MAX_NUMBER_CHARS + b"]")
    for number in (b"0." + b"7" * 4_000_000, b"7" * 4_000_000, b"1e" + b"9" * MAX_NUMBER_CHARS,
                   b"-0." + b"0" * MAX_NUMBER_CHARS, b"7" * (MAX_NUMBER_CHARS + 1)):
        assert json_long_number(b'{"a": "x", "b": [1, ' + number + b"]}"), number[:20]


def test_over_every_transport_a_message_with_a_number_longer_than_an_honest_one_is_refused_unparsed(tmp_path,
                                                                                                    servers):
    """A 4 MiB number (a float of 4 million digits) was parsed by the SDK (over stdio and --mcp-port) or Python's
    JSON (plain HTTP) like any other value: fast for a float (~10 ms), but an int's parse grows faster than its
    digits (up to Python's 4,300: a 4 MiB message of them ~0.1 s). An honest message's numbers are ids and counts,
    so a message with a number past MAX_NUMBER_CHARS is refused before it is parsed, saying why, and the server
    answers the next request."""
    from pipeline.serve.http import MAX_BODY
    from pipeline.serve.messages import MAX_NUMBER_CHARS

    number = b"0." + b"7" * (4 * 2**20 - 200)
    serve = _stdio_serve(tmp_path / "m.duckdb")
    try:
        serve.stdin.write(b'{"jsonrpc": "2.0", "id": 1, "method": "tools/call", "params": {"name": "budget", '
                          b'"arguments": {"x": ' + number + b"}}}\n" + _tool_call(2, "budget", {}))
        serve.stdin.flush()
        refused, answered = _answers(serve, 2)
        assert refused["id"] is None and f"numbers of {MAX_NUMBER_CHARS} characters" in refused["error"]["message"]
        assert answered["id"] == 2 and answered["result"]["structuredContent"]["remaining"] == 2, answered
    finally:
        serve.stdin.close()
        serve.wait(timeout=60)

    (tmp_path / "p").mkdir()
    serve, url = _mcp_over_http(tmp_path / "p")
    try:
        headers = {"Content-Type": "application/json", "Accept": "application/json, text/event-stream"}
        opened = urllib.request.urlopen(urllib.request.Request(url, method="POST", headers=headers, data=json.dumps({
            "jsonrpc": "2.0", "id": 1, "method": "initialize", "params": {"protocolVersion": "2025-06-18",
            "capabilities": {}, "clientInfo": {"name": "t", "version": "1"}}}).encode()), timeout=60)
        session = {**headers, "Mcp-Session-Id": opened.headers["mcp-session-id"], "Mcp-Protocol-Version": "2025-06-18"}
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(urllib.request.Request(url, method="POST", headers=session, data=(
                b'{"jsonrpc": "2.0", "id": 2, "method": "tools/call", "params": {"name": "budget", "arguments": '
                b'{"x": ' + number + b"}}}")), timeout=60)
        assert refused.value.code == 400
        assert "number longer than the server parses" in json.loads(refused.value.read())["error"]["message"]
    finally:
        serve.send_signal(signal.SIGINT)
        serve.wait(timeout=120)

    server = Server(tmp_path / "s.duckdb", "--game", "pong", "--budget", "2")
    servers.append(server)
    status, answer = server.post("budget", b'{"x": ' + number[:MAX_BODY - 10] + b"}")
    assert status == 400 and f"a number of more than {MAX_NUMBER_CHARS} characters" in answer["error"], answer
    assert server.post("budget")[1]["remaining"] == 2


def test_over_mcp_stdio_pipelined_requests_wait_in_the_agents_pipe_not_in_the_server(tmp_path):
    """Over stdio the MCP SDK read on and started every request as it came: 2,000 refused submissions of 190 KB
    written at once, their answers unread, grew the server's peak by 317 MB. It now reads no more of stdin while
    MAX_PENDING_REQUESTS are unanswered, so the agent's writes wait in the pipe: the peak grows by ~15 MB, every
    request is answered once the agent reads, and the next call too."""
    serve = _stdio_serve(tmp_path / "m.duckdb")
    policy = "# " + "x" * 190_000 + "\n"
    calls, written = 2000, 0

    def write() -> None:
        nonlocal written
        for number in range(1, calls + 1):  # refused before its text is parsed: instance 99 is none
            serve.stdin.write(_tool_call(number, "submit", {"policy": policy, "instances": [99]}))
            written = number
        serve.stdin.flush()

    writer = threading.Thread(target=write, daemon=True)
    try:
        before = _peak_rss_mb(serve.pid)
        writer.start()
        seen, moved = 0, time.monotonic()
        while writer.is_alive() and time.monotonic() - moved < 1:  # until all is written, or it waits on the pipe
            time.sleep(0.1)
            if written != seen:
                seen, moved = written, time.monotonic()
        answers = [json.loads(serve.stdout.readline()) for _ in range(calls)]
        writer.join(timeout=60)
        grown = _peak_rss_mb(serve.pid) - before
        assert sorted(a["id"] for a in answers) == list(range(1, calls + 1))
        assert all(a["result"]["isError"] and "99 is not an instance" in a["result"]["content"][0]["text"]
                   for a in answers), answers[0]
        assert grown < 64, f"the server's peak grew by {grown:.0f} MB for {calls:,} pipelined submissions"
        serve.stdin.write(_tool_call(calls + 1, "budget", {}))
        serve.stdin.flush()
        assert json.loads(serve.stdout.readline())["result"]["structuredContent"]["remaining"] == 2
    finally:
        if writer.is_alive():  # a failure above: the writer may wait on the pipe for good
            serve.kill()
        try:
            serve.stdin.close()
        except BrokenPipeError:
            pass
        serve.wait(timeout=60)


@pytest.mark.parametrize("held_out, flagged", [
    ({"best": [-5.0, -5.0], "starter": [-5.0, -5.0]}, True),  # its training gain is gone on the held-out games
    ({"best": [-5.0, "forfeit"], "starter": [-5.0, -5.0]}, True),  # it forfeited a held-out game
    ({"best": [0.0, 0.0], "starter": [-5.0, -5.0]}, False),  # its gain holds up
    ({"best": [0.0, 0.0], "starter": [-5.0, "forfeit"]}, None),  # no reference: the starter forfeited held out
])  # returns relative to the best's training score
def test_finalize_flags_a_best_whose_training_gain_does_not_hold_up(tmp_path, monkeypatch, held_out, flagged):
    """A served run's starter never plays the training instances, so its training score is None, and the overfit
    rule (``store.scores.overfit``) was handed that None as the starter's tuning score: it claims no gain then, so
    finalize never flagged a run, not even a best that forfeited its held-out games. The starter's held-out score,
    under the same standard protocol as every training instance, is the reference now. The games are scripted
    here (``_play_scored``), relative to the submission's training score (what it played over 60 steps). A starter
    that forfeited its held-out games leaves no reference: None, as the audit says it (it was False, quietly)."""
    from pipeline.serve import finalize, protocol
    from pipeline.serve.config import ServeConfig
    from store.scores import score_episodes

    store = Store(tmp_path / "s.duckdb")
    run_id = protocol.create_run(store, ServeConfig(game="pong", budget=1, max_steps=60, validation_episodes=2,
                                                    heldout_episodes=2))
    served = protocol.ServeRun(store, run_id)
    answer = served.submit(instances=[0], policy=pong_policy("return 0"))
    tuning = answer["score"]
    assert tuning is not None, answer
    with store.read() as con:
        starter = protocol.get_run(con, run_id)["starter_version_id"]

    def scripted(store, specs, progress=None, stopping=None):
        out = {}
        for spec in specs:
            role = "starter" if spec.policy_version_id == starter else "best"
            returns = held_out[role] if spec.kind == "audit" else [0.0, 0.0]  # validation: as in training
            value = returns[spec.index]
            episode = {"return": tuning if value == "forfeit" else tuning + value, "length": 10,
                       "end_reason": "policy_error" if value == "forfeit" else "terminated"}
            out.setdefault(spec.policy_version_id, []).append((episode, spec.episode_id))
        return {v: (score_episodes(e for e, _ in eps), [i for _, i in eps]) for v, eps in out.items()}

    monkeypatch.setattr(finalize, "_play_scored", scripted)
    rows = finalize.finalize_run(store, run_id, served.record)
    best = next(r for r in rows if r["role"] == "best")
    assert best["tuning_score"] == tuning and best["overfit"] is flagged, rows


def test_a_submission_s_interval_names_its_level_method_and_n_or_why_there_is_none(tmp_path):
    """Every interval is printed with its level, method and n, and without one, why (``store.statistics``); the
    agent's answers gave a bare ``[low, high]``, and ``null`` with no reason for one game or all-equal returns."""
    from pipeline.serve import protocol
    from pipeline.serve.config import ServeConfig

    store = Store(tmp_path / "s.duckdb")
    run_id = protocol.create_run(store, ServeConfig(game="pong", budget=6, max_steps=400))
    served = protocol.ServeRun(store, run_id)
    policy = pong_policy("return random.choice([0, 2, 3])", prelude="import random\n")  # returns that vary
    one = served.submit(instances=[0], policy=policy)
    assert one["interval"].endswith("(n=1: too few for an interval)"), one
    many = served.submit(instances=[1, 2, 3, 4, 5], policy=policy)
    returns = [e["return"] for e in many["episodes"]]
    if min(returns) == max(returns):
        assert many["interval"].endswith("(n=5: all equal, no interval)"), many
    else:
        assert many["interval"].endswith("95% t, n=5") and many["low"] < many["score"] < many["high"], many
    again = served.feedback(2)
    assert again["interval"] == many["interval"], again


def test_a_request_whose_results_the_store_cannot_take_is_one_line_for_the_person_and_a_reason_for_the_agent(
        tmp_path, monkeypatch, capfd):
    """A submission played on a store whose disk had filled: the server printed a traceback of 20 lines on the
    person's terminal for the store's StoreError (which says the file and what to do in one line, as every command
    says it), and the agent read "the server failed on this request (StoreError)". Now the person reads the line,
    and the agent that nothing was kept because the server's store could not take it (not where the store is)."""
    from pipeline.serve import http
    from pipeline.serve.config import ServeConfig
    from pipeline.serve.protocol import ServeRun, create_run
    from store import StoreError

    store = Store(tmp_path / "s.duckdb")
    run = ServeRun(store, create_run(store, ServeConfig(game="pong", budget=2)))
    full = f"cannot write {tmp_path}/s.duckdb: the disk is full (No space left on device); free space and run the " \
           "command again: what was stored before is intact"

    def submit(**arguments):
        raise StoreError(full)

    monkeypatch.setattr(run, "submit", submit)
    server, thread = http.start_http(run)
    capfd.readouterr()
    try:
        request = urllib.request.Request(f"http://127.0.0.1:{server.server_address[1]}/submit", method="POST",
                                         data=b'{"instances": [0], "policy": "x"}',
                                         headers={"Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as failed:
            urllib.request.urlopen(request, timeout=30)
        answer = json.loads(failed.value.read())
    finally:
        server.shutdown()
        server.server_close()
    assert failed.value.code == 500 and "could not store" in answer["error"], answer
    assert str(tmp_path) not in answer["error"], "the agent is not told where the store is"
    said = capfd.readouterr().err
    assert said.splitlines() == [f"codearcade serve: error: {full}"], said


def test_a_finalized_run_s_best_is_its_best_by_validation_in_the_store_s_summary(tmp_path, monkeypatch, capsys):
    """Two submissions, the validation pool scripted (``_play_scored``) to prefer the one that is not the best by
    training score. The finalize played that one on the held-out pool and ``blame`` named it, but ``run_summary``
    (``runs``, ``report``, ``compare``) kept the best by training score: another version, with the audit of this one
    beside it. Now the run's summary names the version its finalize picked, with its validation score."""
    from pipeline.serve import finalize, protocol
    from pipeline.serve.config import ServeConfig
    from store.comparisons import resolve_version
    from store.scores import score_episodes

    store = Store(tmp_path / "s.duckdb")
    run_id = protocol.create_run(store, ServeConfig(game="pong", budget=2, max_steps=60, validation_episodes=2,
                                                    heldout_episodes=2))
    served = protocol.ServeRun(store, run_id)
    training = {}
    for action in (0, 1):
        answer = served.submit(instances=[0], policy=pong_policy(f"return {action}"))
        assert answer["score"] is not None, answer
        training[answer["submission"]] = answer["score"]
    (trained,) = store.query("SELECT best_version_id FROM iterations WHERE run_id = ? ORDER BY iteration DESC "
                             "LIMIT 1", [run_id])[0]  # the best by training score
    versions = dict(store.query("SELECT policy_version_id, iteration FROM candidates WHERE run_id = ? "
                                "AND iteration >= 1", [run_id]))
    (picked,) = [v for v in versions if v != trained]  # validation prefers the other one

    def scripted(store, specs, progress=None, stopping=None):
        out = {}
        for spec in specs:
            value = 5.0 if spec.policy_version_id == picked else -5.0
            out.setdefault(spec.policy_version_id, []).append(
                ({"return": value, "length": 10, "end_reason": "terminated"}, spec.episode_id))
        return {v: (score_episodes(e for e, _ in eps), [i for _, i in eps]) for v, eps in out.items()}

    monkeypatch.setattr(finalize, "_play_scored", scripted)
    rows = finalize.finalize_run(store, run_id, served.record)
    best = next(r for r in rows if r["role"] == "best")
    assert best["policy_version_id"] == picked
    with store.read() as con:
        assert resolve_version(con, run_id, "best") == picked
    assert main(["runs", "--json", "--store", str(store.path)]) == 0
    (listed,) = json.loads(capsys.readouterr().out)
    assert (listed["best_iteration"], listed["best_score"], listed["audit_iteration"]) == \
        (versions[picked], 5.0, versions[picked]), listed
    assert store.query("SELECT best_version_id, best_iteration, best_score, best_by, best_training_score "
                       "FROM run_summary WHERE run_id = ?", [run_id]) == \
        [(picked, versions[picked], 5.0, "validation", training[versions[picked]])]
