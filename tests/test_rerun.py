"""Rerun recordings: live from the episode workers, rebuilt from the store, and the optimizer's run recording.

The recordings are read back with the Rerun SDK in a separate process (tests/rrd_dump.py): this process forks
episode workers, and must not load Rerun itself (it starts Rust threads).
"""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest

from pipeline.cli import main
from tests.conftest import COMPETENT_REPLY, EXAMPLES, ROOT, run_main

STEPS = 120


def run_view(*argv):
    """``codearcade view`` in a process of its own (it loads Rerun; this one forks episode workers)."""
    result = subprocess.run([sys.executable, "-m", "pipeline.cli", "view", *map(str, argv)], capture_output=True,
                            text=True, timeout=300, cwd=ROOT)
    return result.returncode, result.stdout, result.stderr


def dump(*paths) -> dict:
    """{path: content} of .rrd files, read back with the Rerun SDK (see tests/rrd_dump.py)."""
    result = subprocess.run([sys.executable, str(ROOT / "tests" / "rrd_dump.py"), *map(str, paths)],
                            capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def column(content: dict, name: str, timeline: str = "step") -> dict[int, object]:
    return {int(k): v for k, v in content["timelines"][timeline].get(name, {}).items()}


def stored_boxes(store, episode_id: str) -> dict[str, Counter]:
    """Per category: number of boxes at each step, from the store."""
    rows = store.query("SELECT s.step, o.category, count(*) FROM (SELECT step, unnest(objects) AS o FROM steps "
                       "WHERE episode_id = ?) s GROUP BY ALL", [episode_id])
    out: dict[str, Counter] = {}
    for step, category, n in rows:
        out.setdefault(category, Counter())[step] = n
    return out


def assert_holds_episode(content: dict, store, episode_id: str, frames_every: int) -> None:
    """The recording holds the stored episode: one action/reward/score per step, every category's boxes."""
    steps = store.query("SELECT step, action, reward, score FROM steps WHERE episode_id = ? ORDER BY step", [episode_id])
    n = len(steps)
    assert n > 0
    for name, i in (("action", 1), ("reward", 2), ("score", 3)):
        series = column(content, f"/series/{name}:Scalars:scalars")
        assert len(series) == n, name
        assert [series[s[0]][0] for s in steps] == [float(s[i]) for s in steps], name
    boxes = stored_boxes(store, episode_id)
    assert boxes, "the episode has objects"
    frame_steps = [s for s in range(n) if s % frames_every == 0] if frames_every else list(range(n))
    for category, per_step in boxes.items():
        every_step = column(content, f"/objects/{category}:Boxes2D:centers")
        assert {step: len(v) for step, v in every_step.items() if v} == dict(per_step), category
        # the boxes drawn over the frame are logged on the frame's steps only, with that step's objects, so a
        # scrubbed view never shows the frame of one step under the boxes of another
        over_frame = column(content, f"/game/objects/{category}:Boxes2D:centers")
        assert sorted(over_frame) == frame_steps, category
        assert {step: v for step, v in over_frame.items() if v} == {
            step: every_step[step] for step in frame_steps if every_step.get(step)}, category
    frames = column(content, "/game/frame:EncodedImage:blob")
    assert sorted(frames) == (frame_steps if frames_every else [])
    labels = column(content, "/game/frame_step:Points2D:labels")
    assert labels == {s: [f"frame of step {s}"] for s in frames}, "each frame says which step it is from"
    props = content["properties"]
    assert props["episode:episode_id"] == episode_id and props["episode:length"] == n


@pytest.mark.slow
def test_live_and_rebuilt_recordings_hold_the_stored_episode(store, tmp_path):
    live = tmp_path / "live"
    code, out, err = run_main("eval", EXAMPLES / "breakout.py", "--trace", "--episodes", 2, "--max-steps", STEPS,
                              "--rerun", live, "--store", store.path, "--json")
    assert code == 0, err
    summary = json.loads(out)
    ids = [e["episode_id"] for e in summary["episodes"]]
    assert sorted(p.name for p in live.iterdir()) == sorted(f"{i}.rrd" for i in ids), "one .rrd per episode"

    rebuilt = tmp_path / "rebuilt.rrd"
    code, out, err = run_view(summary["run_id"], "--episode", 0, "--save", rebuilt, "--frames-every", 4,
                              "--store", store.path)
    assert code == 0, err
    assert "replayed frames match the stored objects" in out and rebuilt.exists()

    contents = dump(live / f"{ids[0]}.rrd", live / f"{ids[1]}.rrd", rebuilt)
    first, second, again = (contents[str(p)] for p in (live / f"{ids[0]}.rrd", live / f"{ids[1]}.rrd", rebuilt))
    for content, episode_id in ((first, ids[0]), (second, ids[1]), (again, ids[0])):
        assert_holds_episode(content, store, episode_id, frames_every=4)
    # Breakout's brick rows are categories of their own, beside the paddle and the ball
    assert {"RB", "OB", "YB", "GB", "AB", "BB", "Player"} <= set(stored_boxes(store, ids[0]))
    # node outputs of the traced episode: a series per bundled method, the coordinates drawn on the frame
    calls = store.query("SELECT count(*) FROM nodes WHERE episode_id = ? AND function = 'select_paddle_action'", [ids[0]])
    assert len(column(again, "/policy/select_paddle_action:Scalars:scalars")) == calls[0][0] == STEPS
    overlay = column(again, "/game/policy/target_x:LineStrips2D:strips")
    assert overlay and sorted(overlay) == sorted(column(again, "/game/frame:EncodedImage:blob")), \
        "drawn on the frame, so logged on the frame's steps only"
    # the live recording (written by the worker) and the rebuilt one hold the same data, frames included
    assert first["timelines"] == again["timelines"]
    assert "/code:TextDocument:text" in again["static"]


@pytest.mark.slow
def test_replay_that_diverges_from_the_store_is_reported(store, tmp_path):
    # one random stream (the starter moves at random): with another, the paddle may stand at a wall at step 10,
    # where the swapped move changes nothing
    code, out, err = run_main("eval", EXAMPLES / "pong.py", "--max-steps", 80, "--rng-key", "rerun",
                              "--store", store.path, "--json")
    assert code == 0, err
    episode_id = json.loads(out)["episodes"][0]["episode_id"]
    run_id = episode_id.split(".")[0]
    with store.write() as con:  # pretend a different action was played at step 10
        con.execute("UPDATE steps SET action = CASE WHEN action = 2 THEN 3 ELSE 2 END WHERE episode_id = ? AND step = 10",
                    [episode_id])
    code, out, err = run_view(run_id, "--save", tmp_path / "e.rrd", "--store", store.path)
    assert code == 0, err
    assert "differ from the stored ones" in err and "first at step" in err


def test_view_rejects_what_is_not_there(store):
    code, out, err = run_main("eval", EXAMPLES / "pong.py", "--max-steps", 5, "--store", store.path, "--json")
    run_id = json.loads(out)["run_id"]
    # selection errors come before Rerun is loaded, so these run in this process
    code, out, err = run_main("view", "01NOSUCHRUN", "--store", store.path)
    assert code == 2 and "no run 01NOSUCHRUN" in err
    code, out, err = run_main("view", run_id, "--iteration", 3, "--store", store.path)
    assert code == 2 and "no episodes in iteration 3" in err
    code, out, err = run_main("view", run_id, "--episode", 7, "--store", store.path)
    assert code == 2 and "no episode 7" in err
    # in a process of its own: another test module may have loaded the SDK into this one
    check = ("import contextlib, io, sys\nfrom pipeline.cli import main\n"
             f"with contextlib.redirect_stderr(io.StringIO()):\n"
             f"    main(['view', {run_id!r}, '--episode', '7', '--store', {str(store.path)!r}])\n"
             "print('rerun' in sys.modules)")
    loaded = subprocess.run([sys.executable, "-c", check], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert loaded.stdout.strip() == "False", ("view's checks never load the Rerun SDK", loaded.stderr[-500:])


@pytest.mark.slow
def test_run_recording_has_one_score_per_iteration(store, tmp_path, scripted):
    model = scripted([COMPETENT_REPLY, "Sorry, I cannot help with that."])
    live = tmp_path / "live"
    code, out, err = run_main("optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                              "--iterations", 2, "--eval-max-steps", 60, "--rollout-steps", 40, "--workers", 2,
                              "--rerun", live, "--store", store.path, "--json")
    assert code == 0, err
    result = json.loads(out)
    run_id = result["run_id"]
    episodes = [r[0] for r in store.query("SELECT episode_id FROM episodes WHERE run_id = ? AND kind <> 'audit'",
                                          [run_id])]
    assert len(episodes) == 4, "iteration 2's reply was unusable: it reused iteration 1's episodes (the cache)"
    assert sorted(p.name for p in live.iterdir()) == sorted([f"{e}.rrd" for e in episodes] + [f"{run_id}.rrd"])

    rebuilt = tmp_path / "run.rrd"
    code, out, err = run_view(run_id, "--save", rebuilt, "--store", store.path)
    assert code == 0, err
    contents = dump(live / f"{run_id}.rrd", rebuilt)
    scores = [r[0] for r in store.query("SELECT score FROM iterations WHERE run_id = ? ORDER BY iteration", [run_id])]
    for content in contents.values():
        assert content["properties"]["run:run_id"] == run_id
        score = column(content, "/score/score:Scalars:scalars", "iteration")
        assert score == {i: [s] for i, s in enumerate(scores)}, "one score per iteration"
        assert len(column(content, "/score/best:Scalars:scalars", "iteration")) == 3
        code_docs = column(content, "/code:TextDocument:text", "iteration")
        assert sorted(code_docs) == [0, 1, 2] and "predict_ball_trajectory" in code_docs[1][0]
        assert sorted(column(content, "/llm/prompt:TextDocument:text", "iteration")) == [1, 2]
        assert sorted(column(content, "/llm/reply:TextDocument:text", "iteration")) == [1, 2]
        assert len(column(content, "/llm/tokens/input:Scalars:scalars", "iteration")) == 2
        assert len(column(content, "/metrics/complexity:Scalars:scalars", "iteration")) == 3
        lineage = column(content, "/lineage:GraphNodes:node_ids", "iteration")
        flat = [ids[0] if ids and isinstance(ids[0], list) else ids for ids in (lineage[i] for i in range(3))]
        assert flat == [["0.0"], ["0.0", "1.0"], ["0.0", "1.0", "2.0"]], "the candidates so far, per iteration"
    assert contents[str(live / f"{run_id}.rrd")]["timelines"] == contents[str(rebuilt)]["timelines"]


def test_frame_png_is_lossless_and_small():
    from PIL import Image

    from games.envs import make_env
    from viewers.frames import FrameEncoder

    env = make_env("space_invaders")
    try:
        env.reset(seed=0)
        encoder = FrameEncoder(env.unwrapped.ale)
        for step in range(40):
            env.step(step % 6)
            png = encoder.screen_png()
            rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
            assert np.array_equal(rgb, env.unwrapped.ale.getScreenRGB())
            assert len(png) < 4000
    finally:
        env.close()


@pytest.mark.parametrize("value", ["off", "OFF", None])
def test_rerun_off_means_no_target(value):
    from viewers.rerun_sinks import resolve_live_target

    assert resolve_live_target(value) is None


@pytest.mark.parametrize("value, said", [
    ("http://127.0.0.1:9876", "starts rerun+http://"), ("htp://x", "starts rerun+http://"),
    ("grpc://127.0.0.1:9876", "starts rerun+http://"), ("Spawn", "did you mean spawn?"),
    (" spawn", "did you mean spawn?"), ("{tmp}/missing/recordings", "missing does not exist; give another path"),
])
def test_a_rerun_value_that_is_no_directory_meant_is_refused_and_makes_none(tmp_path, monkeypatch, value, said):
    """``--rerun`` takes spawn, off, a viewer's rerun+http:// address or a directory: a URL of another scheme or a
    keyword misspelt made folders (``./http:/127.0.0.1:9876/<episode>.rrd``), silently, as did a directory whose
    parent is missing. Each is refused now, with what to give, and no folder appears."""
    from viewers.rerun_sinks import ViewerError, resolve_live_target

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ViewerError, match=re.escape(said)):
        resolve_live_target(value.format(tmp=tmp_path))
    assert list(tmp_path.iterdir()) == []
    assert resolve_live_target(str(tmp_path / "recordings")) == str(tmp_path / "recordings")  # a directory: made


@pytest.mark.slow
def test_a_served_viewer_ends_with_the_view_that_started_it_however_it_ends(store, tmp_path, capsys):
    """`view --serve-web` starts `rerun --serve-web` in a session of its own (a terminal's Ctrl-C is the view's to
    handle). Killed with SIGKILL, the view could not stop it: the server stayed, holding its two ports, found twice
    after CI runs. It now ends with the view (PR_SET_PDEATHSIG), checked by its process, which must not exist."""
    import os
    import re
    import signal
    import time

    code = main(["eval", str(EXAMPLES / "pong.py"), "--max-steps", "30", "--store", str(store.path), "--json"])
    run_id = json.loads(capsys.readouterr().out)["run_id"]
    assert code == 0
    view = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "view", run_id, "--serve-web", "--store",
                             str(store.path)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            cwd=ROOT)
    try:
        for line in view.stdout:
            if re.search(r"open http://127\.0\.0\.1:", line):
                break
        with open(f"/proc/{view.pid}/task/{view.pid}/children") as f:
            children = [int(pid) for pid in f.read().split()]
        servers = [pid for pid in children if b"--serve-web" in open(f"/proc/{pid}/cmdline", "rb").read()]
        assert len(servers) == 1, children
        view.send_signal(signal.SIGKILL)
        view.wait(30)
        deadline = time.monotonic() + 30
        while os.path.exists(f"/proc/{servers[0]}") and time.monotonic() < deadline:
            try:  # reaped by init once it ends; until then a zombie counts as ended
                if open(f"/proc/{servers[0]}/stat").read().split(")")[-1].split()[0] == "Z":
                    break
            except FileNotFoundError:
                break
            time.sleep(0.1)
        alive = os.path.exists(f"/proc/{servers[0]}") and \
            open(f"/proc/{servers[0]}/stat").read().split(")")[-1].split()[0] != "Z"
        assert not alive, "the served viewer outlived the view that started it"
    finally:
        if view.poll() is None:
            view.kill()


_ONE_SERVER = """
import json, sys, time
from viewers.rerun_sinks import start_web_viewer

time.sleep(max(0.0, float(sys.argv[1]) - time.time()))  # all start at the same moment, as two terminals may
with start_web_viewer() as viewer:
    print(json.dumps({"grpc": viewer.grpc_port, "web": viewer.web_port, "server": viewer.process.pid}), flush=True)
    sys.stdin.read()  # serving until the test closes stdin
"""


@pytest.mark.slow
def test_views_started_together_each_serve_their_own_viewer():
    """Two `view --serve-web` started at once chose the same free ports near Rerun's defaults; the server that lost
    the race exited (the view failed, 3 of 4 times) or, had the other's port answered first, the view would have
    fed and shown the other's recording. Each now gets ports its own server listens on, checked against the
    kernel's table of listening sockets (``ss``'s source), for three at once, twice."""
    import time

    for _ in range(2):
        at = time.time() + 3.0
        views = [subprocess.Popen([sys.executable, "-c", _ONE_SERVER, str(at)], cwd=ROOT, stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(3)]
        try:
            started = []
            for view in views:
                line = view.stdout.readline()
                assert line, view.stderr.read()
                started.append(json.loads(line))
            ports = [viewer[kind] for viewer in started for kind in ("grpc", "web")]
            assert len(set(ports)) == len(ports), started
            for viewer in started:
                for kind in ("grpc", "web"):
                    assert _listening_process(viewer[kind]) == viewer["server"], (kind, viewer)
        finally:
            for view in views:
                view.stdin.close()
                view.wait(30)


def _listening_process(port: int) -> int | None:
    """The process that listens on TCP ``port``, found by its socket's inode among every process's descriptors."""
    import os
    from pathlib import Path

    inodes = {row.split()[9] for row in Path("/proc/net/tcp").read_text().splitlines()[1:]
              if row.split()[3] == "0A" and int(row.split()[1].rsplit(":", 1)[1], 16) == port}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            links = [os.readlink(f"/proc/{pid}/fd/{fd}") for fd in os.listdir(f"/proc/{pid}/fd")]
            if any(link.startswith("socket:[") and link[len("socket:["):-1] in inodes for link in links):
                return int(pid)
        except OSError:
            continue
    return None


@pytest.fixture
def full_disk(tmp_path):
    """A 1 MB file system with 24 KB left (a tmpfs: root only, else the test skips)."""
    import os

    where = tmp_path / "small"
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {mounted.stderr.decode(errors='replace').strip()}")
    try:
        (where / "filler").write_bytes(b"\0" * (1000 * 1024))
        (where / "rr").mkdir()
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)
        assert not os.path.ismount(where)


@pytest.mark.slow
def test_a_recording_on_a_disk_that_fills_costs_neither_the_episode_nor_the_command(full_disk, tmp_path):
    """Once the disk under a recording filled, Rerun's file-writer thread died and closing the recording waited on
    it for good, inside Rust: `eval --rerun DIR` held the episode's host until its time limit and stored a
    time-out, the policy's forfeit (1 in 3 tries of two episodes); `view --save` hung past Ctrl-C and SIGTERM, or
    printed a traceback, and left a truncated file. Each wait on Rerun's sink is now bounded: the episodes are
    played and scored, and `view` says in one line which file it could not write, leaving none; so does `report`.
    `eval` says which episodes' recordings were lost (their hosts' stderr goes nowhere) and leaves no file cut
    short."""
    store = tmp_path / "s.duckdb"
    for attempt in range(3):  # the stuck sink came one time in three
        for old in (full_disk / "rr").iterdir():
            old.unlink()
        done = subprocess.run([sys.executable, "-m", "pipeline.cli", "eval",
                               str(ROOT / "tests/policies/pong_competent.py"), "--episodes", "2",
                               "--max-steps", "300", "--rerun", str(full_disk / "rr"),
                               "--store", str(store), "--json"], cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, (attempt, done.stdout[-2000:], done.stderr[-2000:])
        episodes = json.loads(done.stdout)["episodes"]
        assert [(e["end_reason"], e["length"]) for e in episodes] == [("truncated", 300)] * 2, (attempt, episodes)
        # each recording lost is said, with how to make it again (the host's own stderr went nowhere: nothing was
        # said), and no file cut short is left under an episode's name (one was, 40-130 KB of a whole one)
        for e in episodes:
            said = [line for line in done.stderr.splitlines()
                    if line.startswith(f"codearcade: the Rerun recording of episode {e['episode_id']} was not made")]
            assert len(said) == 1 and str(full_disk / "rr") in said[0], (attempt, done.stderr[-3000:])
            assert f"--episode {e['episode_id']} --save" in said[0], said
        assert list((full_disk / "rr").iterdir()) == [], attempt
    target = full_disk / "x.rrd"
    viewed = subprocess.run([sys.executable, "-m", "pipeline.cli", "view", "last", "--store", str(store), "--save",
                             str(target)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    said = [line for line in viewed.stderr.splitlines() if line.startswith("codearcade")]
    assert viewed.returncode == 2 and len(said) == 1 and str(target) in said[0], viewed.stderr[-2000:]
    assert "Traceback" not in viewed.stderr
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler", "rr"], "no file cut short is left"
    # a report's figures: PIL's OSError named no file, and the command showed a traceback
    reported = subprocess.run([sys.executable, "-m", "pipeline.cli", "report", "last", "--store", str(store), "--out",
                               str(full_disk / "report")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert reported.returncode == 2 and "Traceback" not in reported.stderr, reported.stderr[-2000:]
    assert f"{full_disk / 'report'}/" in reported.stderr.splitlines()[-1], reported.stderr[-2000:]


@pytest.mark.slow
def test_view_save_ends_when_its_sink_is_stuck(tmp_path, capsys):
    """A recording's sink that does not answer within its time (30 s) is given up (``viewers.rerun_recording.within``),
    but its Rust thread stays stuck in a write, and the interpreter's exit waited on it: `view --save` onto a full
    disk (4 runs in 8) or onto a pipe nobody reads said "Rerun did not flush the recording within 30 s" and never
    exited, past SIGTERM. Here the pipe is held open by a reader that never reads (its buffer one page): the
    command says its one line and ends (~35 s), no process left."""
    import fcntl
    import os

    store = tmp_path / "s.duckdb"
    assert main(["eval", str(EXAMPLES / "pong.py"), "--episodes", "1", "--max-steps", "200", "--store",
                 str(store)]) == 0
    capsys.readouterr()
    pipe = tmp_path / "x.rrd"
    os.mkfifo(pipe)
    reader = os.open(pipe, os.O_RDONLY | os.O_NONBLOCK)  # there, never reading
    fcntl.fcntl(reader, 1031, 4096)  # F_SETPIPE_SZ: a page fills at once
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "view", "last", "--store", str(store), "--save",
                             str(pipe)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=300)  # before, it waited for good
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"view --save did not end once its sink was given up: {err[-2000:]}")
    finally:
        os.close(reader)
    said = [line for line in err.splitlines() if line.startswith("codearcade")]
    assert proc.returncode == 2 and len(said) == 1 and "did not" in said[0] and str(pipe) in said[0], err[-2000:]


@pytest.mark.slow
def test_a_method_that_returns_an_int_past_a_float_is_recorded_live_and_rebuilt(store, tmp_path):
    """A bundled method may return ``10**400``: Python writes it (401 digits) and the store holds it, but a float
    cannot hold it. The live recording was not made (``OverflowError``, said on stderr) and ``view`` of the stored
    episode ended in that traceback. Now both are made, the method's outputs logged as text, the numbers whole."""
    from tests.conftest import pong_policy

    policy = tmp_path / "huge.py"
    policy.write_text(pong_policy("self.huge(3)\nreturn 0") + """
    @trace.bundle()
    def huge(self, n):
        return 10 ** 400 + n
""")
    live = tmp_path / "live"
    code, out, err = run_main("eval", policy, "--trace", "--max-steps", 6, "--rerun", live, "--store", store.path,
                              "--json")
    assert code == 0 and "was not made" not in err, err
    episode_id = json.loads(out)["episodes"][0]["episode_id"]
    rebuilt = tmp_path / "rebuilt.rrd"
    code, out, err = run_view(episode_id.split(".")[0], "--episode", 0, "--save", rebuilt, "--store", store.path)
    assert code == 0 and "Traceback" not in err, err
    contents = dump(live / f"{episode_id}.rrd", rebuilt)
    for content in contents.values():
        logged = column(content, "/policy/huge:TextLog:text")
        assert [json.loads(v[0]) for _, v in sorted(logged.items())] == [10**400 + 3] * 6
