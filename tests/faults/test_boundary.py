"""The operating-system boundary, asserted by effect: policy files that escape the in-process sandbox (through
leaks it cannot close: ``typing.sys``, ``dataclasses.builtins``, ``operator.attrgetter`` on frames,
``str.format`` on ``__globals__``) and then try to write a file, start a process, connect to a socket, read the
parent's secrets, forge the CLI's output, keep state for the next episode, or get the parent to unpickle a
payload. Each is evaluated with ``codearcade eval``; each attack works against the previous design (workers
forked from the parent, an audit hook, pickles over a pipe) and must have no effect now.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.play.validate import CandidateRejected, build_candidate
from store import Store
from tests.conftest import EXAMPLES, ROOT, pong_policy
from tracing.policy_file import PolicyLoadError, inspect_policy

CANARY = f"sk-canary-{uuid.uuid4().hex}"

# Turns off the audit hook of the previous design (module globals of pipeline.boundary.workers, reachable through
# typing.sys.modules); harmless now.
ESCAPE = """
import typing
mods = typing.sys.modules
ex = mods.get('pipeline.boundary.workers')
if ex is not None:
    ex._DENIED_EVENTS = ('no-such-event',)
    ex._WRITE_FLAGS = 0
os = mods['os']
"""

SPAWN = """
try:
    os.system('touch {system}')
except Exception:
    pass
try:
    os.posix_spawn('/bin/sh', ['sh', '-c', 'touch {spawn}'], dict(PATH='/bin:/usr/bin'))
except Exception:
    pass
try:
    if os.fork() == 0:
        fd = os.open('{fork}', os.O_WRONLY | os.O_CREAT, 0o644)
        os._exit(0)
except Exception:
    pass
"""
"""After :data:`ESCAPE`: start a process three ways (``system``, ``posix_spawn``, ``fork``), each of which would
create its sentinel file (``.format(system=..., spawn=..., fork=...)``); the policy goes on when each is refused."""


@pytest.fixture
def sentinel():
    paths = [Path("/tmp") / f"codearcade-boundary-{uuid.uuid4().hex}-{i}" for i in range(3)]
    yield paths
    for p in paths:
        p.unlink(missing_ok=True)


def _eval(capsys, path, store, *extra):
    code = main(["eval", str(path), "--max-steps", "2", "--call-time-limit", "2", "--store", str(store.path), "--json",
                 *map(str, extra)])
    out, err = capsys.readouterr()
    return code, out, err


def _cli(path, store, env=None, *extra):
    """``codearcade eval`` in a process of its own (its own stdout, its own environment)."""
    return subprocess.run([sys.executable, "-m", "pipeline.cli", "eval", str(path), "--max-steps", "2", "--store",
                           str(store.path), "--json", *map(str, extra)], cwd=ROOT, capture_output=True, text=True,
                          env=env, timeout=300)


@pytest.mark.slow
def test_a_file_written_outside_scratch_does_not_appear(store, write_policy, sentinel, capsys):
    a, b, _ = sentinel
    path = write_policy(pong_policy(ESCAPE + f"""
try:
    fd = os.open('{a}', os.O_WRONLY | os.O_CREAT, 0o644)
    os.write(fd, b'x')
    os.close(fd)
finally:
    import dataclasses
    dataclasses.builtins.open('{b}', 'w').write('x')
return 0
"""))
    code, out, err = _eval(capsys, path, store)
    assert code in (0, 1), err
    assert json.loads(out)["episodes"][0]["end_reason"] == "policy_error"
    assert not a.exists() and not b.exists()


@pytest.mark.slow
def test_a_process_spawned_does_not_run(store, write_policy, sentinel, capsys):
    a, b, c = sentinel
    path = write_policy(pong_policy(ESCAPE + SPAWN.format(system=a, spawn=b, fork=c) + """
mods['time'].sleep(0.5)
return 0
"""))
    code, out, err = _eval(capsys, path, store)
    assert code in (0, 1), err
    assert [p.exists() for p in sentinel] == [False, False, False]


def test_a_socket_connect_reaches_nothing(store, write_policy, capsys):
    listener = socket.create_server(("127.0.0.1", 0))
    listener.setblocking(False)
    port = listener.getsockname()[1]
    path = write_policy(pong_policy(ESCAPE + f"""
s = mods['socket'].create_connection(('127.0.0.1', {port}), timeout=2)
s.sendall(b'hello from the policy')
s.close()
return 0
"""))
    try:
        code, out, err = _eval(capsys, path, store)
        assert code in (0, 1), err
        with pytest.raises(BlockingIOError):
            listener.accept()
    finally:
        listener.close()


def _store_text(path: Path) -> str:
    store = Store(path)
    tables = [t for (t,) in store.query("SELECT table_name FROM information_schema.tables")]
    return "\n".join(repr(store.query(f'SELECT * FROM "{t}"')) for t in tables)


@pytest.mark.slow
def test_the_parents_secrets_are_out_of_reach(tmp_path, write_policy):
    path = write_policy(pong_policy(ESCAPE + r"""
import dataclasses
import numpy as np
found = [str(os.environ.get('CODEARCADE_TEST_CANARY')), str(dict(os.environ))]
found.append('{0.__globals__}'.format(os.getenv))
pids = ['self', str(os.getppid())]
try:
    status = dataclasses.builtins.open('/proc/' + pids[1] + '/status').read()
    pids.append(status.split('PPid:')[1].split()[0])
except Exception as exc:
    found.append(repr(exc))
for pid in pids:
    try:
        found.append(dataclasses.builtins.open('/proc/' + pid + '/environ', 'rb').read().decode('latin-1'))
    except Exception as exc:
        found.append(repr(exc))
    try:
        found.append(str(np.fromregex('/proc/' + pid + '/environ', r'(.+)', [('v', 'S65536')])))
    except Exception as exc:
        found.append(repr(exc))
text = ' '.join(found)
print(text, flush=True)
print(text, file=mods['sys'].stderr, flush=True)
raise ValueError(text[-20000:] + text[:20000])
"""))
    store = Store(tmp_path / "canary.duckdb")
    env = {**os.environ, "CODEARCADE_TEST_CANARY": CANARY, "OPENAI_API_KEY": CANARY}
    done = _cli(path, store, env)
    assert CANARY not in done.stdout and CANARY not in done.stderr
    assert CANARY not in _store_text(store.path)
    assert done.returncode == 1, done.stderr
    episode = json.loads(done.stdout)["episodes"][0]
    assert episode["end_reason"] == "policy_error" and episode["error"]


@pytest.mark.slow
def test_a_policys_output_cannot_forge_the_json(tmp_path, write_policy):
    path = write_policy(pong_policy(ESCAPE + """
print('{"run_id": "FORGED-PRINT", "episodes": []}', flush=True)
mods['sys'].stdout.write('FORGED-STDOUT\\n')
mods['sys'].stdout.flush()
os.write(1, b'FORGED-FD1\\n')
os.write(2, b'FORGED-FD2\\n')
return 0
"""))
    done = _cli(path, Store(tmp_path / "forge.duckdb"))
    assert done.returncode == 0, done.stderr
    assert "FORGED" not in done.stdout and "FORGED" not in done.stderr
    assert [e["length"] for e in json.loads(done.stdout)["episodes"]] == [2]


def test_module_state_does_not_leak_into_the_next_episode(store, write_policy, capsys):
    # np.typecodes is a plain dict inside numpy: a policy can change it; the next episode must not see that
    path = write_policy(pong_policy("return 7 if LEAKED else 0", prelude="""
        import numpy as np
        LEAKED = 'codearcade_leak' in np.typecodes
        np.typecodes['codearcade_leak'] = 'x'
    """))
    code, out, err = _eval(capsys, path, store, "--episodes", 2, "--workers", 1)
    assert code == 0, (out, err)
    assert [e["length"] for e in json.loads(out)["episodes"]] == [2, 2]


def test_a_pickle_sent_up_the_pipe_never_runs_in_the_parent(store, write_policy, sentinel, capsys):
    a = sentinel[0]
    path = write_policy(pong_policy(ESCAPE + f"""
import operator
class Evil:
    def __reduce__(self):
        return (os.system, ('touch {a}',))
f = mods['sys']._getframe(0)
while f is not None:
    for name, value in list(operator.attrgetter('f_locals')(f).items()):
        try:
            if hasattr(value, 'send') and hasattr(value, 'recv'):  # a multiprocessing Connection
                value.send(('progress', Evil()))
            elif name == 'fd' and type(value) is int and 'pickle' in mods:  # a raw answer channel
                os.write(value, mods['pickle'].dumps(('progress', Evil())))
        except Exception:
            pass
    f = operator.attrgetter('f_back')(f)
return 0
"""))
    code, out, err = _eval(capsys, path, store)
    assert code in (0, 1), err
    assert json.loads(out)["episodes"][0]["end_reason"] in ("crashed", "truncated")
    assert not a.exists(), "the payload ran in the parent"


def test_a_forged_answer_is_refused(store, write_policy, capsys):
    # the policy process's only way out is its socket to the game host: a forged result written there is read
    # as what it is, a malformed answer, and the score stays the host's
    path = write_policy(pong_policy(ESCAPE + """
row = dict(episode_id='forged', game='pong', started_at=None, duration_s=1.0, env_s=0.0, policy_s=0.0,
           length=0, lives_lost=0, end_reason='truncated', error=None)
row['return'] = 1e9
data = mods['json'].dumps(dict(kind='result', episode=row, nodes=False)).encode()
for fd in range(3, 64):
    try:
        os.write(fd, b'J' + len(data).to_bytes(4, 'big') + data)
    except Exception:
        pass
return 0
"""))
    code, out, err = _eval(capsys, path, store)
    assert code == 1, (out, err)
    episode = json.loads(out)["episodes"][0]
    assert episode["end_reason"] == "crashed" and "malformed" in episode["error"], episode
    assert episode["return"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("body", [
    "import typing\nsig = typing.sys.modules['signal']\nsig.signal(sig.SIGALRM, sig.SIG_IGN)\nwhile True:\n    pass",
    "class Loud(Exception):\n    def __str__(self):\n        while True:\n            pass\nraise Loud()",
], ids=["SIGALRM ignored", "__str__ loops"])
def test_a_policy_that_defeats_its_timer_is_killed_and_the_run_goes_on(body, store, write_policy, capsys,
                                                                      monkeypatch):
    from pipeline.boundary import workers

    monkeypatch.setattr(workers, "KILL_GRACE_S", 1.0)
    path = write_policy(pong_policy(body))
    code, out, err = _eval(capsys, path, store, "--episodes", 2, "--episode-time-limit", 2, "--call-time-limit", 0.3)
    assert code == 1, (out, err)
    episodes = json.loads(out)["episodes"]
    assert [e["end_reason"] for e in episodes] == ["timeout", "timeout"], episodes


HUGE = "return " + " + ".join(["1"] * 100_000)
NESTED = "return " + "[" * 5000 + "]" * 5000


@pytest.mark.parametrize("body", [HUGE, NESTED], ids=["200 KB expression", "deep nesting"])
def test_code_that_breaks_the_parser_is_refused_in_one_line(body, store, write_policy, capsys):
    path = write_policy(pong_policy(body))
    code, out, err = _eval(capsys, path, store)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    info = inspect_policy((EXAMPLES / "pong.py").read_text(), "pong.py")
    source = "def select_action(self, predicted_ball_y, obs):\n    " + body + "\n"
    with pytest.raises(CandidateRejected) as rejected:
        build_candidate(info, {"select_action": source})
    assert str(rejected.value)
    with pytest.raises(PolicyLoadError):  # and a parse in this process, where one happens, says why
        inspect_policy(pong_policy(body), "deep.py")


DEEP_METRICS = "return " + "-" * 400 + "1"  # parses, then exhausts the recursion limit in radon's metrics
PARSER_MEMORY = "return " + "-" * 100_000 + "1"  # 100 KB that CPython's parser turns into gigabytes (OOM-killed)
SAFETY_NET_AS = 8 * 2**30
"""Address space the CLI under test may take: should a regression parse untrusted text in the parent again,
the test fails with a MemoryError there instead of the machine's OOM killer ending whatever runs beside it."""


def _cli_limited(verb: str, path: Path, store: Store, *extra: str) -> subprocess.CompletedProcess:
    import resource

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (SAFETY_NET_AS, resource.getrlimit(resource.RLIMIT_AS)[1]))

    return subprocess.run([sys.executable, "-m", "pipeline.cli", verb, str(path), "--store", str(store.path), *extra],
                          cwd=ROOT, capture_output=True, text=True, timeout=300, preexec_fn=limit)


@pytest.mark.slow
@pytest.mark.parametrize("verb, body", [
    ("eval", DEEP_METRICS), ("eval", PARSER_MEMORY), ("optimize", DEEP_METRICS), ("optimize", PARSER_MEMORY),
], ids=["eval: deep for radon", "eval: parser memory", "optimize: deep for radon", "optimize: parser memory"])
def test_a_policy_file_too_deep_for_the_checks_is_refused_in_one_line(verb, body, store, write_policy):
    path = write_policy(pong_policy(body), "deep.py")
    extra = ("--max-steps", "5") if verb == "eval" else ("--dry-run", "--iterations", "1", "--workers", "1")
    done = _cli_limited(verb, path, store, *extra)
    assert done.returncode == 2, done.stderr[-2000:]
    assert len(done.stderr.strip().splitlines()) == 1 and "deep.py: the code cannot be checked" in done.stderr, \
        done.stderr[-2000:]
    assert not store.exists() or store.query("SELECT count(*) FROM runs") == [(0,)], "nothing was stored"


@pytest.fixture
def kernel_lacks_landlock(monkeypatch):
    """The zygote's hello says Landlock is missing (as on a kernel without it); a fresh zygote is started."""
    from pipeline.boundary import zygotes

    original = zygotes.Zygote._recv

    def recv(self, timeout):
        msg = original(self, timeout)
        if msg is not None and msg.get("kind") == "hello" and self.role == "policy":
            msg["missing"] = ["landlock (Landlock is not enabled in this kernel)"]
        return msg

    monkeypatch.setattr(zygotes.Zygote, "_recv", recv)
    zygotes.stop_zygote()
    yield
    zygotes.stop_zygote()


def test_a_missing_kernel_feature_is_refused_loudly(kernel_lacks_landlock, store, capsys, monkeypatch):
    monkeypatch.delenv("CODEARCADE_ALLOW_WEAK_SANDBOX", raising=False)
    code = main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "5", "--store", str(store.path)])
    out, err = capsys.readouterr()
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "landlock" in err and "CODEARCADE_ALLOW_WEAK_SANDBOX=1" in err
    assert not store.exists() or store.query("SELECT count(*) FROM episodes") == [(0,)], "nothing ran"


@pytest.mark.slow
def test_the_weak_sandbox_is_an_explicit_choice_warned_about(kernel_lacks_landlock, store, capsys, monkeypatch):
    monkeypatch.setenv("CODEARCADE_ALLOW_WEAK_SANDBOX", "1")
    code = main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "5", "--store", str(store.path)])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "WARNING: weak sandbox" in err and "landlock" in err


@pytest.mark.slow
def test_the_store_cannot_be_read_or_truncated(store, write_policy, capsys):
    assert main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "30", "--store", str(store.path)]) == 0
    capsys.readouterr()
    path = write_policy(pong_policy(ESCAPE + f"""
import dataclasses
seen = []
try:
    seen.append(repr(dataclasses.builtins.open('{store.path}', 'rb').read(64)))
except Exception as exc:
    seen.append(repr(exc))
try:
    os.truncate('{store.path}', 0)
except Exception as exc:
    seen.append(repr(exc))
raise ValueError(' '.join(seen))
"""))
    code, out, err = _eval(capsys, path, store)
    assert code == 1, err
    error = json.loads(out)["episodes"][0]["error"]
    # refused (Landlock) or not there at all (the policy process's minimal filesystem view)
    assert "DUCK" not in error and error.count("PermissionError") + error.count("FileNotFoundError") == 2, error
    assert store.query("SELECT count(*) FROM steps")[0][0] == 30 + 1, "earlier rows intact, the failing step added"


@pytest.mark.slow
def test_no_signal_reaches_the_parent(store, write_policy, capsys):
    import signal as signals

    received = []
    previous = signals.signal(signals.SIGUSR1, lambda *a: received.append(a))
    path = write_policy(pong_policy(ESCAPE + f"""
for target in ({os.getpid()}, os.getppid()):
    try:
        os.kill(target, mods['signal'].SIGUSR1)
    except Exception:
        pass
return 0
"""))
    try:
        code, out, err = _eval(capsys, path, store)
    finally:
        signals.signal(signals.SIGUSR1, previous)
    assert code in (0, 1), err
    assert received == [], "the policy signalled this process"
