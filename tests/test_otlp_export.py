"""`codearcade export RUN --otlp URL`: a stored run sent to a real OTLP receiver and read back from it.

The receiver is Arize Phoenix (`phoenix serve`, from .venv-phoenix: scripts/setup_phoenix.sh), started on
127.0.0.1 with a throwaway working directory; the spans are read back through its REST API and compared with
the store: the span tree, names, times and token counts. The run is a 2-iteration optimization against the
scripted model (an accepted update, then a rejected one), short rollouts. Without Phoenix the receiver tests
skip; the error tests need no receiver. (Phoenix binds its gRPC port on every interface, hard-coded in
phoenix/server/grpc_server.py; everything these tests send goes to 127.0.0.1.)
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from datetime import datetime, timezone
from pathlib import Path

import pytest

from pipeline.cli import main
from store import Store
from tests.conftest import COMPETENT_REPLY, ROOT, json_reply
from viewers.otlp_export import build_spans, span_id_for, trace_id_for

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
REJECTED_REPLY = json_reply(
    {"select_action": "def select_action(self, predicted_ball_y, obs):\n    return obs['Nope']\n"})


def _phoenix_executable() -> str | None:
    for candidate in (os.environ.get("CODEARCADE_PHOENIX"), str(ROOT / ".venv-phoenix" / "bin" / "phoenix"),
                      shutil.which("phoenix")):
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Phoenix:
    """A `phoenix serve` process on 127.0.0.1: OTLP/HTTP on ``http_url`` (which also serves the REST API) and
    OTLP/gRPC on ``grpc_url``."""

    def __init__(self, executable: str, workdir: Path):
        self.http_port, self.grpc_port = _free_port(), _free_port()
        self.http_url = f"http://127.0.0.1:{self.http_port}"
        self.grpc_url = f"http://127.0.0.1:{self.grpc_port}"
        self.log = open(workdir / "phoenix.log", "wb")
        env = {**os.environ, "PHOENIX_WORKING_DIR": str(workdir), "PHOENIX_HOST": "127.0.0.1",
               "PHOENIX_PORT": str(self.http_port), "PHOENIX_GRPC_PORT": str(self.grpc_port),
               "PHOENIX_TELEMETRY_ENABLED": "false"}
        self.process = subprocess.Popen([executable, "serve"], cwd=workdir, env=env, stdout=self.log,
                                        stderr=subprocess.STDOUT)

    def wait_ready(self, timeout_s: float = 180.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"phoenix serve exited with {self.process.returncode}; see {self.log.name}")
            try:
                with urllib.request.urlopen(self.http_url + "/healthz", timeout=2) as reply:
                    if reply.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                pass
            time.sleep(0.5)
        raise RuntimeError(f"phoenix serve did not answer within {timeout_s:.0f} s; see {self.log.name}")

    def spans(self, trace_id: str, project: str = "codearcade") -> list[dict]:
        """Every span Phoenix holds for ``trace_id`` (following its cursor)."""
        spans, cursor = [], None
        while True:
            query = f"trace_id={trace_id}&limit=500" + (f"&cursor={cursor}" if cursor else "")
            try:
                with urllib.request.urlopen(f"{self.http_url}/v1/projects/{project}/spans?{query}", timeout=10) as r:
                    page = json.load(r)
            except urllib.error.HTTPError as exc:
                if exc.code == 404:  # the project appears with its first span
                    return []
                raise
            spans += page["data"]
            cursor = page.get("next_cursor")
            if not cursor:
                return spans

    def wait_for_spans(self, trace_id: str, count: int, timeout_s: float = 60.0) -> list[dict]:
        """Phoenix inserts what it receives in batches: poll until ``count`` spans of the trace are there."""
        deadline = time.monotonic() + timeout_s
        while True:
            spans = self.spans(trace_id)
            if len(spans) >= count or time.monotonic() > deadline:
                return spans
            time.sleep(0.3)

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.log.close()


@pytest.fixture(scope="module")
def run_and_phoenix(tmp_path_factory):
    """(store, run id, Phoenix or None): Phoenix starts first and comes up while the run is made."""
    from tests.scripted_llm import ScriptedModel

    workdir = tmp_path_factory.mktemp("otlp")
    executable = _phoenix_executable()
    phoenix = Phoenix(executable, workdir) if executable else None
    try:
        store = Store(workdir / "run.duckdb", lock_timeout_s=20)
        model = ScriptedModel([COMPETENT_REPLY, REJECTED_REPLY], workdir / "model").start()
        try:
            done = subprocess.run([EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base",
                                   model.api_base, "--iterations", "2", "--eval-max-steps", "300",
                                   "--rollout-steps", "100", "--workers", "1", "--store", str(store.path), "--json",
                                   # iteration 2 is rejected: without the cache it plays its own episodes
                                   "--no-eval-cache"],
                                  cwd=ROOT, capture_output=True, text=True, timeout=600)
        finally:
            model.stop()
        assert done.returncode == 0, done.stderr
        run_id = json.loads(done.stdout)["run_id"]
        if phoenix is not None:
            phoenix.wait_ready()
        yield store, run_id, phoenix
    finally:
        if phoenix is not None:
            phoenix.stop()


@pytest.fixture
def phoenix(run_and_phoenix):
    if run_and_phoenix[2] is None:
        pytest.skip("Arize Phoenix (the real OTLP receiver) is not installed: run `bash scripts/setup_phoenix.sh` "
                    "(CI does), or point CODEARCADE_PHOENIX at a `phoenix` executable")
    return run_and_phoenix[2]


def _export(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["export", *args])
    out, err = capsys.readouterr()
    return code, out, err


def _utc_us(text: str) -> int:
    """Microseconds since the epoch of an ISO time Phoenix returns."""
    moment = datetime.fromisoformat(text)
    return round(moment.timestamp() * 1e6)


def _stored_us(moment: datetime) -> int:
    return round(moment.replace(tzinfo=timezone.utc).timestamp() * 1e6)


@pytest.mark.slow
def test_a_run_sent_to_phoenix_reads_back_with_its_tree_times_and_tokens(run_and_phoenix, phoenix, capsys):
    store, run_id, _ = run_and_phoenix
    code, out, err = _export(capsys, run_id[:10], "--otlp", phoenix.http_url, "--store", str(store.path), "--json")
    assert code == 0, err
    sent = json.loads(out)
    iterations = store.query("SELECT iteration, started_at, finished_at, score, update_status FROM iterations "
                             "WHERE run_id = ? ORDER BY iteration", [run_id])
    calls = store.query("SELECT call_id, iteration, input_tokens, output_tokens, created_at, latency_s FROM llm_calls "
                        "WHERE run_id = ? ORDER BY iteration, repair_turn", [run_id])
    episodes = store.query("SELECT episode_id, iteration, kind, return, length, end_reason FROM episodes "
                           "WHERE run_id = ?", [run_id])
    assert [i[4] for i in iterations] == ["initial", "accepted", "rejected"] and len(calls) == 3
    assert sent["trace_id"] == f"{trace_id_for(run_id):032x}"
    assert sent["spans_by_kind"] == {"run": 1, "iteration": 3, "llm_call": 3, "episode": len(episodes)}
    assert (sent["input_tokens"], sent["output_tokens"]) == (sum(c[2] for c in calls), sum(c[3] for c in calls))

    spans = phoenix.wait_for_spans(sent["trace_id"], sent["spans"])
    assert len(spans) == sent["spans"] == 1 + len(iterations) + len(calls) + len(episodes)
    by_id = {s["context"]["span_id"]: s for s in spans}

    # the tree: the run at the root, iterations under it, each iteration's LLM call and episodes under that
    root = next(s for s in spans if s["parent_id"] is None)
    assert root["name"] == "optimize pong" and root["attributes"]["codearcade.run.id"] == run_id
    assert root["attributes"]["codearcade.best_score"] == max(i[3] for i in iterations)
    assert root["context"]["span_id"] == f"{span_id_for(run_id, 'run'):016x}"
    under_root = [s for s in spans if s["parent_id"] == root["context"]["span_id"]]
    iteration_spans = {s["attributes"]["codearcade.iteration"]: s for s in under_root
                       if s["attributes"]["codearcade.span"] == "iteration"}
    # the held-out audit is played after the iterations: its episodes hang from the run, not from an iteration
    audits = [s for s in under_root if s["attributes"]["codearcade.span"] == "episode"]
    assert len(audits) == sum(e[2] == "audit" for e in episodes) > 0
    assert {s["attributes"]["codearcade.episode.kind"] for s in audits} == {"audit"}
    assert sorted(iteration_spans) == [0, 1, 2]
    for number, started, finished, score, status in iterations:
        span = iteration_spans[number]
        assert span["name"] == f"iteration {number}"
        assert span["attributes"]["codearcade.score"] == score
        assert span["attributes"]["codearcade.update_status"] == status
        # the stored times, not the export's
        assert _utc_us(span["start_time"]) == _stored_us(started)
        assert _utc_us(span["end_time"]) == _stored_us(finished)
    assert "KeyError" in iteration_spans[2]["attributes"]["codearcade.update_rejection"]
    assert any(e["name"] == "codearcade.feedback" and "Score" in e["attributes"]["codearcade.feedback.text"]
               for e in iteration_spans[1]["events"])

    # LLM calls: gen_ai names and attributes, token counts equal to the store's, under their iteration
    llm = {s["attributes"]["codearcade.llm.call_id"]: s for s in spans if s["attributes"].get("gen_ai.operation.name")}
    assert sorted(llm) == sorted(c[0] for c in calls)
    for call_id, iteration, input_tokens, output_tokens, created_at, latency_s in calls:
        span = llm[call_id]
        assert span["name"] == "chat openai/scripted"
        assert by_id[span["parent_id"]] is iteration_spans[iteration]
        attributes = span["attributes"]
        assert attributes["gen_ai.usage.input_tokens"] == input_tokens > 0
        assert attributes["gen_ai.usage.output_tokens"] == output_tokens > 0
        assert attributes["gen_ai.provider.name"] == attributes["gen_ai.system"] == "openai"
        assert attributes["gen_ai.request.model"] == "openai/scripted"
        assert attributes["gen_ai.response.finish_reasons"] == ["stop"]
        assert json.loads(attributes["gen_ai.input.messages"])[0]["role"] == "user"
        assert "#Instruction" in json.loads(attributes["gen_ai.input.messages"])[0]["parts"][0]["content"]
        assert "suggestion" in json.loads(attributes["gen_ai.output.messages"])[0]["parts"][0]["content"]
        # Phoenix understood the conventions: its own LLM span kind and token counts
        assert span["span_kind"] == "LLM" and attributes["llm.token_count.prompt"] == input_tokens
        assert _utc_us(span["end_time"]) == _stored_us(created_at)
        assert abs(_utc_us(span["end_time"]) - _utc_us(span["start_time"]) - latency_s * 1e6) <= 2
    # iteration 2's reply raised on the recorded observations: one repair turn, linked to the call it repairs
    first, repair = calls[1][0], calls[2][0]
    assert llm[repair]["attributes"]["codearcade.llm.purpose"] == "repair"
    assert llm[repair]["attributes"]["codearcade.llm.repair_of"] == first
    assert llm[repair]["attributes"]["codearcade.llm.repair_turn"] == 1
    assert "KeyError" in json.loads(llm[repair]["attributes"]["gen_ai.input.messages"])[-1]["parts"][0]["content"]

    # episodes: under their iteration, with return, length and end reason
    episode_spans = {s["attributes"]["codearcade.episode.id"]: s for s in spans
                     if "codearcade.episode.id" in s["attributes"]}
    assert len(episode_spans) == len(episodes)
    for episode_id, iteration, kind, return_, length, end_reason in episodes:
        span = episode_spans[episode_id]
        if kind == "audit":
            assert by_id[span["parent_id"]] is root and span["name"].startswith("audit episode ")
        else:
            assert by_id[span["parent_id"]] is iteration_spans[iteration]
            assert span["name"] == ("train rollout" if kind == "train" else "eval episode 0")
        assert (span["attributes"]["codearcade.episode.return"], span["attributes"]["codearcade.episode.length"],
                span["attributes"]["codearcade.episode.end_reason"]) == (return_, length, end_reason)


@pytest.mark.slow
def test_exporting_again_over_grpc_sends_the_same_spans(run_and_phoenix, phoenix, capsys):
    store, run_id, _ = run_and_phoenix
    trace_id = f"{trace_id_for(run_id):032x}"
    code, _, err = _export(capsys, run_id, "--otlp", phoenix.http_url, "--store", str(store.path))
    assert code == 0, err
    expected = len(build_spans(_rows(store, run_id)))
    before = phoenix.wait_for_spans(trace_id, expected)
    code, out, err = _export(capsys, run_id, "--otlp", phoenix.grpc_url, "--protocol", "grpc", "--store",
                             str(store.path))
    assert code == 0, err
    assert f"sent to {phoenix.grpc_url} (grpc); trace id {trace_id}" in out
    time.sleep(3)  # give Phoenix time to insert whatever it would add
    after = phoenix.spans(trace_id)
    assert len(before) == len(after) == expected, "same ids: Phoenix keeps one copy of each span"
    assert {s["context"]["span_id"] for s in after} == {s["context"]["span_id"] for s in before}


def _rows(store: Store, run_id: str) -> dict:
    from store.run_trace import run_trace_rows

    with store.read() as con:
        return run_trace_rows(con, run_id)


@pytest.mark.slow
def test_a_killed_run_still_exports_with_ends_from_its_children(run_and_phoenix, tmp_path):
    """A run killed inside its last iteration has no finished_at and no row for that iteration: the iteration
    still gets a span (its LLM call and episodes under it) ending at its last child, and so does the run."""
    store, run_id, _ = run_and_phoenix
    killed = Store(tmp_path / "killed.duckdb")
    shutil.copy(store.path, killed.path)
    with killed.write() as con:
        con.execute("DELETE FROM iterations WHERE run_id = ? AND iteration = 2", [run_id])
        con.execute("UPDATE runs SET finished_at = NULL, status = 'interrupted' WHERE run_id = ?", [run_id])
    spans = build_spans(_rows(killed, run_id))
    by_key = {s.context.span_id: s for s in spans}
    last = by_key[span_id_for(run_id, "iteration:2")]
    children = [s for s in spans if s.parent is not None and s.parent.span_id == last.context.span_id]
    assert {s.attributes["codearcade.span"] for s in children} == {"llm_call", "episode"}
    assert last.attributes["codearcade.iteration.complete"] is False
    assert last.start_time == min(s.start_time for s in children)
    assert last.end_time == max(s.end_time for s in children)
    root = by_key[span_id_for(run_id, "run")]
    assert root.end_time == max(s.end_time for s in spans) and not root.status.is_ok


@pytest.mark.slow
def test_errors_are_one_line(run_and_phoenix, capsys):
    store, run_id, _ = run_and_phoenix
    code, _, err = _export(capsys, "NOSUCHRUN", "--otlp", "http://127.0.0.1:4318", "--store", str(store.path))
    assert code == 2 and err.count("\n") == 1 and "no run NOSUCHRUN" in err and "codearcade runs" in err
    closed = f"http://127.0.0.1:{_free_port()}"
    code, _, err = _export(capsys, run_id, "--otlp", closed, "--store", str(store.path))
    assert code == 2 and err.count("\n") == 1
    assert f"cannot reach the OTLP receiver at {closed}" in err and "Connection refused" in err
    code, _, err = _export(capsys, run_id, "--otlp", "ftp://example", "--store", str(store.path))
    assert code == 2 and "not an http(s) URL" in err and err.count("\n") == 1


@pytest.mark.slow
def test_a_receiver_that_refuses_is_one_line(run_and_phoenix, phoenix, capsys):
    store, run_id, _ = run_and_phoenix
    code, _, err = _export(capsys, run_id, "--otlp", phoenix.http_url + "/not/otlp", "--store", str(store.path))
    assert code == 2 and err.count("\n") == 1, err
    assert f"{phoenix.http_url}/not/otlp/v1/traces did not take the spans" in err and "--protocol grpc" in err


@pytest.mark.slow
def test_an_eval_run_has_its_episodes_under_the_run(tmp_path):
    store = Store(tmp_path / "eval.duckdb")
    done = subprocess.run([EXE, "eval", str(ROOT / "tests" / "policies" / "pong_competent.py"), "--episodes", "2",
                           "--max-steps", "150", "--store", str(store.path), "--json"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    spans = build_spans(_rows(store, summary["run_id"]))
    root = next(s for s in spans if s.parent is None)
    episodes = sorted((s for s in spans if s is not root), key=lambda s: s.attributes["codearcade.episode.index"])
    assert root.name == "eval pong" and [s.name for s in episodes] == ["eval episode 0", "eval episode 1"]
    assert all(s.parent.span_id == root.context.span_id for s in episodes)
    returns = [e["return"] for e in summary["episodes"]]
    assert [s.attributes["codearcade.episode.return"] for s in episodes] == returns
    assert root.attributes["codearcade.run.mean_return"] == sum(returns) / 2
    assert root.start_time <= min(s.start_time for s in episodes) and root.end_time >= max(s.end_time for s in episodes)
