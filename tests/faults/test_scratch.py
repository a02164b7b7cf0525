"""The scratch and the frame's deadline (issue 38, "The scratch"): what a policy leaves behind or sends slowly costs
its own episode at most, never the zygote that other episodes depend on, never the host's time past its limits.

Each attack runs as a policy file through ``codearcade eval`` (this process is the ``codearcade`` process) or as an
LLM reply to an ``optimize`` best-of-n run, and is asserted by effect: the episodes after it (the same zygote) play
to their end; the files it could make; the kernel memory the machine's ``/proc/meminfo`` shows while they exist;
the seconds a trickled frame holds the host and the steps stored with its episode.
"""

from __future__ import annotations

import io
import json
import os
import re
import socket
import subprocess
import sys
import textwrap
import threading
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest

from pipeline.boundary import mounts
from pipeline.boundary.policy import Channel
from pipeline.cli import main
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from store import Store
from tests.conftest import json_reply
from tests.faults.test_outside_attacker import _candidate

DEPTH = 1_600
"""Levels of the deep directory: past the ~1,000 at which ``shutil.rmtree`` (recursive on Python 3.11) raises
RecursionError, within a worker's inode cap."""


def _policy(body: str) -> str:
    """A Pong policy file whose bundled method ``work`` (called every step, traced) has ``body``; it plays NOOP."""
    return textwrap.dedent("""
        import typing
        import tracing as trace

        GAME = "pong"

        @trace.model
        class Policy(trace.Module):
            def __call__(self, obs):
                self.work()
                return 0

            @trace.bundle(trainable=True)
            def work(self):
                mods = typing.sys.modules
                os = mods['os']
        """) + textwrap.indent(textwrap.dedent(body).strip("\n"), " " * 8) + "\n"


def _eval(tmp_path: Path, policy: str, *args: str) -> tuple[int, dict, Store, float]:
    path = tmp_path / "attack.py"
    path.write_text(policy)
    store = Store(tmp_path / "eval.duckdb")
    out, err = io.StringIO(), io.StringIO()
    t0 = time.monotonic()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(["eval", str(path), "--store", str(store.path), "--json", *args])
    wall = time.monotonic() - t0
    assert code in (0, 1), out.getvalue() + err.getvalue()
    return code, json.loads(out.getvalue()), store, wall


DIG = f"""
top = os.getcwd()
if os.path.exists('d'):
    return -1
depth = 0
for _ in range({DEPTH}):
    os.mkdir('d')
    os.chdir('d')
    depth += 1
os.chdir(top)
return depth
"""


@pytest.mark.slow
def test_a_deep_directory_in_the_scratch_leaves_the_next_episodes_unharmed(tmp_path):
    # every episode's policy process digs 1,600 levels deep, then plays on; all on one zygote (--workers 1). Before:
    # its cleanup (shutil.rmtree) raised RecursionError in the zygote, and 3-4 of the 5 episodes crashed
    _, summary, store, _ = _eval(tmp_path, _policy(DIG), "--episodes", "5", "--workers", "1", "--max-steps", "30",
                                 "--trace")
    ends = [(e["end_reason"], e["length"]) for e in summary["episodes"]]
    assert ends == [("truncated", 30)] * 5, summary["episodes"]
    dug = store.query("SELECT output FROM nodes WHERE step = 0 AND function = 'work' ORDER BY episode_id")
    assert [json.loads(o) for (o,) in dug] == [DEPTH] * 5, "each episode really made the deep directory"


@pytest.mark.slow
def test_a_candidate_s_deep_directory_leaves_the_other_candidates_unharmed(tmp_path, scripted):
    # best-of-n: one candidate digs (in its check and in each of its episodes), the others are honest. Before: the
    # zygote died, and the other candidates' checks and evaluations crashed with it
    dig = ("top = os.getcwd()\nif not os.path.exists('d'):\n"
           f"    for _ in range({DEPTH}):\n        os.mkdir('d')\n        os.chdir('d')\n    os.chdir(top)\nreturn 0")
    model = scripted([json_reply({"select_action": _candidate(dig)}),
                      json_reply({"select_action": _candidate("return 1")}),
                      json_reply({"select_action": _candidate("return 2 if obs else 3")})])
    store = Store(tmp_path / "optimize.duckdb")
    config = OptimizeConfig(game="pong", strategy="best-of-n", candidates=3, iterations=1, eval_max_steps=30,
                            eval_episodes=2, rollout_steps=10, workers=1, token_budget=8000, audit_episodes=0)
    result = optimize(config, store, LiteLLMClient(model.model, api_base=model.api_base, retries=0))
    assert result.status == "finished", result.error
    statuses = store.query("SELECT update_status FROM candidates WHERE iteration = 1")
    assert len(statuses) == 3 and ("rejected",) not in statuses, statuses
    ends = store.query("SELECT end_reason, length, count(*) FROM episodes WHERE iteration = 1 AND kind = 'eval' "
                       "GROUP BY ALL")
    assert ends == [("truncated", 30, 6)], ends


INODES = """
time = mods['time']
made, why = 0, 'none'
while made < 300_000:
    try:
        fd = os.open('f%d' % made, os.O_CREAT | os.O_WRONLY, 0o600)
    except OSError as exc:
        why = mods['errno'].errorcode.get(exc.errno, str(exc.errno))
        break
    os.close(fd)
    made += 1
st = os.statvfs('.')
time.sleep(1.0)  # the files exist while this sleeps: the test reads the machine's kernel memory meanwhile
raise ValueError('made %d files (%s); inodes %d' % (made, why, st.f_files))
"""


def _kernel_memory_kb() -> int:
    """The kernel's slab memory (where inodes and dentries live) of the whole machine, in kB."""
    with open("/proc/meminfo") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("Slab:"))


@pytest.mark.slow
def test_files_made_until_the_scratch_is_full_stop_at_its_inode_cap(tmp_path):
    # before: a tmpfs of 64 MiB without nr_inodes took all 300,000 empty files (~3.1M allowed) and the machine's
    # slab memory grew by ~400 MB, which no limit of the policy process counts
    before, peak, done = _kernel_memory_kb(), [0], threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], _kernel_memory_kb())
            time.sleep(0.02)

    sampler = threading.Thread(target=sample)
    sampler.start()
    try:
        _, summary, _, _ = _eval(tmp_path, _policy(INODES), "--max-steps", "5", "--call-time-limit", "20")
    finally:
        done.set()
        sampler.join()
    (episode,) = summary["episodes"]
    assert episode["end_reason"] == "policy_error", episode
    found = re.search(r"made (\d+) files \((\w+)\); inodes (\d+)", episode["error"])
    assert found, episode["error"]
    made, why, inodes = int(found[1]), found[2], int(found[3])
    grew_mb = (peak[0] - before) / 1024
    assert grew_mb < 64, f"the kernel's slab grew by {grew_mb:.0f} MB while the {made:,} files existed"
    assert made < 10_000 and why == "ENOSPC", episode["error"]
    assert made < inodes == mounts.SCRATCH_INODES, "the scratch's own tmpfs, full at its cap (df -i)"


TRICKLE = """
STEP.append(1)
if len(STEP) <= 10:
    return len(STEP)
signal, stat, time = mods['signal'], mods['stat'], mods['time']
signal.signal(signal.SIGALRM, signal.SIG_IGN)  # the policy process's own timer cannot stop it
fds = []
for n in range(64):  # the pipe its answers go over: the one FIFO it may write to
    try:
        if stat.S_ISFIFO(os.fstat(n).st_mode):
            os.write(n, b'')  # refused on the pipe it reads from
            fds.append(n)
    except OSError:
        pass
os.write(fds[0], b'a' + (30000).to_bytes(4, 'big'))  # an answer of 30,000 bytes, within the frame limit
while True:
    time.sleep(1.5)  # one byte at a time, each well within a read's limit
    os.write(fds[0], b'x')
"""


@pytest.mark.slow
@pytest.mark.parametrize("call_limit, episode_limit, within", [("1", "20", 2.0), ("0", "4", 4.0 + 1.0)])
def test_a_frame_trickled_byte_by_byte_times_out_at_the_call_limit_and_keeps_its_steps(
        tmp_path, call_limit, episode_limit, within):
    # before: each read had the call limit (+1 s) of its own; the host waited until the parent killed it (its
    # episode limit + 30 s: 34 s for a 1 s call limit) and the episode was stored with length 0, its steps lost
    policy = _policy(TRICKLE).replace('GAME = "pong"', 'GAME = "pong"\nSTEP = []')
    _, summary, store, wall = _eval(tmp_path, policy, "--max-steps", "100", "--call-time-limit", call_limit,
                                    "--episode-time-limit", episode_limit)
    (episode,) = summary["episodes"]
    assert episode["end_reason"] == "timeout" and episode["length"] == 10, episode
    assert "did not answer at this step" in episode["error"], episode["error"]
    duration, stored = store.query("SELECT duration_s, (SELECT count(*) FROM steps) FROM episodes")[0]
    assert stored in (10, 11), "the steps played before the time-out are stored (and the step it failed on)"
    assert duration < within + 4, f"the host held the call for {duration:.1f} s (limit {within:g} s)"
    assert wall < 30, wall


@pytest.mark.slow
def test_a_policy_that_never_finishes_loading_ends_at_the_episode_s_limit(tmp_path):
    """The host waited for a policy to load for 60 s whatever the episode's limit, so one that looped at import,
    its timer ignored, held a 15 s episode until the parent's kill (45.8 s). The load counts toward the episode's
    time, and is waited on no longer than its limit (+1 s): the episode ends `timeout`, saying so, at once."""
    policy = _policy("pass").replace('GAME = "pong"', 'GAME = "pong"\n'
                                     'signal = typing.sys.modules["signal"]\n'
                                     'signal.signal(signal.SIGALRM, signal.SIG_IGN)\n'
                                     'while True:\n    pass\n')
    _, summary, store, wall = _eval(tmp_path, policy, "--max-steps", "50", "--call-time-limit", "1",
                                    "--episode-time-limit", "4")
    (episode,) = summary["episodes"]
    assert episode["end_reason"] == "timeout" and "while loading the policy within 5 s" in episode["error"], episode
    assert wall < 25, f"the episode's limit is 4 s; the parent's kill would have come at 34 s: {wall:.1f} s"


def test_a_frame_has_one_deadline_not_one_per_read():
    host, policy = socket.socketpair()

    def trickle() -> None:
        try:
            policy.sendall(b"a" + (100).to_bytes(4, "big"))
            for _ in range(20):
                time.sleep(0.2)
                policy.sendall(b"x")
        except OSError:
            pass

    sender = threading.Thread(target=trickle)
    sender.start()
    try:
        channel = Channel(host)
        t0 = time.monotonic()
        with pytest.raises(TimeoutError):
            channel.receive(1000, within=0.7)
        assert 0.6 < time.monotonic() - t0 < 1.5
        policy.sendall(b"a" + (3).to_bytes(4, "big") + b"abc")  # a frame that comes whole is read as before
    finally:
        host.close()
        policy.close()
        sender.join()


def test_the_walk_that_cleans_a_weak_sandbox_s_scratch_has_no_depth_limit(tmp_path):
    # without a tmpfs of its own (a weak sandbox) a scratch is walked: without recursion, never raising
    top = tmp_path / "scratch"
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep").write_text("kept")
    here = os.getcwd()
    top.mkdir()
    os.chdir(top)
    try:
        for _ in range(1_200):
            os.mkdir("d")
            os.chdir("d")
            os.symlink(outside, "link")
            (Path("f")).write_text("x")
    finally:
        os.chdir(here)
    assert mounts.remove_tree(str(top)) and not top.exists()
    assert (outside / "keep").read_text() == "kept", "links are removed, never followed"
    assert mounts.remove_tree(str(tmp_path / "not-there"))


def _aged(path: Path, hours: float = 2.0) -> Path:
    old = time.time() - hours * 3600
    os.utime(path, (old, old))
    return path


def test_scratch_left_by_zygotes_killed_with_their_parent_is_swept_and_nothing_else(tmp_path):
    """A zygote removes its scratch when it ends; one killed with its parent (a whole process group at once) cannot.
    The next process's first zygote sweeps those: this user's, untouched for an hour, no process working in them;
    never one in use, a fresh one, a link, another name or another user's."""
    prefix = mounts.SCRATCH_PREFIX
    stale = []
    for i in range(3):
        folder = tmp_path / f"{prefix}dead{i}"
        (folder / "w7" / "d").mkdir(parents=True)
        (folder / "zygote.log").write_text("log")
        stale.append(_aged(folder))
    fresh = tmp_path / f"{prefix}fresh"
    fresh.mkdir()
    busy = tmp_path / f"{prefix}busy"
    (busy / "w3").mkdir(parents=True)
    _aged(busy)
    other_name = tmp_path / "someone-else-sandbox"
    other_name.mkdir()
    _aged(other_name)
    target = tmp_path / "kept"
    target.mkdir()
    (target / "file").write_text("kept")
    link = tmp_path / f"{prefix}link"
    link.symlink_to(target)
    theirs = [tmp_path / f"{prefix}theirs"] if os.getuid() == 0 else []  # root can make another user's
    for folder in theirs:
        folder.mkdir()
        os.chown(folder, 65534, 65534)
        _aged(folder)
    worker = subprocess.Popen(["sleep", "60"], cwd=busy / "w3")  # a worker of a live zygote works below it
    try:
        # the first zygote of a process sweeps; its own scratch is made, then removed at its end
        code = subprocess.run([sys.executable, "-c", "from pipeline.boundary.zygotes import zygote; zygote('policy')"],
                              cwd=Path(__file__).resolve().parents[2], env={**os.environ, "TMPDIR": str(tmp_path)},
                              timeout=120).returncode
        assert code == 0
        assert not any(folder.exists() for folder in stale)
        assert busy.exists() and fresh.exists() and other_name.exists() and link.is_symlink()
        assert (target / "file").read_text() == "kept", "a link is never followed"
        assert all(folder.exists() for folder in theirs)
        left = sorted(p.name for p in tmp_path.iterdir())  # the zygote's own scratch is gone with it
        assert left == sorted([busy.name, fresh.name, other_name.name, link.name, target.name]
                              + [folder.name for folder in theirs]), left
    finally:
        worker.kill()
        worker.wait()
    assert mounts.sweep_stale_scratch(str(tmp_path)) == [str(busy)], "once no process works there, it goes too"
