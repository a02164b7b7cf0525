"""The same escapes as tests/faults/test_boundary.py, delivered the other way policy code arrives: as an LLM
reply to `codearcade optimize` (a scripted model behind a real HTTP endpoint). The candidate runs in the
runtime check and, if accepted, in the episodes; either way, asserted by effect: no file, no process, no
connection, and the parent's key in no output, no store column and no request the model receives."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import pytest

from store import Store
from tests.conftest import json_reply
from tests.faults.test_boundary import ESCAPE, _store_text

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
CANARY = f"sk-canary-{uuid.uuid4().hex}"


def _method(body: str) -> str:
    return ("def select_action(self, predicted_ball_y, obs):\n"
            + textwrap.indent(textwrap.dedent(ESCAPE + body).strip("\n"), " " * 4) + "\n")


def _optimize(model, store: Store, tmp_path: Path):
    env = {**os.environ, "CODEARCADE_TEST_CANARY": CANARY, "OPENAI_API_KEY": CANARY,
           "LITELLM_LOCAL_MODEL_COST_MAP": "True", "CODEARCADE_LLM_BACKOFF_S": "0.05"}
    return subprocess.run([EXE, "optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                           "--iterations", "2", "--rollout-steps", "20", "--eval-max-steps", "50", "--workers", "1",
                           "--store", str(store.path), "--json"], cwd=tmp_path, capture_output=True, text=True,
                          env=env, timeout=600)


def _assert_no_leak(done, model, store: Store) -> None:
    assert done.returncode == 0, done.stderr
    assert CANARY not in done.stdout and CANARY not in done.stderr
    assert CANARY not in _store_text(store.path)
    assert CANARY not in json.dumps(model.raw_requests()), "the key reached a request sent to the model"
    assert json.loads(done.stdout)["status"] == "finished"


@pytest.mark.slow
def test_file_process_and_socket_attacks_as_replies_have_no_effect(store, scripted, tmp_path):
    sentinels = [Path("/tmp") / f"codearcade-reply-{uuid.uuid4().hex}-{i}" for i in range(4)]
    listener = socket.create_server(("127.0.0.1", 0))
    listener.setblocking(False)
    port = listener.getsockname()[1]
    attacks = [
        f"""
fd = os.open('{sentinels[0]}', os.O_WRONLY | os.O_CREAT, 0o644)
os.write(fd, b'x')
return 0
""",
        f"""
try:
    os.system('touch {sentinels[1]}')
except Exception:
    pass
try:
    os.posix_spawn('/bin/sh', ['sh', '-c', 'touch {sentinels[2]}'], dict(PATH='/bin:/usr/bin'))
except Exception:
    pass
try:
    import dataclasses
    dataclasses.builtins.open('{sentinels[3]}', 'w').write('x')
except Exception:
    pass
s = mods['socket'].create_connection(('127.0.0.1', {port}), timeout=2)
s.sendall(b'hello from the reply')
return 0
""",
    ]
    model = scripted([json_reply({"select_action": _method(a)}) for a in attacks])
    try:
        done = _optimize(model, store, tmp_path)
        _assert_no_leak(done, model, store)
        with pytest.raises(BlockingIOError):
            listener.accept()
    finally:
        listener.close()
    assert [p.exists() for p in sentinels] == [False] * 4
    statuses = [r[0] for r in store.query("SELECT update_status FROM iterations WHERE iteration > 0 ORDER BY 1")]
    assert statuses == ["rejected", "rejected"], "an attack that fails in its runtime check is rejected"
    for p in sentinels:
        p.unlink(missing_ok=True)


@pytest.mark.slow
def test_a_reply_that_reads_the_key_cannot_carry_it_into_the_next_prompt(store, scripted, tmp_path):
    steal = r"""
import dataclasses
found = [str(os.environ.get('OPENAI_API_KEY')), str(dict(os.environ)), '{0.__globals__}'.format(os.getenv)]
for pid in ('self', str(os.getppid())):
    try:
        found.append(dataclasses.builtins.open('/proc/' + pid + '/environ', 'rb').read().decode('latin-1'))
    except Exception as exc:
        found.append(repr(exc))
raise ValueError(' '.join(found)[:20000])
"""
    model = scripted([json_reply({"select_action": _method(steal)}), "No change."])
    done = _optimize(model, store, tmp_path)
    _assert_no_leak(done, model, store)
    # each rejected reply had its repair turn, whose prompt carries the exact error: the key is in none of them
    assert len(model.raw_requests()) == 4, "the repair prompts and the second prompt, carrying the feedback, were sent"
    assert "ValueError" in model.requests()[1][-1]["content"], "the reason reached the model (without the key)"
    feedback = store.query("SELECT text FROM feedback WHERE iteration = 1")[0][0]
    assert "not usable" in feedback, "the feedback is the repaired reply's: the last word on the update"
