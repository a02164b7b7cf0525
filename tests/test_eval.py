"""`codearcade eval` end to end: real ALE, real worker processes, a real DuckDB file."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
from datetime import timezone
from pathlib import Path

import pytest

from games import GAMES, get_game
from pipeline.cli import main
from pipeline.play.episodes import run_episodes
from pipeline.play.spec import EpisodeSpec
from tests.conftest import EXAMPLES, POLICIES, ROOT, pong_policy, random_policy, run_main, said

BUNDLED_CALLS_PER_STEP = {"pong": 2, "breakout": 3, "space_invaders": 3}


@pytest.mark.parametrize("game", ["pong", "breakout", "space_invaders"])
def test_examples_evaluate_end_to_end_with_trace(game, store):
    code, out, err = run_main("eval", EXAMPLES / f"{game}.py", "--trace", "--max-steps", 600,
                              "--store", store.path, "--json")
    assert code == 0, err
    summary = json.loads(out)
    episode = summary["episodes"][0]
    assert episode["end_reason"] in ("terminated", "truncated")
    length = episode["length"]
    episode_id = episode["episode_id"]
    assert store.query("SELECT count(*) FROM steps WHERE episode_id = ?", [episode_id])[0][0] == length
    nodes = store.query("SELECT count(*) FROM nodes WHERE episode_id = ?", [episode_id])[0][0]
    assert nodes == length * BUNDLED_CALLS_PER_STEP[game]
    # the last bundled call of every step (select_action, combine_actions, ...) consumed earlier outputs
    last_calls = store.query(
        "SELECT parents FROM nodes WHERE episode_id = ? AND call_index = ?", [episode_id, BUNDLED_CALLS_PER_STEP[game] - 1]
    )
    assert len(last_calls) == length and all(parents for (parents,) in last_calls)
    run = store.query("SELECT kind, game, status FROM runs WHERE run_id = ?", [summary["run_id"]])[0]
    assert run == ("eval", game, "finished")
    versions = store.query("SELECT produced_by, loc, complexity, len(functions) FROM policy_versions")
    assert versions[0][0] == "file" and versions[0][1] > 40 and versions[0][3] == BUNDLED_CALLS_PER_STEP[game]


@pytest.mark.slow
def test_competent_pong_policy_wins_a_full_game(store):
    from pipeline.play.evaluate import EvalConfig, evaluate

    result = evaluate(POLICIES / "pong_competent.py", EvalConfig(max_steps=27_000), store)
    episode = result.outcomes[0].episode
    assert episode["end_reason"] == "terminated"
    assert episode["return"] >= 19, episode


def test_summary_table_and_truncation(store):
    code, out, err = run_main("eval", EXAMPLES / "pong.py", "--episodes", 2, "--max-steps", 50,
                              "--store", store.path)
    assert code == 0, err
    assert "truncated" in out and "mean return" in out
    rows = store.query("SELECT episode_index, seed, length, end_reason FROM episodes ORDER BY episode_index")
    assert rows == [(0, 0, 50, "truncated"), (1, 1, 50, "truncated")]


def test_standard_protocol_flags_are_recorded(store):
    code, out, _ = run_main("eval", EXAMPLES / "pong.py", "--max-steps", 30, "--sticky", 0.25,
                            "--noop-max", 30, "--store", store.path, "--json")
    assert code == 0
    assert store.query("SELECT sticky, noop_max FROM episodes") == [(0.25, 30)]


@pytest.mark.parametrize(
    "argv_tail, text, fragment",
    [
        (["--game", "brekout"], None, "unknown game 'brekout'"),
        ([], "import os\n" + pong_policy("return 0"), "import of 'os' is not allowed"),
        ([], pong_policy("import subprocess\nreturn 0"), "import of 'subprocess' is not allowed"),
        ([], pong_policy("return (0"), "syntax error"),
        ([], "import tracing as trace\nGAME = 'pong'\n", "no class named 'Policy'"),
        ([], pong_policy("return 0").replace('GAME = "pong"', ""), "does not declare GAME"),
        (["--game", "breakout"], pong_policy("return 0"), "declares GAME = 'pong' but --game is 'breakout'"),
    ],
)
def test_bad_input_is_one_line_and_stores_nothing(argv_tail, text, fragment, store, write_policy):
    path = write_policy(text) if text is not None else EXAMPLES / "pong.py"
    code, out, err = run_main("eval", path, *argv_tail, "--store", store.path)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and fragment in lines[0], err
    assert not store.exists() or store.query("SELECT count(*) FROM runs")[0][0] == 0


def test_missing_policy_file(store):
    code, _, err = run_main("eval", "no/such/policy.py", "--store", store.path)
    assert code == 2 and "does not exist" in err


@pytest.mark.parametrize(
    "body, end_reason, fragment",
    [
        ("while True:\n    pass", "timeout", "time limit"),
        ("return 7", "policy_error", "illegal action 7"),
        ("return 'up'", "policy_error", "illegal action 'up'"),
        ("return None", "policy_error", "illegal action None"),
        ("return {}['missing']", "policy_error", "KeyError"),
        ("import random\nreturn random._os.system('true')", "policy_error", "available to policies"),
        ("raise SystemExit(3)", "policy_error", "SystemExit"),
        ("x = bytearray(10 * 2**30)\nreturn 0", "policy_error", "MemoryError"),
        ("return self.select_action(predicted_ball_y, obs)", "policy_error", "RecursionError"),
    ],
)
def test_misbehaving_policy_ends_its_episode_with_a_reason(body, end_reason, fragment, store, write_policy):
    # an earlier, healthy run in the same store must survive untouched
    assert run_main("eval", EXAMPLES / "pong.py", "--max-steps", 40, "--store", store.path)[0] == 0
    before = store.query("SELECT count(*) FROM steps")[0][0]
    path = write_policy(pong_policy(body))
    code, out, err = run_main("eval", path, "--call-time-limit", 0.3, "--store", store.path, "--json")
    assert code == 1
    episode = json.loads(out)["episodes"][0]
    assert episode["end_reason"] == end_reason and fragment in episode["error"], episode
    assert len(said(err)) == 1, err  # one line besides the progress
    assert store.query("SELECT count(*) FROM steps")[0][0] == before + 1, "earlier rows kept; failing step stored"
    failing = store.query("SELECT action FROM steps WHERE episode_id = ?", [episode["episode_id"]])
    assert failing == [(None,)]


def test_worker_crash_is_recorded_not_raised():
    spec = EpisodeSpec("e", "r", "pong", "", "v")
    spec.game = "not-a-game"  # the worker raises before playing
    [(index, outcome)] = list(run_episodes([spec], workers=1))
    assert index == 0 and outcome.end_reason == "crashed" and "unknown game" in outcome.episode["error"]


def test_a_policy_file_near_its_size_cap_plays():
    """A policy file near MAX_POLICY_CHARS whose task, as JSON, about filled the socket that carries it to its game
    host (~205-220 KB here: 1,500 trainable methods with docstrings did it) left no room behind it for the
    go-ahead, which was dropped: the episode waited out its time limit with no step played and ended as the
    policy's timeout. Swept across the sizes around the socket's buffer, first pairs and staged ones alike."""
    from tracing.policy_file import MAX_POLICY_CHARS

    base = pong_policy("return 0")
    plain, quoted = "#" + "a" * 98 + "\n", "#" + '"' * 98 + "\n"  # 100 characters; 101 and 199 as JSON
    texts = []
    for target in range(200_000, 260_001, 4_000):  # the task's JSON size, around the 212,992-byte buffer
        lines = (MAX_POLICY_CHARS - 200 - len(base)) // 100
        quotes = max(0, min(lines, (target - len(base) - 101 * lines) // 98))
        texts.append(base + quoted * quotes + plain * (lines - quotes))
    assert max(len(t) for t in texts) <= MAX_POLICY_CHARS
    ends = {}
    for i, text in enumerate(texts):  # each the first pair of its call, sent its go-ahead right behind its task
        specs = [EpisodeSpec(f"e{i}.{j}", "r", "pong", text, "v", index=j, max_steps=5, episode_time_limit_s=8)
                 for j in range(2)]  # and a pair staged behind it
        ends[len(json.dumps(text))] = [outcome.end_reason for _, outcome in sorted(run_episodes(specs, workers=1))]
    assert all(reasons == ["truncated"] * 2 for reasons in ends.values()), ends


def test_a_progress_callback_s_own_error_is_the_caller_s_not_the_worker_s():
    """The progress callback runs in the loop that reads the workers' messages: its error (a progress line written
    to a closed stderr) was taken for a malformed message from the worker, and the episode recorded as crashed.
    It is the caller's error, raised to the caller, and every process of the call is ended."""
    from pipeline.boundary import zygotes

    class Unwritable(Exception):
        pass

    def progress(index: int, played: int) -> None:
        raise Unwritable("the progress line could not be written")

    specs = [EpisodeSpec(f"e{i}", "r", "pong", pong_policy("return 0"), "v", index=i, max_steps=400)
             for i in range(2)]
    with pytest.raises(Unwritable):
        list(run_episodes(specs, workers=2, progress=progress))
    both = [zygotes.zygote("game"), zygotes.zygote("policy")]
    deadline = time.monotonic() + 10
    while any(z.count() for z in both) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [z.count() for z in both] == [0, 0], "every host and policy process has exited"


def test_a_policy_that_misbehaves_leaves_nothing_in_its_host_for_the_next_episode():
    """The host of a policy that spun past its call limit, and of one that raised, plays the next episode on it
    exactly as a fresh host does: nothing of a hostile episode stays in the host it shared."""
    from pipeline.boundary import zygotes

    hostile = [pong_policy("while True:\n    pass"), pong_policy("raise ValueError('x' * 100000)")]
    benign = pong_policy("return random.randrange(6)", prelude="import random\n")
    for text in hostile:
        specs = [EpisodeSpec("e0", "r", "pong", text, "v", index=0, max_steps=50, call_time_limit_s=0.3),
                 EpisodeSpec("e1", "r", "pong", benign, "v", index=1, seed=5, max_steps=60),
                 EpisodeSpec("e2", "r", "pong", benign, "v", index=2, seed=9, max_steps=60)]
        forks_before = zygotes.zygote("game").next_id
        together = dict(run_episodes(specs, workers=1))
        assert zygotes.zygote("game").next_id - forks_before == 2, "e2 was played by e0's host"
        assert together[0].end_reason in ("timeout", "policy_error"), together[0].episode
        [(_, alone)] = list(run_episodes([specs[2]], workers=1))
        assert together[2].end_reason == alone.end_reason == "truncated"
        assert together[2].steps.equals(alone.steps)


def test_a_host_that_failed_is_not_handed_the_next_episode():
    """A host that reported an error exits; the episodes after it are played in full, by other hosts (one handed
    to a host that is gone, or going, would look crashed too)."""
    bad = EpisodeSpec("e0", "r", "pong", "", "v", index=0)
    bad.game = "not-a-game"
    good = [EpisodeSpec(f"e{i}", "r", "pong", pong_policy("return 0"), "v", index=i, seed=i, max_steps=30)
            for i in (1, 2, 3)]
    results = dict(run_episodes([bad, *good], workers=1))
    assert results[0].end_reason == "crashed" and "unknown game" in results[0].episode["error"]
    assert [results[i].end_reason for i in (1, 2, 3)] == ["truncated"] * 3, [results[i].episode for i in (1, 2, 3)]


@pytest.mark.parametrize("check", ["passes", "refuses"])
def test_the_next_episode_plays_while_the_parent_checks_the_last_ones_answer(check, monkeypatch):
    """One pair at a time: the staged pair has its go-ahead once the episode before has sent its whole answer,
    not once the parent has checked it (a traced episode's node rows take milliseconds to check, between every two
    episodes). Here the first episode's check takes 3 s: the second episode has played to its end before that
    check is over. A check that then refuses the answer ends that episode alone, and its host plays no other."""
    from pipeline.boundary import zygotes
    from pipeline.boundary.wire import BadMessage
    from pipeline.play import episodes

    real = episodes.EPISODE.decode
    checked_until: dict[int, float] = {}

    def slow_check(spec, msg, tables):
        outcome = real(spec, msg, tables)
        if spec.index == 0:
            time.sleep(3)
            checked_until[0] = time.time()
            if check == "refuses":
                raise BadMessage("refused by the test")
        return outcome

    monkeypatch.setattr(episodes, "EPISODE", dataclasses.replace(episodes.EPISODE, decode=slow_check))
    specs = [EpisodeSpec(f"e{i}", "r", "pong", pong_policy("return 0"), "v", index=i, seed=i, max_steps=40)
             for i in range(3)]
    forks_before = zygotes.zygote("game").next_id
    results = dict(run_episodes(specs, workers=1))
    second = results[1].episode
    second_ended = second["started_at"].replace(tzinfo=timezone.utc).timestamp() + second["duration_s"]
    assert second_ended < checked_until[0], "the second episode waited for the first one's check"
    assert [results[i].end_reason for i in (1, 2)] == ["truncated"] * 2, [results[i].episode for i in (1, 2)]
    if check == "refuses":
        assert results[0].end_reason == "crashed" and "refused by the test" in results[0].episode["error"]
        assert zygotes.zygote("game").next_id - forks_before == 3, "the refused answer's host played no other"
    else:
        assert results[0].end_reason == "truncated"
        assert zygotes.zygote("game").next_id - forks_before == 2, "the first host played the third episode"


def test_a_call_returns_without_waiting_for_its_workers_which_exit_cleanly():
    from pipeline.boundary import zygotes

    specs = [EpisodeSpec(f"e{i}", "r", "pong", pong_policy("return 0"), "v", index=i, max_steps=5)
             for i in range(2)]
    results = list(run_episodes(specs, workers=2))
    assert sorted(i for i, _ in results) == [0, 1] and all(o.end_reason == "truncated" for _, o in results)
    both = [zygotes.zygote("game"), zygotes.zygote("policy")]
    deadline = time.monotonic() + 10
    while any(z.count() for z in both) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [z.count() for z in both] == [0, 0], "every host and policy process has exited"


def test_the_zygotes_start_no_numeric_thread_pool():
    """A game host plays on one core beside its policy process, and a policy process may not start threads: the
    zygotes they fork from start no BLAS or OpenMP pool (the game zygote's OpenBLAS pools spun ~100-175 ms of CPU
    after it started, until its first fork shut them down). Their threads as they have said hello, from /proc: the
    main one and at most jemalloc's background thread."""
    from pipeline.boundary.zygotes import Zygote

    def tree(pid: int) -> list[int]:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        return [pid] + [p for child in children for p in tree(int(child))]

    for role in ("game", "policy"):
        zygote = Zygote(role)  # a fresh one: before it forks anything
        try:
            for pid in tree(zygote.proc.pid):
                names = sorted(Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
                               for tid in os.listdir(f"/proc/{pid}/task"))
                others = [name for name in names if name != "jemalloc_bg_thd"]
                assert len(others) == 1, f"{role} zygote process {pid} runs threads {names}"
        finally:
            zygote.close()


def test_the_game_zygote_loads_the_emulator_after_its_hello_before_any_request():
    """The emulator stack (~0.7 s of imports) is every game task's: the game zygote imports it as soon as it has
    said hello, while the command checks its policy, rather than inside the first request's "prepare". Seen in
    its memory map, with no request sent."""
    from pipeline.boundary.zygotes import Zygote

    def tree(pid: int) -> list[int]:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        return [pid] + [p for child in children for p in tree(int(child))]

    zygote = Zygote("game")
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if any("ale_py" in Path(f"/proc/{pid}/maps").read_text() for pid in tree(zygote.proc.pid)):
                break
            time.sleep(0.05)
        else:
            raise AssertionError("the game zygote never loaded ALE without being asked to prepare a game")
    finally:
        zygote.close()


CHECK_THEN_LEAVE = """
import sys
from pipeline.boundary import zygotes
from pipeline.play.validate import PolicyLoadError, checked_inspect
try:
    checked_inspect(sys.argv[1], "pong.py")
    print("checked")
except PolicyLoadError as exc:
    print("refused")
game = zygotes._zygotes["game"]
print(game.proc.pid, game.greeted, game.proc.poll())
"""


@pytest.mark.parametrize("policy", ["starter", "broken"])
def test_a_checked_policy_s_game_zygote_starts_beside_its_check_and_ends_with_the_process(policy):
    """Every caller of ``checked_inspect`` plays the policy next, so its game zygote starts beside the policy zygote
    that checks it, not after. A process that ends before playing (a policy that fails its check) leaves no zygote
    running: one still starting is killed, not waited for."""
    text = (ROOT / "games" / "scaffolds" / "pong.py").read_text() if policy == "starter" else "def broken(:\n"
    done = subprocess.run([sys.executable, "-c", CHECK_THEN_LEAVE, text], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    said, zygote = done.stdout.splitlines()
    pid, greeted, exited = zygote.split()
    assert said == ("checked" if policy == "starter" else "refused")
    assert greeted == "False" and exited == "None", "started while the policy was checked, not waited for"
    deadline = time.monotonic() + 30  # an orphan is reaped by init at once; a live zygote would stay
    while Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not Path(f"/proc/{pid}").exists(), f"the game zygote {pid} outlived its process"


def test_kept_hosts_play_the_next_call_as_fresh_ones_and_exit_when_the_block_ends():
    """Inside ``keep_hosts`` the game hosts idle at the end of a call play the next call's episodes (no host is
    forked for it) exactly as fresh hosts do; a call on other environments gets fresh hosts (the kept ones go);
    when the block ends every kept host exits."""
    from pipeline.boundary import zygotes

    benign = pong_policy("return random.randrange(6)", prelude="import random\n")
    specs = [EpisodeSpec(f"e{i}", "r", "pong", benign, "v", index=i, seed=seed, max_steps=60)
             for i, seed in enumerate((5, 9, 13))]
    fresh = dict(run_episodes(specs, workers=2))
    game = zygotes.zygote("game")
    with zygotes.keep_hosts():
        list(run_episodes(specs[:2], workers=2))
        assert game.count() == 2, "the two hosts of the first call wait for the next"
        forks_before = game.next_id
        kept = dict(run_episodes(specs[1:], workers=2))
        assert game.next_id == forks_before, "the second call was played by the first call's hosts"
        assert all(kept[i].steps.equals(fresh[i + 1].steps) for i in range(2)), "a kept host plays as a fresh one"
        other = [EpisodeSpec("b0", "r", "breakout", random_policy("breakout", "0"), "v", index=0,
                               max_steps=20)]
        forks_before = game.next_id
        [(_, played)] = list(run_episodes(other, workers=1))
        assert played.end_reason == "truncated" and game.next_id == forks_before + 1, "another game: a fresh host"
    deadline = time.monotonic() + 10
    while game.count() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert game.count() == 0, "the kept hosts exited with the block"


def test_a_block_of_kept_hosts_ends_without_waiting_for_a_thread_that_plays():
    """A command that ends while another of its threads holds the zygotes (the proposal pool's, playing) lets its
    kept hosts go at once: it never waits for that thread's episodes."""
    import threading

    from pipeline.boundary import zygotes

    specs = [EpisodeSpec("e0", "r", "pong", pong_policy("return 0"), "v", index=0, max_steps=20)]
    game = zygotes.zygote("game")
    playing, done, how = threading.Event(), threading.Event(), []

    def other_thread() -> None:
        with zygotes.ZYGOTE_USE:  # as a thread inside run_tasks holds it
            playing.set()
            how.append("released by the block's end" if done.wait(60) else "the block waited for this thread")

    with zygotes.keep_hosts():
        list(run_episodes(specs, workers=1))
        thread = threading.Thread(target=other_thread)
        thread.start()
        playing.wait(60)
    done.set()
    thread.join()
    assert how == ["released by the block's end"]
    deadline = time.monotonic() + 10
    while game.count() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert game.count() == 0, "the kept host exited with the block"


@pytest.mark.slow
@pytest.mark.parametrize("ending", ["returns", "os._exit"])
def test_kept_hosts_do_not_outlive_the_process_that_kept_them(ending, tmp_path):
    """A process that keeps game hosts (as every ``codearcade`` verb does) leaves none behind, whether it ends
    normally inside the block or dies at once (``os._exit``: no ``finally``, no ``atexit``)."""
    from tests.faults.test_ctrl_c_group import _nothing_left

    script = (
        "import os, sys\n"
        "from pipeline.boundary.zygotes import keep_hosts, zygote\n"
        "from pipeline.play.episodes import run_episodes\n"
        "from pipeline.play.spec import EpisodeSpec\n"
        "from tests.conftest import pong_policy\n"
        "specs = [EpisodeSpec(f'e{i}', 'r', 'pong', pong_policy('return 0'), 'v', index=i, max_steps=20)\n"
        "         for i in range(2)]\n"
        "with keep_hosts():\n"
        "    for _ in range(2):\n"
        "        list(run_episodes(specs, workers=2))\n"
        "    print(zygote('game').count(), flush=True)\n"
        f"    {'os._exit(0)' if ending == 'os._exit' else 'sys.exit(0)'}\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, process_group=0)  # its own group: its zygotes and hosts are in it
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert out.split() == ["2"], "two hosts were kept while it ran"
    _nothing_left(proc.pid, err)


def test_a_worker_whose_parent_died_before_it_asked_for_the_death_signal_ends_at_once(tmp_path):
    marker = tmp_path / "survived"
    script = (
        "import os, sys, time\n"
        "from pipeline.boundary.namespaces import die_with_parent\n"
        "parent = os.getpid()\n"
        "r, w = os.pipe()\n"
        "if os.fork() == 0:\n"
        "    os.close(w)\n"
        "    os.read(r, 1)  # EOF: the parent is exiting\n"
        "    time.sleep(0.3)  # and has gone\n"
        "    die_with_parent(parent)\n"
        "    open(sys.argv[1], 'w').write('still running')\n"
        "    os._exit(0)\n"
        "os._exit(0)\n"
    )
    subprocess.run([sys.executable, "-c", script, str(marker)], cwd=ROOT, check=True, timeout=60)
    time.sleep(1.5)
    assert not marker.exists(), "an orphan would have played on"


def test_parallel_workers_keep_every_episode(store):
    code, out, _ = run_main("eval", EXAMPLES / "space_invaders.py", "--episodes", 3, "--workers", 2,
                            "--max-steps", 80, "--store", store.path, "--json")
    assert code == 0
    episodes = json.loads(out)["episodes"]
    assert [e["length"] for e in episodes] == [80, 80, 80]
    assert store.query("SELECT count(*), count(DISTINCT episode_id) FROM steps") == [(240, 3)]


@pytest.mark.slow
def test_console_script(tmp_path):
    exe = os.path.join(os.path.dirname(sys.executable), "codearcade")
    help_text = subprocess.run([exe, "eval", "--help"], capture_output=True, text=True, check=True).stdout
    assert "--trace" in help_text and "--store" in help_text
    env = {**os.environ, "CODEARCADE_STORE": str(tmp_path / "env.duckdb")}
    done = subprocess.run([exe, "eval", str(EXAMPLES / "breakout.py"), "--max-steps", "30", "--json"],
                          capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["episodes"][0]["length"] == 30
    assert (tmp_path / "env.duckdb").exists(), "CODEARCADE_STORE chooses the store"


def test_a_dead_zygote_costs_only_its_episodes_and_the_next_call_starts_another():
    import signal as signals

    from pipeline.boundary import zygotes

    # a policy slow enough (~0.3-1 ms a step) that the first episode is still playing when the kill, at its first
    # progress report (step 250), reaches it on a busy machine: at ~0.2 ms a step it had ended 0.1 s later
    slow = pong_policy("sum(range(20_000))\nreturn 0")
    specs = [EpisodeSpec(f"e{i}", "r", "pong", slow, "v", index=i, max_steps=2000) for i in range(2)]
    pid = zygotes.zygote().proc.pid
    killed = []

    def progress(i, n):
        if not killed:
            os.kill(pid, signals.SIGKILL)
            killed.append(i)

    results = dict(run_episodes(specs, workers=1, progress=progress))
    assert killed and [results[i].end_reason for i in (0, 1)] == ["crashed", "crashed"], results
    [(_, again)] = list(run_episodes(specs[:1], workers=1))
    assert again.end_reason in ("terminated", "truncated") and zygotes.zygote().proc.pid != pid


def test_a_staged_worker_plays_its_episode_as_a_fresh_one_and_its_wait_is_not_its_time():
    """The next episode's worker loads its policy and resets its environment while the current one plays
    (``pipeline/boundary/zygote.py``): what it then plays is what an episode started alone plays (the seeded random
    draws survive the wait), and its duration counts its preparation, not its wait."""
    random_policy = pong_policy("return random.randrange(6)", prelude="import random\n")
    long_first = EpisodeSpec("e0", "r", "pong", random_policy, "v", index=0, seed=3, max_steps=1500)
    staged = EpisodeSpec("e1", "r", "pong", random_policy, "v", index=1, seed=7, max_steps=40)
    results = dict(run_episodes([long_first, staged], workers=1))
    [(_, alone)] = list(run_episodes([staged], workers=1))
    first, second = results[0], results[1]
    assert second.end_reason == alone.end_reason == "truncated"
    assert second.steps.equals(alone.steps), "the staged episode plays as it does alone"
    assert len(set(second.steps.column("action").to_pylist())) > 1, "the policy's draws vary"
    # the staged worker waited for the whole first episode; its own duration is its reset and 40 steps
    assert second.episode["duration_s"] < first.episode["duration_s"] / 2, (second.episode, first.episode)


@pytest.mark.slow
@pytest.mark.parametrize("game", sorted(GAMES))
def test_a_game_host_plays_each_next_episode_as_a_fresh_host_would(game):
    """A game host is handed the next episode instead of exiting (``pipeline/boundary/zygote.py``: the
    environment is reset with the episode's seed, the policy process is new): every episode it plays, steps and
    observations, is the one a fresh host plays alone. Breakout also under the standard stochastic protocol, whose
    reset reloads the ROM and draws its no-ops."""
    from pipeline.boundary import zygotes

    n = get_game(game).n_actions
    text = random_policy(game, f"(random.randrange({n}) + len(obs)) % {n}")
    protocols = [dict(sticky=0.0, noop_max=0)] + ([dict(sticky=0.25, noop_max=30)] if game == "breakout" else [])
    for protocol in protocols:
        specs = [EpisodeSpec(f"e{i}", "r", game, text, "v", index=i, seed=11 + i, max_steps=120, **protocol)
                 for i in range(3)]
        forks_before = zygotes.zygote("game").next_id
        together = dict(run_episodes(specs, workers=1))
        assert zygotes.zygote("game").next_id - forks_before < len(specs), "hosts were handed the next episode"
        for i, spec in enumerate(specs):
            [(_, alone)] = list(run_episodes([spec], workers=1))
            assert together[i].end_reason == alone.end_reason, (game, protocol, i, together[i].episode)
            assert together[i].steps.equals(alone.steps), (game, protocol, i)
            assert together[i].episode["return"] == alone.episode["return"]
        assert len(set(together[2].steps.column("action").to_pylist())) > 1, "the policy's draws vary"


def test_a_policy_that_does_not_load_in_its_process_ends_with_its_reason(store, write_policy, capsys):
    # passes the static checks, fails when loaded: the policy process says why, its host records it
    path = write_policy('GAME = "pong"\n\n\nclass Policy:\n    def __call__(self, obs):\n        return 0\n')
    code = main(["eval", str(path), "--max-steps", "20", "--store", str(store.path), "--json"])
    out, err = capsys.readouterr()
    assert code == 1, err
    episode = json.loads(out)["episodes"][0]
    assert episode["end_reason"] == "policy_error" and "must subclass tracing.Module" in episode["error"], episode


@pytest.mark.slow
def test_an_evaluation_holds_no_episode_s_rows_once_written(tmp_path):
    """`eval` kept every episode's step and node rows until the run ended, so its memory grew with the episodes
    (a traced policy whose methods return ~31 KB a step: 233 MB at 1 episode, 1.2 GB at 40). The process's own
    peak (VmHWM) with 12 episodes is now about its peak with 3."""
    import subprocess
    import sys
    import textwrap

    policy = tmp_path / "big_outputs.py"
    policy.write_text(textwrap.dedent('''
        import tracing as trace

        GAME = "pong"


        @trace.model
        class Policy(trace.Module):
            def __call__(self, obs):
                self.pad(1)
                self.pad(2)
                return self.select_action(obs)

            @trace.bundle(trainable=True)
            def pad(self, k):
                """Padding."""
                return "ab" * 7800

            @trace.bundle(trainable=True)
            def select_action(self, obs):
                """Act."""
                return 0
    '''))

    def peak_mb(episodes: int) -> float:
        script = textwrap.dedent(f"""
            import sys
            from pipeline.cli import main
            code = main(["eval", {str(policy)!r}, "--episodes", "{episodes}", "--max-steps", "800", "--trace",
                         "--workers", "1", "--store", {str(tmp_path / f's{episodes}.duckdb')!r}])
            assert code == 0, code
            print(next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")),
                  file=sys.stderr)
        """)
        done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]
        return int(done.stderr.strip().splitlines()[-1]) / 1024

    few, many = peak_mb(3), peak_mb(12)
    # nine more episodes held their rows: 230 MB more, measured; held no more: +0-69 MB across runs on busy cores
    assert many - few < 120, (few, many)
