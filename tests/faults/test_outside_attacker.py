"""The boundary's second round: what an attacker who read docs/sandbox.md tried next, each tried both ways.

Every attack is the body of ``select_action``: once in a policy file given to ``codearcade eval`` (the test process
is the ``codearcade`` process), once as an LLM reply to ``optimize`` (a scripted model behind real HTTP: the
candidate is checked, then played). Each is asserted by its effect outside the policy process: a limit, priority
or CPU set of this process or of a bystander that must not change, a signal that must not arrive, a secret that
must not appear in any output, the store or a request to the model, memory that must not stay allocated, threads
that must not exist, an emulator that must not be found, files that must not be read, changed or planted.
"""

from __future__ import annotations

import ctypes
import json
import os
import resource
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from store import Store
from tests.conftest import ROOT, json_reply, pong_policy
from tests.faults.test_boundary import _store_text

PRELUDE = "import typing\n"
LEAK = "mods = typing.sys.modules\nos = mods['os']\nimport_module = mods['importlib'].import_module\n"


def _candidate(body: str) -> str:
    return "def select_action(self, predicted_ball_y, obs):\n    import typing\n" + "".join(
        f"    {line}\n" for line in (LEAK + body).splitlines())


def _eval(tmp_path: Path, body: str, *extra: str, steps: int = 40) -> tuple[int, dict, str, Store]:
    path = tmp_path / "attack.py"
    path.write_text(pong_policy(LEAK + body, prelude=PRELUDE))
    store = Store(tmp_path / "eval.duckdb")
    import io
    from contextlib import redirect_stderr, redirect_stdout

    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(["eval", str(path), "--max-steps", str(steps), "--store", str(store.path), "--json", *extra])
    return code, json.loads(out.getvalue()), out.getvalue() + err.getvalue(), store


def _optimize(tmp_path: Path, scripted, body: str, steps: int = 40, call_time_limit_s: float = 1.0):
    model = scripted([json_reply({"select_action": _candidate(body)})])
    store = Store(tmp_path / "optimize.duckdb")
    client = LiteLLMClient(model.model, api_base=model.api_base, retries=0)
    config = OptimizeConfig(game="pong", iterations=1, eval_max_steps=steps, rollout_steps=20, token_budget=8000,
                            workers=1, call_time_limit_s=call_time_limit_s)
    result = optimize(config, store, client)
    return result, store, model


PATHS = ["eval", pytest.param("optimize", marks=pytest.mark.slow)]  # the quick lane attacks through eval


def _run(path: str, tmp_path: Path, scripted, body: str, steps: int = 40,
         call_time_limit_s: float = 1.0) -> tuple[Store, str, list]:
    """Run the attack one way; the store, every text printed, and what the model was sent. ``call_time_limit_s``:
    for an attack whose one call does a lot (on a busy machine, more than the default second)."""
    if path == "eval":
        code, summary, printed, store = _eval(tmp_path, body, "--call-time-limit", str(call_time_limit_s),
                                              steps=steps)
        assert code in (0, 1), printed
        assert summary["episodes"], "the episode was stored"
        return store, printed, []
    result, store, model = _optimize(tmp_path, scripted, body, steps, call_time_limit_s)
    assert result.status == "finished", result.error
    played = store.query("SELECT count(*) FROM episodes WHERE iteration = 1")[0][0]
    statuses = store.query("SELECT update_status FROM iterations WHERE iteration = 1")
    assert played or statuses == [("rejected",)], "the candidate was played or rejected with a reason"
    return store, "", model.raw_requests()


@pytest.fixture
def bystander(tmp_path):
    """A process of the same user that writes a file on any catchable signal."""
    mark = tmp_path / "bystander-signalled"
    code = (f"import signal, time\n"
            f"def hit(n, f):\n    open({str(mark)!r}, 'a').write(str(n) + ' ')\n"
            f"for s in range(1, 32):\n    try:\n        signal.signal(s, hit)\n    except (OSError, ValueError):\n"
            f"        pass\ntime.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code])
    time.sleep(0.5)
    yield proc, mark
    proc.kill()
    proc.wait()


@pytest.mark.slow
@pytest.mark.parametrize("path", PATHS)
def test_calls_that_name_a_process_change_nothing_outside(path, tmp_path, scripted, bystander):
    proc, mark = bystander
    received: list[int] = []
    previous = {s: signal.signal(s, lambda n, f: received.append(n)) for s in (signal.SIGUSR1, signal.SIGUSR2)}
    before = (resource.getrlimit(resource.RLIMIT_CPU), os.getpriority(os.PRIO_PROCESS, 0),
              os.sched_getaffinity(0), resource.prlimit(proc.pid, resource.RLIMIT_CPU),
              os.getpriority(os.PRIO_PROCESS, proc.pid), os.sched_getaffinity(proc.pid))
    body = f"""
resource = import_module('resource')
me = os.getpid()
targets = [{os.getpid()}, {proc.pid}, 1, os.getppid()] + list(range(2, 400))
for pid in targets:
    if pid == me:
        continue
    for attack in (lambda p: resource.prlimit(p, resource.RLIMIT_CPU, (1, 1)),
                   lambda p: resource.prlimit(p, resource.RLIMIT_NOFILE, (3, 3)),
                   lambda p: os.setpriority(os.PRIO_PROCESS, p, 19),
                   lambda p: os.sched_setaffinity(p, {{0}}),
                   lambda p: os.kill(p, 10), lambda p: os.kill(p, 12)):
        try:
            attack(pid)
        except Exception:
            pass
for who in (os.PRIO_PGRP, os.PRIO_USER):
    try:
        os.setpriority(who, 0, 19)
    except Exception:
        pass
try:
    os.kill(0, 10)
    os.kill(-1, 10)
except Exception:
    pass
return 0
"""
    try:
        store, _, _ = _run(path, tmp_path, scripted, body)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    after = (resource.getrlimit(resource.RLIMIT_CPU), os.getpriority(os.PRIO_PROCESS, 0),
             os.sched_getaffinity(0), resource.prlimit(proc.pid, resource.RLIMIT_CPU),
             os.getpriority(os.PRIO_PROCESS, proc.pid), os.sched_getaffinity(proc.pid))
    assert after == before, "no limit, priority or CPU set of this process or a bystander changed"
    assert received == [] and not mark.exists(), "no signal reached this process or the bystander"
    assert proc.poll() is None
    ends = [r[0] for r in store.query("SELECT end_reason FROM episodes")]
    assert ends and "crashed" not in ends, ends


def test_the_filter_a_worker_fills_its_pid_into_is_the_one_assembled_for_that_pid():
    """The policy zygote assembles the seccomp filter once and each worker writes its own pid into it
    (``seccomp.seccomp_program``): byte for byte the program assembled for that pid, over a sweep of pids."""
    import random

    from pipeline.boundary import seccomp

    rng = random.Random(5)
    pids = [0, 1, 2, 255, 256, 65535, 65536, 2**22, 2**31 - 1] + [rng.randrange(1, 2**22) for _ in range(60)]
    for pid in pids:
        assert seccomp.seccomp_program(pid) == seccomp._filter(pid).assemble(), pid
    assert seccomp.seccomp_program(7) != seccomp.seccomp_program(8)


def test_a_policy_process_may_name_itself_by_its_pid_and_no_other(tmp_path):
    """By effect, in a real policy process: the calls that name a process pass for its own pid, as the filter
    it filled in says, and are refused for its zygote's (pid 1 of its namespace)."""
    body = """
resource = import_module('resource')
me = os.getpid()
seen = []
for pid in (me, 0, 1):
    for name, call in (('affinity', lambda p: os.sched_getaffinity(p)),
                       ('priority', lambda p: os.getpriority(os.PRIO_PROCESS, p)),
                       ('prlimit', lambda p: resource.prlimit(p, resource.RLIMIT_CPU))):
        try:
            call(pid)
            seen.append(name + (' self' if pid == me else ' ' + str(pid)) + ' passed')
        except OSError as exc:
            seen.append(name + (' self' if pid == me else ' ' + str(pid)) + ' errno ' + str(exc.errno))
raise ValueError('named: ' + ', '.join(seen))
"""
    code, summary, printed, store = _eval(tmp_path, body, steps=5)
    errors = [e for (e,) in store.query("SELECT error FROM episodes")]
    expected = ", ".join([f"{name} self passed" for name in ("affinity", "priority", "prlimit")]
                         + [f"{name} 0 passed" for name in ("affinity", "priority", "prlimit")]
                         + [f"{name} 1 errno 1" for name in ("affinity", "priority", "prlimit")])
    assert errors and all(f"named: {expected}" in (e or "") for e in errors), errors


def _shm(key: int, data: bytes | None = None, create: bool = True) -> int:
    """A System V segment of this process (ctypes), filled with ``data``."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.shmat.restype = ctypes.c_void_p
    shmid = libc.shmget(key, 4096, (0o1000 | 0o600) if create else 0)
    assert shmid >= 0, os.strerror(ctypes.get_errno())
    if data is not None:
        address = libc.shmat(shmid, None, 0)
        ctypes.memmove(address, data, len(data))
        libc.shmdt(ctypes.c_void_p(address))
    return shmid


SHM_READER = """
ctypes = import_module('ctypes')
libc = ctypes.CDLL(None)
libc.shmat.restype = ctypes.c_void_p
found = []
for shmid in list(range(0, 64)) + [KNOWN]:
    address = libc.shmat(shmid, None, 0o10000)
    if address not in (None, 2**64 - 1):
        found.append(ctypes.string_at(address, 64)[::-1].hex())
for key in (0x5eed, KEY):
    shmid = libc.shmget(key, 4096, 0o1000 | 0o600)
    if shmid >= 0:
        address = libc.shmat(shmid, None, 0)
        if address not in (None, 2**64 - 1):
            found.append(ctypes.string_at(address, 64)[::-1].hex())
            ctypes.memmove(address, b'EPISODE-MARK', 12)
raise ValueError('found ' + ' '.join(found))
"""


@pytest.mark.parametrize("path", PATHS)
def test_another_process_s_shared_memory_is_out_of_reach(path, tmp_path, scripted):
    secret = f"sk-shm-{uuid.uuid4().hex}".encode()
    key = 0x5eed0000 + os.getpid() % 0xffff
    shmid = _shm(key, secret)
    libc = ctypes.CDLL(None)
    try:
        body = SHM_READER.replace("KNOWN", str(shmid)).replace("KEY", str(key))
        store, printed, requests = _run(path, tmp_path, scripted, body)
        texts = [printed, _store_text(store.path), json.dumps(requests)]
        for shown in (secret, secret[::-1]):
            assert not any(shown.decode() in t or shown.hex() in t for t in texts), "the secret got out"
        address = ctypes.CDLL(None).shmat
        address.restype = ctypes.c_void_p
        view = address(shmid, None, 0)
        assert ctypes.string_at(view, len(secret)) == secret, "and it was not overwritten"
        libc.shmdt(ctypes.c_void_p(view))
    finally:
        libc.shmctl(shmid, 0, None)  # IPC_RMID


def test_a_fixed_key_segment_carries_nothing_from_one_episode_to_the_next(tmp_path):
    body = SHM_READER.replace("KNOWN", "0").replace("KEY", "0x5eed")
    code, summary, printed, store = _eval(tmp_path, body, "--episodes", "2", "--workers", "1", steps=5)
    errors = [e["error"] for e in summary["episodes"]]
    assert all(e.startswith("ValueError: found") for e in errors), errors
    mark = b"EPISODE-MARK"[::-1].hex()
    assert mark not in printed and mark not in _store_text(store.path)


def _shmem_kb() -> int:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("Shmem:"):
            return int(line.split()[1])
    return 0


@pytest.mark.slow
@pytest.mark.parametrize("path", PATHS)
def test_memory_outside_the_address_space_limit_is_refused(path, tmp_path, scripted):
    body = """
ctypes = import_module('ctypes')
mmap = import_module('mmap')
held = []
size = 512 * 2**20
try:
    fd = os.memfd_create('hold')
    os.ftruncate(fd, size)
    m = mmap.mmap(fd, size)
    m.write(b'x' * size)
    held.append(m)
except Exception:
    pass
libc = ctypes.CDLL(None)
for i in range(4):
    shmid = libc.shmget(0x6eed + i, size, 0o1000 | 0o600)
    if shmid >= 0:
        libc.shmat.restype = ctypes.c_void_p
        address = libc.shmat(shmid, None, 0)
        if address not in (None, 2**64 - 1):
            ctypes.memset(address, 1, size)
for name in ('/dev/shm/hold', 'hold'):
    try:
        with open(name, 'wb') as f:
            f.write(b'x' * size)
    except Exception:
        pass
return 0
""".replace("open(", "mods['builtins'].open(")
    before = _shmem_kb()
    _run(path, tmp_path, scripted, body, steps=3)
    time.sleep(0.5)
    assert _shmem_kb() - before < 96 * 1024, "no shared memory stays allocated after the run"


@pytest.mark.parametrize("path", PATHS)
def test_a_policy_process_starts_no_threads(path, tmp_path, scripted):
    body = """
start = import_module('_thread').start_new_thread
sleep = import_module('time').sleep
for _ in range(3000):
    try:
        start(sleep, (20,))
    except Exception:
        break
return 0
"""
    peak = [0]
    stop = threading.Event()

    def watch():
        while not stop.is_set():
            peak[0] = max(peak[0], int(Path("/proc/loadavg").read_text().split()[3].split("/")[1]))
            time.sleep(0.02)

    baseline = int(Path("/proc/loadavg").read_text().split()[3].split("/")[1])
    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        _run(path, tmp_path, scripted, body, steps=20)
    finally:
        stop.set()
        watcher.join()
    assert peak[0] - baseline < 200, f"the machine's task count rose by {peak[0] - baseline}"


@pytest.mark.parametrize("path", PATHS)
def test_a_policy_finds_no_emulator(path, tmp_path, scripted):
    rom = Path(__import__("ale_py").__file__).parent / "roms" / "pong.bin"
    assert rom.exists()
    body = f"""
found = []
if any(name.split('.')[0] in ('ale_py', 'gymnasium', 'ocatari') for name in mods):
    found.append('an emulator module is loaded')
for name in ('ale_py', 'gymnasium', 'ocatari', 'games.envs'):
    try:
        import_module(name)
        found.append('imported ' + name)
    except Exception:
        pass
try:
    for o in import_module('gc').get_objects():
        if hasattr(type(o), 'cloneState') or hasattr(type(o), 'getRAM'):
            found.append('a live emulator object')
            break
except Exception:
    pass
try:
    fd = os.open({str(rom)!r}, os.O_RDONLY)
    found.append('read the ROM: ' + str(len(os.read(fd, 4096))))
except Exception:
    pass
raise ValueError('emulator search: ' + (', '.join(f for f in found if f) or 'nothing found'))
"""
    # its one call walks every object and tries four imports: more than a second on a busy machine (it timed out)
    store, printed, _ = _run(path, tmp_path, scripted, body, call_time_limit_s=30)
    errors = [r[0] for r in store.query("SELECT error FROM episodes WHERE error IS NOT NULL")]
    reasons = [r[0] for r in store.query("SELECT reason FROM rejected_candidates")] if path == "optimize" else []
    recorded = errors + reasons
    assert recorded and all("emulator search: nothing found" in e for e in recorded if "emulator" in e), recorded
    assert any("emulator search: nothing found" in e for e in recorded), recorded


@pytest.mark.slow
@pytest.mark.parametrize("path", PATHS)
def test_a_rerun_directory_grants_the_policy_nothing(path, tmp_path, scripted):
    folder = tmp_path / "project"
    (folder / ".git" / "hooks").mkdir(parents=True)
    secret = f"sk-env-{uuid.uuid4().hex}"
    (folder / ".env").write_text(f"OPENAI_API_KEY={secret}\n")
    (folder / "other.duckdb").write_bytes(b"DUCK" * 1000)
    hook = folder / ".git" / "hooks" / "post-checkout"
    body = f"""
opened = mods['builtins'].open
found = []
for name in ('.env', 'other.duckdb'):
    try:
        found.append(opened({str(folder)!r} + '/' + name).read()[::-1])
    except Exception:
        pass
try:
    os.truncate({str(folder / 'other.duckdb')!r}, 0)
except Exception:
    pass
try:
    opened({str(hook)!r}, 'w').write('#!/bin/sh\\ntouch PWNED\\n')
except Exception:
    pass
raise ValueError(' '.join(found) or 'nothing read')
"""
    # as real commands: recording loads the Rerun SDK, which this test process must not (tests/test_rerun.py)
    exe = str(Path(sys.executable).parent / "codearcade")
    store = Store(tmp_path / f"{path}.duckdb")
    if path == "eval":
        policy = tmp_path / "attack.py"
        policy.write_text(pong_policy(LEAK + body, prelude=PRELUDE))
        command, requests = [exe, "eval", str(policy), "--max-steps", "40"], None
    else:
        model = scripted([json_reply({"select_action": _candidate(body)})])
        command = [exe, "optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                   "--iterations", "1", "--eval-max-steps", "40", "--rollout-steps", "20", "--token-budget", "8000",
                   "--workers", "1"]
    done = subprocess.run(command + ["--rerun", str(folder), "--store", str(store.path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode in (0, 1), done.stderr
    assert list(folder.glob("*.rrd")), "the host wrote the recordings"
    printed = done.stdout + done.stderr
    requests = model.raw_requests() if path == "optimize" else []
    texts = [printed, _store_text(store.path), json.dumps(requests)]
    assert not any(secret in t or secret[::-1] in t for t in texts), "the .env beside the recordings was read"
    assert (folder / "other.duckdb").read_bytes() == b"DUCK" * 1000, "the other store is intact"
    assert not hook.exists(), "no hook was planted"


@pytest.mark.parametrize("path", PATHS)
def test_the_user_s_files_cannot_even_be_stat_ed(path, tmp_path, scripted):
    """``stat()`` is outside Landlock's rules: only the policy process's minimal filesystem view keeps a file's
    existence, size and times from it. A file of a telling size and mtime, its folder, the store: not there for
    the policy (each stat fails). The user's home and the project folder exist in the view only as the empty
    folders its mounts hang from (the interpreter and the venv live below them): their real figures never show."""
    secret = tmp_path / "plans" / "secret.txt"
    secret.parent.mkdir()
    secret.write_bytes(b"x" * 48_611)
    os.utime(secret, (1_234_567_890, 1_234_567_890))
    hidden = [str(secret), str(secret.parent), str(tmp_path / f"{path}.duckdb")]
    above_mounts = [str(Path.home()), str(ROOT)]
    body = f"""
seen = []
for target in {hidden + above_mounts!r}:
    try:
        st = os.stat(target)
        seen.append(str(st.st_size) + '@' + str(int(st.st_mtime)))
    except OSError as exc:
        seen.append(type(exc).__name__)
raise ValueError('stat: ' + ' '.join(seen))
"""
    real = [f"{st.st_size}@{int(st.st_mtime)}" for st in map(os.stat, above_mounts)]
    store, printed, requests = _run(path, tmp_path, scripted, body)
    texts = [printed, _store_text(store.path), json.dumps(requests)]
    # The figures as the policy writes them (size@mtime): a bare "48611" also turns up by chance among the
    # store's durations and token counts (it did, once in CI), which says nothing of the sandbox.
    for figure in ("48611@", "@1234567890", *real):
        assert not any(figure in t for t in texts), f"{figure} got out"
    errors = [e for (e,) in store.query("SELECT error FROM episodes WHERE error IS NOT NULL")]
    reasons = [r for (r,) in store.query("SELECT reason FROM rejected_candidates")] if path == "optimize" else []
    nothing = "ValueError: stat: " + " ".join(["FileNotFoundError"] * len(hidden))
    assert any(nothing in e for e in errors + reasons), ("the attack ran, and found nothing", errors, reasons)


CHILD_SUBREAPER = 36


@pytest.mark.slow
def test_no_process_of_a_run_outlives_it(tmp_path):
    """kill -9 of ``codearcade`` while its policy process tries to outlive it: it cleared its parent-death signal
    and lowered its zygote's CPU limit, then ignores its timer and spins. Orphans of the run are reparented to a
    subreaper here, so whatever survives is seen."""
    policy = tmp_path / "linger.py"
    policy.write_text(pong_policy(LEAK + """
ctypes = import_module('ctypes')
ctypes.CDLL(None).prctl(1, 0, 0, 0, 0)
try:
    import_module('resource').prlimit(1, import_module('resource').RLIMIT_CPU, (1, 1))
except Exception:
    pass
mods['signal'].signal(14, mods['signal'].SIG_IGN)
while True:
    pass
""", prelude=PRELUDE))
    store = tmp_path / "linger.duckdb"
    script = f"""
import ctypes, os, subprocess, sys, time
ctypes.CDLL(None).prctl({CHILD_SUBREAPER}, 1, 0, 0, 0)
run = subprocess.Popen([{sys.executable!r}, "-m", "pipeline.cli", "eval", {str(policy)!r}, "--call-time-limit",
                        "300", "--episode-time-limit", "600", "--store", {str(store)!r}], cwd={str(ROOT)!r},
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
deadline = time.monotonic() + 120
def descendants():
    found, todo = [], [os.getpid()]
    while todo:
        pid = todo.pop()
        for task in os.listdir(f"/proc/{{pid}}/task") if os.path.exists(f"/proc/{{pid}}/task") else []:
            try:
                kids = open(f"/proc/{{pid}}/task/{{task}}/children").read().split()
            except OSError:
                kids = []
            found += [int(k) for k in kids]
            todo += [int(k) for k in kids]
    return found
while time.monotonic() < deadline and len(descendants()) < 5:  # codearcade, 2 zygotes x 2, host, policy
    time.sleep(0.2)
time.sleep(3)  # the policy process is spinning now
before = descendants()
run.kill()
run.wait()
deadline = time.monotonic() + 15
while descendants() and time.monotonic() < deadline:
    try:
        while os.waitpid(-1, os.WNOHANG)[0]:
            pass
    except ChildProcessError:
        pass
    time.sleep(0.1)
print(len(before), len(descendants()))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    before, after = map(int, done.stdout.split())
    assert before >= 5, f"the run had only {before} processes: it did not get as far as playing"
    assert after == 0, f"{after} process(es) of the run outlived it"


@pytest.mark.parametrize("path", PATHS)
def test_kernel_buffers_no_limit_counts_stay_small(path, tmp_path, scripted):
    """Socket pairs' buffers, raised with setsockopt and passed to the process itself in flight past its open-file
    limit, let one policy process hold 4.6 GB of kernel memory that its address-space limit does not count (the
    machine's MemAvailable fell by as much until the episode ended); a pipe's buffer grows to 1 MiB and more with
    fcntl(F_SETPIPE_SZ). The policy fills all it can and reports what the kernel took: socketpair, setsockopt and
    F_SETPIPE_SZ are refused, and what is left (pipes at their default 64 KiB, 256 descriptors) stays under 16 MiB."""
    body = """
so = mods['socket']
fcntl = import_module('fcntl')
held, queued, refused = [], 0, []
chunk = b'x' * 65536
for i in range(120):
    try:
        a, b = so.socketpair(so.AF_UNIX, so.SOCK_STREAM)
    except OSError as e:
        refused.append('socketpair')
        break
    held += [a, b]
    for s in (a, b):
        try:
            s.setsockopt(so.SOL_SOCKET, so.SO_SNDBUF, 4 * 2**20)
        except OSError:
            refused.append('setsockopt')
        s.setblocking(False)
        while True:
            try:
                queued += s.send(chunk)
            except OSError:
                break
for i in range(120):
    try:
        r, w = os.pipe()
    except OSError:
        break
    held += [r, w]
    try:
        fcntl.fcntl(w, 1031, 2**20)
    except OSError:
        refused.append('F_SETPIPE_SZ')
    os.set_blocking(w, False)
    while True:
        try:
            queued += os.write(w, chunk)
        except OSError:
            break
raise ValueError('QUEUED %d MiB, refused %s' % (queued >> 20, sorted(set(refused))))
"""
    store, printed, _ = _run(path, tmp_path, scripted, body, steps=3, call_time_limit_s=60.0)
    # a policy file's game, or an LLM's candidate's check (its confined worker, before it plays)
    errors = [e for (e,) in store.query("SELECT error FROM episodes WHERE error LIKE '%QUEUED%' UNION ALL "
                                        "SELECT reason FROM rejected_candidates WHERE reason LIKE '%QUEUED%'")]
    assert errors, printed[-2000:]
    queued = int(errors[0].split("QUEUED ", 1)[1].split(" MiB")[0])
    assert queued < 16, errors[0]
    assert "'F_SETPIPE_SZ'" in errors[0] and "'socketpair'" in errors[0], errors[0]


@pytest.mark.slow
@pytest.mark.parametrize("trace", [False, True], ids=["untraced", "traced"])
def test_a_policy_that_holds_back_its_end_holds_its_host_no_longer_than_its_episode(tmp_path, trace):
    """The end of an episode (the policy process's `done`, and its node rows) was waited for 30 s whatever the
    episode's time limit: a policy that held them back held its host 25 s an episode past a 3 s limit, or, holding
    both back, had the host killed and the steps it had played lost (stored as a timeout of length 0). The end is
    now waited for until the episode's limit (and a second's grace): the steps stand, and the episodes end in time."""
    body = """
pol = mods['pipeline.boundary.policy']
if not getattr(pol, '_patched', False):
    pol._patched = True
    send_json, write_all = pol.Channel.send_json, pol.Channel.write_all
    def slow_done(self, obj, within=None):
        if isinstance(obj, dict) and obj.get('kind') == 'done':
            mods['time'].sleep(29.0)
        return send_json(self, obj, within)
    def slow_rows(self, data, within=None):
        if data[:1] == b'A':
            mods['time'].sleep(29.0)
        return write_all(self, data, within)
    pol.Channel.send_json = slow_done
    pol.Channel.write_all = slow_rows
return 0
"""
    began = time.monotonic()
    code, summary, printed, store = _eval(tmp_path, body, "--episodes", "2", "--workers", "1",
                                          "--episode-time-limit", "3", *(["--trace"] if trace else []), steps=20)
    took = time.monotonic() - began
    ends = store.query("SELECT end_reason, length, duration_s FROM episodes ORDER BY episode_index")
    # a traced episode whose node rows are held back past its limit has no trace: the policy's forfeit, its
    # steps kept (it passed for traced with no rows); untraced, its steps are the host's and it played out
    reason = "timeout" if trace else "truncated"
    assert [(reason_, length) for reason_, length, _ in ends] == [(reason, 20)] * 2, (ends, printed[-2000:])
    if trace:
        assert all("trace missing" in error for (error,) in store.query("SELECT error FROM episodes")), printed
    assert all(duration < 3 + 3 for _, _, duration in ends), ends
    assert took < 2 * (3 + 3) + 20, took  # was ~56 s untraced (25 s an episode), ~70 s traced
