"""`codearcade batch`: experiment files, local processes, kill -9 and rerun, and the Ray executor."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from pipeline.jobs.experiments import ExperimentError, load_experiments

from store.views import run_user_query
from tests.conftest import COMPETENT_REPLY, ROOT

POLICIES = __import__("pathlib").Path(__file__).parent / "policies"

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")


def _experiments(tmp_path, model, name="smoke", iterations=1, seeds=(0, 1), audit_episodes=3, eval_max_steps=300,
                 rollout_steps=100):
    """A batch of Pong and Breakout runs, one per seed and game (what these tests check of a batch does not need
    each run's held-out audit: ``audit_episodes=0`` leaves it out; tests/test_audit.py tests it; nor long games:
    ``eval_max_steps=60`` plays a fifth of the steps)."""
    path = tmp_path / f"{name}.toml"
    path.write_text(textwrap.dedent(f"""
        name = "{name}"
        [defaults]
        iterations = {iterations}
        eval_max_steps = {eval_max_steps}
        rollout_steps = {rollout_steps}
        rng_key = "smoke"
        audit_episodes = {audit_episodes}
        model = "{model.model}"
        api_base = "{model.api_base}"
        [matrix]
        game = ["pong", "breakout"]
        seed = {list(seeds)}
    """))
    return path


def _batch(path, store, *extra, **kwargs):
    return subprocess.run([EXE, "batch", str(path), "--store", str(store.path), *extra], cwd=ROOT,
                          capture_output=True, text=True, timeout=900, **kwargs)


def _wait_for_iterations(store, process, n: int, timeout_s: float = 300) -> None:
    """Until the batch ``process`` has stored ``n`` iterations (the store may not exist or be held meanwhile), or
    it ended, or ``timeout_s`` passed."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and process.poll() is None:
        try:
            if store.query("SELECT count(*) FROM iterations")[0][0] >= n:
                return
        except Exception:
            pass
        time.sleep(0.2)


def _rows(store):
    return sorted(store.query(
        """SELECT r.game, json_extract(r.config, '$.seed')::INT, i.iteration, i.policy_version_id, i.score,
                  i.update_status
           FROM iterations i JOIN runs r USING (run_id) WHERE r.kind = 'optimize'"""))


def test_experiment_file_errors_are_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    for text, fragment in [
        ("[defaults]\niteratoins = 3\n[matrix]\ngame = ['pong']\n", "did you mean 'iterations'"),
        ("[matrix]\ngame = ['pongg']\n", "unknown game 'pongg'"),
        ("[matrix]\ngame = ['pong']\nfeedback = ['loud']\n", "feedback must be one of"),
        ("[defaults]\ngame = 'pong'\n", "no runs"),
        ("[matrix\n", "not valid TOML"),
        ("[matrx]\ngame = ['pong']\n", "did you mean 'matrix'"),
        ("[defaults]\ngame = 'pong'\n[[run]]\nname = 'a'\n[[run]]\nname = 'a'\nseed = 1\n",
         "[[run]] #2: name 'a' is the name of [[run]] #1 too"),
        # each of these ended in a traceback, or passed --dry-run and failed when run, or was dropped unsaid
        ("matrix = 5\n", "'matrix' must be a table"),
        ("defaults = 5\n[matrix]\ngame = ['pong']\n", "'defaults' must be a table"),
        ("[defaults]\ngame = 'pong'\nseed = 1979-05-27\n", "seed = datetime.date(1979, 5, 27): give a number"),
        ("name = 'x/y'\n[defaults]\ngame = 'pong'\n", "no '/'"),
        ("[defaults]\ngame = 'pong'\n[[run]]\nname = 'alpha'\n[[run]]\nname = 'beta'\n",
         "('beta') has the same settings as pong ('alpha')"),
        ("name = 'lab'\n[defaults]\ngame = 'pong'\n[matrix]\nseed = [0, 1]\n[[run]]\nname = 'lab:pong,seed=1'\n"
         "memory = 3\n", "name 'lab:pong,seed=1' is a matrix entry's label too"),
    ]:
        bad.write_text(text)
        with pytest.raises(ExperimentError) as err:
            load_experiments(bad)
        assert fragment in str(err.value) and "\n" not in str(err.value)


def test_matrix_expands_with_stable_keys(tmp_path, scripted):
    model = scripted([COMPETENT_REPLY])
    batch = load_experiments(_experiments(tmp_path, model))
    assert [r.label for r in batch.runs] == ["pong seed=0", "pong seed=1", "breakout seed=0", "breakout seed=1"]
    again = load_experiments(_experiments(tmp_path, model))
    assert [r.key for r in batch.runs] == [r.key for r in again.runs]
    assert len({r.key for r in batch.runs}) == 4


@pytest.mark.slow
def test_local_batch_then_kill_and_rerun(tmp_path, store, scripted):
    model = scripted([COMPETENT_REPLY])
    path = _experiments(tmp_path, model, iterations=2, audit_episodes=0, eval_max_steps=60, rollout_steps=30)
    process = subprocess.Popen([EXE, "batch", str(path), "--store", str(store.path), "--workers", "2"], cwd=ROOT,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _wait_for_iterations(store, process, 2)
    process.send_signal(signal.SIGKILL)
    process.wait()
    time.sleep(1.0)
    leftover = subprocess.run(["pgrep", "-f", f"pipeline.jobs.worker.*{store.path}"], capture_output=True, text=True)
    assert leftover.stdout.strip() == "", "the run processes died with the batch"

    dry = _batch(path, store, "--dry-run")
    assert "resume" in dry.stdout or "start" in dry.stdout

    done = _batch(path, store, "--workers", "2")
    assert done.returncode == 0, done.stderr + done.stdout
    runs = store.query("SELECT count(*), count(DISTINCT json_extract_string(config, '$.batch_key')) FROM runs")
    assert runs == [(4, 4)], "killed runs were resumed, not started again"
    per_iteration = store.query("SELECT run_id, iteration, count(*) FROM iterations GROUP BY ALL HAVING count(*) > 1")
    assert per_iteration == []
    assert store.query("SELECT count(*) FROM iterations")[0][0] == 4 * 3
    assert store.query("SELECT count(*) FROM runs WHERE status = 'finished'")[0][0] == 4
    log = store.path.with_name(f"{store.path.name}.smoke.log").read_text()
    # A run may finish in the instant before the kill: the rerun then logs it as skipped, not finished.
    for label in ("pong seed=0", "pong seed=1", "breakout seed=0", "breakout seed=1"):
        assert f"finished {label}" in log or f"skipped {label} (finished already" in log, label
    assert "batch smoke done" in log

    again = _batch(path, store, "--dry-run")
    assert again.stdout.count("skip") == 4, "a finished batch has nothing left to do"


@pytest.mark.slow
def test_a_batch_stopped_by_ctrl_c_says_how_to_resume_and_leaves_no_process(tmp_path, store, scripted):
    """It said only 'codearcade: interrupted'."""
    model = scripted([COMPETENT_REPLY])
    path = _experiments(tmp_path, model, iterations=2, audit_episodes=0, eval_max_steps=60, rollout_steps=30)
    process = subprocess.Popen([EXE, "batch", str(path), "--store", str(store.path), "--workers", "2"], cwd=ROOT,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _wait_for_iterations(store, process, 1)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert "rerun the same command to resume them" in err and "Traceback" not in err, err
    time.sleep(1.0)
    leftover = subprocess.run(["pgrep", "-f", f"pipeline.jobs.worker.*{store.path}"], capture_output=True, text=True)
    assert leftover.stdout.strip() == "", "the run processes stopped with the batch"


@pytest.mark.slow
def test_a_sigint_to_the_batch_alone_stops_its_runs_at_once(tmp_path, store, scripted):
    """``kill -INT`` of the batch's process alone (not its group, as a terminal's Ctrl-C is): the batch took it for
    a Ctrl-C its runs had heard too and waited for them, while they went on waiting for the model, until its
    wind-down limit (60 s) ran out. It passes the stop on now: every run is interrupted well before that limit."""
    from pipeline.jobs.batch import WORKER_WIND_DOWN_S

    model = scripted([{"sleep": 600, "content": COMPETENT_REPLY}] * 2)  # iteration 1's calls never come back in time
    path = _experiments(tmp_path, model, iterations=1, seeds=(0,), audit_episodes=0, eval_max_steps=60,
                        rollout_steps=30)
    process = subprocess.Popen([EXE, "batch", str(path), "--store", str(store.path), "--workers", "2"], cwd=ROOT,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _wait_for_iterations(store, process, 2)  # both runs' iteration 0: each now waits for its model call
    assert process.poll() is None
    pressed = time.monotonic()
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=3 * WORKER_WIND_DOWN_S)
    took = time.monotonic() - pressed
    assert process.returncode == 130 and "Traceback" not in err, err
    assert took < WORKER_WIND_DOWN_S, f"the batch waited out its wind-down limit ({took:.0f} s)"
    assert store.query("SELECT status, count(*) FROM runs GROUP BY ALL") == [("interrupted", 2)]


STUCK_RUN = """
import json, runpy, signal, sys, time

def stuck_winding_down(text):  # the run's process as the batch starts it, stuck where it reads its spec
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # as a run that is winding down ignores another stop
    print("ready", flush=True)
    time.sleep(600)

json.loads = stuck_winding_down
sys.argv = ["worker", "{}"]
runpy.run_module("pipeline.jobs.worker", run_name="__main__")
"""


def test_a_run_stuck_past_the_wind_down_writes_where_it_was_stuck_into_its_log(tmp_path):
    """A stopped batch waits ``WORKER_WIND_DOWN_S`` for its runs to mark themselves interrupted. One still running
    then was sent SIGTERM, which a run winding down ignores, and it died with the batch, its run 'running' and its
    log silent (CI, once in 1,684 tests: 69.5 s, a run left 'running'). Now the batch sends it SIGABRT, on which a
    run process writes every thread's stack into its log (``faulthandler``) and ends. By effect: a run process
    stuck in a function of its own, its log after the wind-down."""
    from pipeline.jobs.batch import RunLog, _wait_for_workers

    env = {k: v for k, v in os.environ.items() if k != "PYTHONFAULTHANDLER"}  # the run process enables it itself
    proc = subprocess.Popen([sys.executable, "-c", STUCK_RUN], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    log = RunLog(tmp_path / "run.log").follow(proc)
    deadline = time.monotonic() + 60
    while b"ready" not in b"".join(log.tail) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, (tmp_path / "run.log").read_text()
    _wait_for_workers({0: (proc, log)}, 0.5)
    text = (tmp_path / "run.log").read_text()
    assert proc.returncode == -signal.SIGABRT, (proc.returncode, text[-3000:])
    assert "most recent call first" in text and "stuck_winding_down" in text, text[-3000:]


@pytest.mark.slow
def test_ray_executor_produces_the_same_rows(tmp_path, scripted):
    pytest.importorskip("ray")
    from store import Store

    model = scripted([COMPETENT_REPLY])
    path = _experiments(tmp_path, model, seeds=(0,), audit_episodes=0, eval_max_steps=60,
                        rollout_steps=30)  # a run of each game
    local, remote = Store(tmp_path / "local.duckdb"), Store(tmp_path / "ray.duckdb")
    done = _batch(path, local, "--workers", "2")
    assert done.returncode == 0, done.stderr + done.stdout
    done = _batch(path, remote, "--executor", "ray", env={**os.environ, "RAY_AUTH_MODE": "disabled"})
    assert done.returncode == 0, done.stderr + done.stdout
    assert _rows(remote) == _rows(local)
    for table in ("steps", "nodes", "episodes", "llm_calls", "policy_versions", "feedback"):
        assert remote.query(f"SELECT count(*) FROM {table}") == local.query(f"SELECT count(*) FROM {table}"), table


@pytest.mark.slow
def test_ablation_example_and_its_sql(tmp_path, store, scripted):
    """examples/ablation.toml with the scripted model standing in, shortened; then examples/ablation.sql."""
    import tomllib

    model = scripted([COMPETENT_REPLY])
    source = (ROOT / "examples" / "ablation.toml").read_text()
    data = tomllib.loads(source)
    assert data["matrix"] == {"feedback": ["rollout", "staged"], "seed": [0, 1, 2]}
    assert len(load_experiments(ROOT / "examples" / "ablation.toml").runs) == 6
    # each run's audit in one held-out game per version and protocol (4 games, not the default's 12)
    short = source.replace("iterations = 20", "iterations = 1\neval_max_steps = 200\nrollout_steps = 60\n"
                           "audit_episodes = 1") \
        .replace('model = "anthropic/claude-sonnet-4-5"  # the paper used Claude 3.5 Sonnet (Oct 2024), since retired',
                 f'model = "{model.model}"\napi_base = "{model.api_base}"')
    path = tmp_path / "ablation.toml"
    path.write_text(short)
    done = _batch(path, store, "--workers", "2")
    assert done.returncode == 0, done.stderr + done.stdout
    sql = (ROOT / "examples" / "ablation.sql").read_text()
    rows = run_user_query(store, sql).rows  # as `codearcade sql` runs it: with mean_ci and ci_text
    assert [r[0] for r in rows] == ["rollout", "staged"]
    assert all(r[1] == 3 and r[5] == 1 for r in rows), rows
    audited = dict(store.query("SELECT json_extract_string(r.config, '$.feedback'), count(*) FROM run_summary s "
                               "JOIN runs r USING (run_id) WHERE s.audit_score IS NOT NULL GROUP BY 1"))
    assert audited == {"rollout": 3, "staged": 3}, "every run has its held-out audit"
    assert all(r[6] is not None and r[7] <= 3 for r in rows), "the audit and its overfit count beside the scores"
    for feedback, _, mean_best, max_best, _, _, _, _ in rows:  # mean [low, high] over the three seeds, with n
        bests = [b for (b,) in store.query(
            "SELECT max(i.score) FROM runs r JOIN iterations i USING (run_id) WHERE json_extract_string(r.config, "
            "'$.feedback') = ? GROUP BY r.run_id", [feedback])]
        shown = re.fullmatch(r"(\S+)(?: \[(\S+), (\S+)\] 95% t, n=3| \(n=3: all equal, no interval\))", mean_best)
        assert shown, mean_best
        mean = float(shown.group(1))
        assert mean == round(sum(bests) / 3, 1) and max_best == max(bests), (mean_best, bests)
        if len(set(bests)) == 1:  # all equal: no interval to print (store/scores.py), the mean alone
            assert shown.group(2) is None, mean_best
        else:
            assert float(shown.group(2)) <= mean <= float(shown.group(3)), mean_best


@pytest.mark.slow
def test_anthropic_batch_with_a_token_budget_stops_then_resumes_with_a_larger_one(tmp_path, store, scripted):
    """An Anthropic model in a batch (no seed sent), a missing key refused before any run starts, and a
    per-run budget: status `budget`, then the same batch with a larger budget resumes the same runs."""
    model = scripted([{"content": "No change.", "usage": {"input": 3000, "output": 100}}])
    route, base = model.route("anthropic", "claude-sonnet-4-5")

    def write(budget):
        path = tmp_path / "anthropic.toml"
        path.write_text(textwrap.dedent(f"""
            name = "anthropic"
            [defaults]
            game = "pong"
            iterations = 3
            eval_max_steps = 60
            rollout_steps = 50
            audit_episodes = 0
            token_budget = 2500
            max_tokens = 200
            max_total_tokens = {budget}
            model = "{route}"
            api_base = "{base}"
            [matrix]
            seed = [0, 1]
        """))
        return path

    env = {k: v for k, v in os.environ.items() if k != "ANTHROPIC_API_KEY"}
    refused = _batch(write(7000), store, env=env)
    assert refused.returncode == 2 and "ANTHROPIC_API_KEY" in refused.stderr and not store.exists()
    # the way out is said where the model was named: the batch file, not a flag (its api_base is set already)
    assert "remove model from the batch file" in refused.stderr and "--model" not in refused.stderr, refused.stderr
    env["ANTHROPIC_API_KEY"] = "sk-ant-scripted"
    done = _batch(write(7000), store, "--workers", "2", env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    # each call uses 3,100 tokens and may use up to 2,700: two fit in 7,000 (0 + 2,700, 3,100 + 2,700), a third not
    assert store.query("SELECT status, count(*) FROM runs GROUP BY status") == [("budget", 2)]
    assert "done: 0 finished, 2 stopped by a budget" in done.stdout, done.stdout
    assert store.query("SELECT max(iteration) FROM iterations GROUP BY run_id") == [(2,), (2,)]
    assert all("seed" not in r["body"] for r in model.raw_requests())
    done = _batch(write(100_000), store, "--workers", "2", env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert store.query("SELECT status, count(*) FROM runs GROUP BY status") == [("finished", 2)]
    rows = store.query("SELECT run_id, iteration, count(*) FROM iterations GROUP BY ALL HAVING count(*) > 1")
    assert rows == [] and store.query("SELECT count(*) FROM iterations")[0][0] == 8


@pytest.mark.slow  # batch run processes: ~10 s of CPU each before they play
def test_one_batch_is_run_by_one_command_at_a_time(tmp_path, store, scripted):
    """The same batch started twice at once on one store: each command planned the runs and started them all, two
    runs per entry under the same key and label (which `examples/ablation.sql` then counted twice). The second
    command now says who runs the batch and starts nothing; the first's runs are the batch's only ones. Its runs
    play iteration 0 alone, one at a time: the second is still to start, or starting, when the first's iteration is
    stored."""
    model = scripted([COMPETENT_REPLY])
    path = _experiments(tmp_path, model, iterations=0, seeds=(0,), audit_episodes=0, eval_max_steps=60,
                        rollout_steps=30)
    first = subprocess.Popen([EXE, "batch", str(path), "--store", str(store.path), "--workers", "1"], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_iterations(store, first, 1)
        assert first.poll() is None, "the first batch is still running"
        second = _batch(path, store, "--workers", "1")
        assert second.returncode == 2 and f"is being run on {store.path} by process {first.pid}" in second.stderr, \
            second.stderr
        assert first.wait(timeout=600) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    keys = store.query("SELECT json_extract_string(config, '$.batch_key') FROM runs WHERE kind = 'optimize'")
    assert len(keys) == 2 and len(set(keys)) == 2, keys


@pytest.mark.slow
def test_a_finished_run_whose_label_changed_is_renamed_without_being_run_again(tmp_path, store, scripted):
    """A [[run]] name edited after its run finished reached the store only if the run ever resumed (a finished
    run is skipped): `runs` kept showing the old label. Each way a label changes (a name edited, a name taken away:
    the batch's default label; one entry changed, the other not) is applied in one write, said in the log and in
    --dry-run, and nothing is played again."""
    model = scripted([COMPETENT_REPLY])
    path = tmp_path / "labels.toml"

    def write(first: str | None, second: str | None) -> None:
        named = [f"name = '{n}'\n" if n else "" for n in (first, second)]
        path.write_text(f"name = 'labels'\n[defaults]\niterations = 0\neval_max_steps = 60\naudit_episodes = 0\n"
                        f"model = '{model.model}'\napi_base = '{model.api_base}'\n"
                        f"[[run]]\ngame = 'pong'\n{named[0]}[[run]]\ngame = 'breakout'\n{named[1]}")

    def names() -> dict[str, str | None]:
        return dict(store.query("SELECT game, name FROM runs"))

    write("alpha", "beta")
    assert _batch(path, store).returncode == 0
    assert names() == {"pong": "alpha", "breakout": "beta"}
    episodes = store.query("SELECT count(*) FROM episodes")[0][0]
    for first, second, expected in [("gamma", "beta", {"pong": "gamma", "breakout": "beta"}),
                                    (None, "delta", {"pong": "labels:pong", "breakout": "delta"}),
                                    (None, "delta", {"pong": "labels:pong", "breakout": "delta"})]:
        before = names()
        write(first, second)
        dry = _batch(path, store, "--dry-run")
        assert dry.returncode == 0, dry.stderr
        changed = {game for game in expected if expected[game] != before[game]}
        for game in ("pong", "breakout"):
            line = next(line for line in dry.stdout.splitlines() if f" {game}" in line)
            assert line.split()[0] == "skip", dry.stdout
            assert (f"named {before[game]!r} now" in line) == (game in changed), dry.stdout
        assert names() == before, "a dry run changes nothing"
        done = _batch(path, store)
        assert done.returncode == 0, done.stderr
        assert names() == expected
        log = store.path.with_name(f"{store.path.name}.labels.log").read_text().split(" batch labels: ")[-1]
        assert log.count("renamed run") == len(changed), log
    assert store.query("SELECT count(*) FROM runs")[0][0] == 2, "nothing was started again"
    assert store.query("SELECT count(*) FROM episodes")[0][0] == episodes, "nothing was played again"


@pytest.mark.slow  # batch run processes: ~10 s of CPU each before they play
def test_a_batch_folder_moved_whole_keeps_its_runs(tmp_path, store, scripted):
    """A run's key hashed its policy file's absolute path: a batch folder moved (or its checkout cloned elsewhere)
    started every policy-file run again. A policy file inside the batch's folder now counts by its path from
    there; a run keyed the old way (by the absolute path) is still found where the folder has not moved."""
    import shutil

    from pipeline.jobs import batch as batch_module
    from pipeline.jobs.experiments import load_experiments

    model = scripted([COMPETENT_REPLY])
    folder = tmp_path / "experiment"
    (folder / "policies").mkdir(parents=True)
    shutil.copy(POLICIES / "pong_competent.py", folder / "policies" / "pong.py")
    path = folder / "moved.toml"
    path.write_text(f"name = 'moved'\n[defaults]\niterations = 0\neval_max_steps = 60\naudit_episodes = 0\n"
                    f"model = '{model.model}'\napi_base = '{model.api_base}'\n[[run]]\npolicy = 'policies/pong.py'\n"
                    "[[run]]\ngame = 'breakout'\n")
    assert _batch(path, store).returncode == 0
    assert store.query("SELECT count(*), count(*) FILTER (WHERE status = 'finished') FROM runs") == [(2, 2)]
    moved = shutil.move(folder, tmp_path / "elsewhere") / "moved.toml"
    dry = _batch(moved, store, "--dry-run")
    assert dry.returncode == 0 and [line.split()[0] for line in dry.stdout.splitlines() if "[moved:" in line] == \
        ["skip", "skip"], dry.stdout
    assert _batch(moved, store).returncode == 0
    assert store.query("SELECT count(*) FROM runs")[0][0] == 2, "nothing was started again"
    # a store whose run has the key of before: found by it, not started again
    batch = load_experiments(moved)
    [policy_run] = [run for run in batch.runs if run.config.policy]
    assert policy_run.legacy_key and policy_run.legacy_key != policy_run.key
    with store.write() as con:
        con.execute("UPDATE runs SET config = json_merge_patch(config, json_object('batch_key', ?)) "
                    "WHERE config->>'batch_key' = ?", [policy_run.legacy_key, policy_run.key])
    assert [p.action for p in batch_module.plan(batch, store)] == ["skip", "skip"]


def test_the_live_table_says_no_score_once_every_assessed_version_forfeited():
    """The live table showed `-` for a run whose every assessed version forfeited (its best NULL by the rule), as
    for one that had played nothing yet."""
    from pipeline.cli.batch import best_cell
    from pipeline.jobs.batch import Progress

    assert best_cell(Progress("a")) == "-"  # nothing assessed yet
    assert best_cell(Progress("a", iteration=0)) == "no score"  # the starter forfeited
    assert best_cell(Progress("a", iteration=3, best=-4.5)) == "-4.5"
