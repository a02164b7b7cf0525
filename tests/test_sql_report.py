"""`codearcade sql`, `runs` and `report`: output formats, one-line errors, reading while a run writes."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest

from pipeline.cli import main
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from pipeline.play.evaluate import EvalConfig, evaluate
from store import Store
from tests.conftest import COMPETENT_REPLY, EXAMPLES, ROOT

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")


@pytest.fixture(scope="module")
def filled(tmp_path_factory):
    """A store with a 2-iteration optimize run (accepted, then an unusable reply) and a 3-episode eval run."""
    from tests.scripted_llm import ScriptedModel

    tmp = tmp_path_factory.mktemp("sql")
    store = Store(tmp / "s.duckdb", lock_timeout_s=20)
    with ScriptedModel([COMPETENT_REPLY, "no code today"], tmp / "model") as model:
        client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
        result = optimize(OptimizeConfig(game="pong", iterations=2, rollout_steps=100, eval_max_steps=200,
                                         workers=2, token_budget=8000), store, client)
    assert result.status == "finished", result.error
    ev = evaluate(EXAMPLES / "pong.py", EvalConfig(episodes=3, max_steps=150, workers=2), store)
    return store, result.run_id, ev.run_id


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------------------------------------------ sql

def test_sql_table_csv_and_json_agree(filled, capsys):
    store, run_id, _ = filled
    query = ("SELECT iteration, score, update_status, rolled_back, started_at, policy_version_id IS NULL AS n "
             f"FROM learning_curve WHERE run_id = '{run_id}' ORDER BY iteration")
    rows = store.query(query)
    code, out, _ = _run(capsys, "sql", query, "--store", str(store.path))
    lines = out.splitlines()
    assert code == 0 and lines[0].split() == ["iteration", "score", "update_status", "rolled_back", "started_at", "n"]
    assert set(lines[1]) == {"-", " "} and lines[-1] == "(3 rows)"
    assert [line.split()[2] for line in lines[2:5]] == ["initial", "accepted", "rejected"]
    assert lines[2].index("0") == lines[0].index("iteration") + len("iteration") - 1, "numbers are right-aligned"

    code, out, _ = _run(capsys, "sql", query, "--csv", "--store", str(store.path))
    parsed = list(csv.reader(io.StringIO(out)))
    assert code == 0 and parsed[0][0] == "iteration" and len(parsed) == 4
    assert [float(r[1]) for r in parsed[1:]] == [r[1] for r in rows] and parsed[1][3] == "false"

    code, out, _ = _run(capsys, "sql", query, "--json", "--store", str(store.path))
    records = json.loads(out)
    assert code == 0 and [r["iteration"] for r in records] == [0, 1, 2]
    assert [r["score"] for r in records] == [r[1] for r in rows] and records[0]["rolled_back"] is False
    assert records[0]["started_at"] == rows[0][4].isoformat()


def test_sql_csv_reads_back_every_float_and_a_table_writes_whole_numbers_out(tmp_path, capsys):
    """CSV is for programs: a float there was cut to six digits (-0.666667 for a stored -0.6666666666666666) and
    a sum in the millions came out as -9.3e+06. Over doubles of every size and sign, each CSV field reads back
    as the stored double; a table cell is within six significant digits of it, and a whole-number part of up to
    15 figures is written out, not in scientific notation."""
    import random

    rng = random.Random(7)
    values = [-2 / 3, -9.3e6, 1e15 - 1, 0.1 + 0.2, 5e-324, -1.7976931348623157e308, 0.0, 2.0]
    values += [rng.choice((-1, 1)) * rng.random() * 10.0 ** rng.randint(-12, 20) for _ in range(120)]
    query = "SELECT v FROM (VALUES " + ", ".join(f"({v!r}::DOUBLE, {i})" for i, v in enumerate(values)) + \
        ") t(v, i) ORDER BY i"
    store = tmp_path / "s.duckdb"
    with Store(store).write():  # an empty store
        pass
    code, out, err = _run(capsys, "sql", query, "--csv", "--max-rows", "1000", "--store", str(store))
    assert code == 0, err
    assert [float(row[0]) for row in list(csv.reader(io.StringIO(out)))[1:]] == values
    code, out, err = _run(capsys, "sql", query, "--max-rows", "1000", "--store", str(store))
    cells = [line.strip() for line in out.splitlines()[2:2 + len(values)]]
    for value, cell in zip(values, cells):
        assert float(cell) == pytest.approx(value, rel=5e-6, abs=0), (value, cell)
        if 1 <= abs(value) < 1e15:
            assert "e" not in cell, (value, cell)


def test_sql_json_embeds_json_columns_and_nulls(filled, capsys):
    store, run_id, _ = filled
    code, out, _ = _run(capsys, "sql", f"SELECT config, model, finished_at, NULL AS nothing, [1, 2] AS l, "
                        f"{{'a': 1}} AS s FROM runs WHERE run_id = '{run_id}'", "--json", "--store", str(store.path))
    (record,) = json.loads(out)
    assert code == 0 and record["config"]["iterations"] == 2 and record["config"]["game"] == "pong"
    assert record["nothing"] is None and record["l"] == [1, 2] and record["s"] == {"a": 1}
    code, out, _ = _run(capsys, "sql", "SELECT NULL AS a, 'x,y' AS b, 'two\nlines' AS c", "--csv",
                        "--store", str(store.path))
    assert list(csv.reader(io.StringIO(out))) == [["a", "b", "c"], ["", "x,y", "two\nlines"]]


def test_sql_truncates_wide_cells_and_long_results(filled, capsys):
    store, _, _ = filled
    code, out, _ = _run(capsys, "sql", "SELECT text FROM blobs WHERE kind = 'policy'", "--store", str(store.path))
    body = out.splitlines()[2:-1]
    assert code == 0 and body and all(len(line) <= 40 and line.endswith("…") for line in body)
    code, out, _ = _run(capsys, "sql", "SELECT text FROM blobs WHERE kind = 'policy'", "--max-width", "0",
                        "--store", str(store.path))
    assert max(len(line) for line in out.splitlines()) > 200 and "\\n" in out, "newlines shown as \\n, one line a row"
    code, out, _ = _run(capsys, "sql", "SELECT * FROM range(50)", "--max-rows", "5", "--store", str(store.path))
    assert len(out.splitlines()) == 2 + 5 + 1 and "45 not shown" in out


@pytest.mark.parametrize("query, message", [
    ("SELEC 1", "Parser Error"),
    ("SELECT * FROM no_such_table", "no_such_table does not exist"),
    ("DELETE FROM runs", "read-only"),
    ("  ", "empty query"),
])
def test_sql_errors_are_one_line_and_exit_2(filled, capsys, query, message):
    store, _, _ = filled
    code, out, err = _run(capsys, "sql", query, "--store", str(store.path))
    assert code == 2 and out == "" and message in err
    assert err.count("\n") == 1 and err.startswith("codearcade: error: ")
    assert store.query("SELECT count(*) FROM runs")[0][0] == 2, "nothing was changed"


def test_sql_on_a_missing_store(tmp_path, capsys):
    code, _, err = _run(capsys, "sql", "SELECT 1", "--store", str(tmp_path / "none.duckdb"))
    assert code == 2 and "no store at" in err and err.count("\n") == 1
    assert not (tmp_path / "none.duckdb").exists(), "a query never creates a store"


def test_sql_reads_the_query_from_stdin(filled, capsys, monkeypatch):
    store, _, _ = filled
    monkeypatch.setattr(sys, "stdin", io.StringIO("SELECT count(*) AS runs FROM runs"))
    code, out, _ = _run(capsys, "sql", "-", "--csv", "--store", str(store.path))
    assert code == 0 and out == "runs\n2\n"


# ----------------------------------------------------------------------------------------------------- runs

def _columns(out: str) -> list[dict[str, str]]:
    """An aligned table's rows by heading (the dashes under each heading give its column)."""
    import re

    lines = out.splitlines()
    spans = [m.span() for m in re.finditer(r"-+", lines[1])]
    heads = [lines[0][a:b].strip() for a, b in spans]
    return [{h: line[a:b].strip() for h, (a, b) in zip(heads, spans)} for line in lines[2:]]


def test_runs_lists_every_run(filled, capsys):
    store, run_id, eval_id = filled
    code, out, _ = _run(capsys, "runs", "--store", str(store.path))
    rows = _columns(out)
    assert code == 0 and len(rows) == 2 and list(rows[0])[:3] == ["run", "created (UTC)", "kind"]
    assert eval_id.startswith(rows[0]["run"]) and run_id.startswith(rows[1]["run"]), "newest first, short ids"
    opt, ev = rows[1], rows[0]
    assert [opt[k] for k in ("kind", "game", "policy", "strategy", "feedback", "model", "status", "iterations")] == \
        ["optimize", "pong", "scaffold", "greedy", "staged", "openai/scripted", "finished", "2/2"]
    tokens = store.query("SELECT sum(input_tokens + output_tokens) FROM llm_calls")[0][0]
    assert int(opt["tokens"]) == tokens
    assert [ev[k] for k in ("kind", "game", "strategy", "model", "status", "iterations", "episodes", "tokens")] == \
        ["eval", "pong", "-", "-", "finished", "-", "3", "-"]

    code, out, _ = _run(capsys, "runs", "--json", "--store", str(store.path))
    records = {r["run_id"]: r for r in json.loads(out)}
    assert records[run_id]["iterations_done"] == 2 and records[run_id]["total_tokens"] == tokens
    returns = [r[0] for r in store.query("SELECT return FROM episodes WHERE run_id = ?", [eval_id])]
    assert records[eval_id]["best_score"] == pytest.approx(sum(returns) / 3)


def test_runs_on_an_empty_store(store, capsys):
    with store.write():
        pass
    code, out, _ = _run(capsys, "runs", "--store", str(store.path))
    assert code == 0 and "no runs" in out


# --------------------------------------------------------------------------------------------------- report

def test_report_of_an_optimize_run(filled, tmp_path, capsys):
    import matplotlib.image

    store, run_id, _ = filled
    out_dir = tmp_path / "rep"
    code, out, err = _run(capsys, "report", run_id[:20], "--store", str(store.path), "--out", str(out_dir))
    assert code == 0 and out.strip() == str(out_dir / "README.md")
    # off a terminal it says each stage as it starts (a long report is never a silent wait), on stderr
    assert err.splitlines() == ["codearcade report: reading the run from the store",
                                *(f"codearcade report: drawing {name}" for name in
                                  ("score.png", "code.png", "tokens.png", "lineage.png", "calls.png")),
                                "codearcade report: writing README.md"], err
    readme = (out_dir / "README.md").read_text()
    for name in ("score.png", "code.png", "tokens.png"):
        image = matplotlib.image.imread(out_dir / name)
        assert image.shape[0] >= 400 and image.shape[1] >= 800, name
        assert image[..., :3].std() > 0.05, f"{name} is not blank"
        assert f"]({name})" in readme
    assert f"run `{run_id}`" in readme and "| 2 | rejected" in readme and "| 1 | accepted" in readme
    assert "| 2 | parse | the reply contains neither" in readme, "the rejection reason is shown"
    assert "`eval_max_steps` | 200" in readme and "openai/scripted" in readme


@pytest.mark.parametrize("calls", [1, 2, 3, 7])
def test_the_calls_figure_counts_lanes_and_calls_in_whole_numbers(calls):
    """The call lanes and the calls in flight are counts: their axes never tick at 0.5 (a sweep of how many calls
    overlap, matplotlib's default locator put ticks at 0.5 for small counts)."""
    from datetime import datetime, timedelta

    from viewers.report_figures import calls_figure

    t0 = datetime(2026, 12, 3, 12)
    rows = [{"started_at": t0 + timedelta(seconds=i), "ended_at": t0 + timedelta(seconds=i + 5), "iteration": 1,
             "candidate": i, "purpose": "propose", "outcome": "accepted", "request_model": f"m{i % 2}"}
            for i in range(calls)]
    run = {"game": "pong", "run_id": "01RUN", "kind": "optimize", "model": "m0", "name": None}
    fig = calls_figure({"calls": rows, "run": run})
    lanes, flight = fig.axes[:2]
    for ax in (lanes, flight):
        low, high = ax.get_ylim()
        ticks = [t for t in ax.get_yticks() if min(low, high) <= t <= max(low, high)]
        assert ticks and all(float(t).is_integer() for t in ticks), (ax.get_ylabel(), ticks)


def test_report_of_an_eval_run_defaults_to_reports_dir(filled, tmp_path, capsys, monkeypatch):
    store, _, eval_id = filled
    monkeypatch.chdir(tmp_path)
    code, _, _ = _run(capsys, "report", eval_id, "--store", str(store.path))
    out_dir = tmp_path / "reports" / eval_id
    assert code == 0 and sorted(p.name for p in out_dir.iterdir()) == ["README.md", "score.png"]
    readme = (out_dir / "README.md").read_text()
    assert "## Episodes" in readme and readme.count("| truncated |") + readme.count("| terminated |") == 3


def test_a_killed_run_is_reported_interrupted_and_a_live_one_running(filled, tmp_path, capsys):
    """``runs`` and ``doctor`` said a killed run (status ``running``, no process holding its lock) was interrupted;
    ``report`` said it was running."""
    import duckdb

    from store.locks import run_lock

    store, opt_id, eval_id = filled
    copy = tmp_path / "s.duckdb"
    copy.write_bytes(store.path.read_bytes())
    con = duckdb.connect(str(copy))
    con.execute("UPDATE runs SET status = 'running', finished_at = NULL")  # as a kill -9 leaves them
    con.close()
    for run_id in (opt_id, eval_id):
        for live, shown in ((False, "interrupted"), (True, "running")):
            with run_lock(copy, run_id) if live else contextlib.nullcontext():
                code, _, err = _run(capsys, "report", run_id, "--out", str(tmp_path / run_id), "--store", str(copy))
                assert code == 0, err
                readme = (tmp_path / run_id / "README.md").read_text()
                assert f"status **{shown}**" in readme, (run_id, live, readme[:400])


def test_report_of_an_unknown_or_ambiguous_run(filled, capsys):
    store, run_id, _ = filled
    code, _, err = _run(capsys, "report", "NOPE", "--store", str(store.path))
    assert code == 2 and "no run NOPE" in err and "codearcade runs" in err
    code, _, err = _run(capsys, "report", "", "--store", str(store.path))
    assert code == 2
    code, _, err = _run(capsys, "report", run_id[:2], "--store", str(store.path))  # both ULIDs share a prefix
    assert code == 2 and "ambiguous" in err


def test_blame_of_a_missing_iteration_names_the_iterations_there_are(filled):
    """Iteration 2 stored no version of its own (an unusable reply): the range still reaches it."""
    from viewers.blame import blame

    store, run_id, _ = filled
    assert store.query("SELECT max(iteration) FROM policy_versions WHERE run_id = ?", [run_id])[0][0] == 1
    with pytest.raises(ValueError, match=r"has no iteration 7 \(iterations 0\.\.2\); give --iteration within them"):
        blame(store, run_id, iteration=7)


# ------------------------------------------------------------------------------- reading during a writing run

def _poll_counts(store_path: Path, writer: subprocess.Popen, query: str, capsys,
                 enough: Callable[[list], bool] | None = None, stop: Path | None = None) -> tuple[list, list[str]]:
    """Run `codearcade sql` in this process until the writer exits; (counts seen, failures after the first success).
    ``enough(seen)``: once true, the file ``stop`` is made, which tells the writer to finish (so that a slow reader
    on a busy machine is given as many commits as it needs, not a fixed time)."""
    seen: list[tuple[int, ...]] = []
    failures: list[str] = []
    while writer.poll() is None:
        code, out, err = _run(capsys, "sql", query, "--csv", "--store", str(store_path))
        if code == 0:
            seen.append(tuple(int(x) for x in out.splitlines()[1].split(",")))
            if enough is not None and stop is not None and enough(seen):
                stop.touch()
        elif seen or "no store at" not in err:  # before the writer's first commit there is no store yet
            failures.append(err)
    return seen, failures


@pytest.mark.slow
def test_queries_while_eval_writes(tmp_path, capsys):
    """A real `codearcade eval` writes 4 episodes; `codearcade sql` in this process and in subprocesses meanwhile."""
    path = tmp_path / "live.duckdb"
    writer = subprocess.Popen([EXE, "eval", str(EXAMPLES / "pong.py"), "--episodes", "4", "--max-steps", "2000",
                               "--workers", "2", "--store", str(path)], cwd=ROOT, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
    query = "SELECT (SELECT count(*) FROM episodes), (SELECT count(*) FROM steps), (SELECT count(*) FROM run_summary)"
    side = []  # a few separate `codearcade sql` processes, started while the run goes on
    try:
        while writer.poll() is None and not path.exists():
            time.sleep(0.05)
        for _ in range(2):
            side.append(subprocess.Popen([EXE, "sql", query, "--csv", "--store", str(path)], stdout=subprocess.PIPE,
                                         stderr=subprocess.PIPE, text=True))
        seen, failures = _poll_counts(path, writer, query, capsys)
    finally:
        writer.wait(120)
    assert writer.returncode == 0, writer.stderr.read()
    for p in side:
        out, err = p.communicate(60)
        assert p.returncode == 0, err
    assert not failures, failures[:3]
    assert seen == sorted(seen), "counts only grow"
    assert seen[0][0] < 4 and len(set(seen)) >= 2, f"the queries overlapped the writing: {sorted(set(seen))}"
    final = Store(path).query("SELECT count(*), sum(length) FROM episodes")[0]
    assert seen[-1][0] <= final[0] == 4 and seen[-1][1] <= final[1]


@pytest.mark.slow
def test_queries_while_a_writer_commits_many_times_a_second(tmp_path, capsys):
    """A harsher writer: small transactions through Store.write, 50 a second (an evaluation commits about twice a
    second), until the reader has seen the counts change five times (at most 3,000 commits); every query gets in
    between them and sees the counts grow, however slow the machine makes the reader."""
    path, stop = tmp_path / "busy.duckdb", tmp_path / "stop"
    script = ("import os, sys, time\nfrom store import Store\nfrom store.writer import put_blob\ns = Store(sys.argv[1])\n"
              "for i in range(3000):\n    if os.path.exists(sys.argv[2]):\n        break\n"
              "    with s.write() as con:\n        put_blob(con, 'note', f'note {i}')\n    time.sleep(0.02)\n")
    writer = subprocess.Popen([sys.executable, "-c", script, str(path), str(stop)], cwd=ROOT, stderr=subprocess.PIPE,
                              text=True)
    try:
        seen, failures = _poll_counts(path, writer, "SELECT count(*), 0 FROM blobs", capsys,
                                      enough=lambda seen: len(set(seen)) >= 5, stop=stop)
    finally:
        writer.wait(120)
    assert writer.returncode == 0, writer.stderr.read()
    assert not failures, failures[:3]
    assert seen == sorted(seen) and len(set(seen)) >= 5, seen[-10:]


def test_output_piped_into_head_ends_quietly(tmp_path):
    """`codearcade sql ... | head -1`: the reader closes the pipe early; the command exits 0 without a traceback."""
    store = tmp_path / "empty.duckdb"
    with Store(store).write():  # an empty store
        pass
    exe = os.path.join(os.path.dirname(sys.executable), "codearcade")
    done = subprocess.run(f"'{exe}' sql 'SELECT * FROM range(200000)' --csv --store '{store}' | head -1; "
                          "exit ${PIPESTATUS[0]}", shell=True, executable="/bin/bash", cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert done.stdout == "range\n" and done.stderr == "" and done.returncode == 0, done.stderr[-500:]


@pytest.mark.slow
def test_a_reader_of_stderr_that_goes_away_ends_nothing(tmp_path):
    """`codearcade eval ... 2>&1 >/dev/null | head -1`: the progress lines' reader leaves after the first. The next
    progress line's BrokenPipeError ended the good run as failed (raised in the episodes' message loop, it was taken
    for a worker's malformed message, and one episode was stored crashed), and the command still exited 0. Now a
    line that cannot be written is dropped: the run is finished, its episodes played out, exit 0."""
    store = tmp_path / "s.duckdb"
    exe = os.path.join(os.path.dirname(sys.executable), "codearcade")
    done = subprocess.run(f"'{exe}' eval games/scaffolds/pong.py --episodes 6 --workers 1 --max-steps 300 "
                          f"--store '{store}' 2>&1 >/dev/null | head -1; exit ${{PIPESTATUS[0]}}", shell=True,
                          executable="/bin/bash", cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, (done.stdout, done.stderr[-500:])
    assert done.stdout.count("\n") == 1 and "episodes to play" in done.stdout, done.stdout
    assert Store(store).query("SELECT status, error FROM runs") == [("finished", None)]
    assert Store(store).query("SELECT DISTINCT end_reason FROM episodes") == [("truncated",)]


def test_replay_refuses_a_run_still_running_and_audit_one_without_iterations(filled, tmp_path, capsys):
    """A replay of a live run stopped where its record then ended and stored itself as 'interrupted'; an audit of
    a run with nothing to audit said so and exited 0."""
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.loop import start_run
    from store.locks import run_lock

    store, opt_id, _ = filled
    copy = Store(tmp_path / "s.duckdb")
    copy.path.write_bytes(store.path.read_bytes())
    runs_before = copy.query("SELECT count(*) FROM runs")[0][0]
    with run_lock(copy.path, opt_id):
        code, _, err = _run(capsys, "replay", opt_id, "--store", str(copy.path))
        assert code == 2 and "is still running: replay it once it has finished or stopped" in err, err
        code, out, err = _run(capsys, "optimize", "--resume", opt_id, "--iterations", "3", "--store",
                              str(copy.path))
        assert code == 2 and "is being worked on by another process" in err and "resumed" not in out + err, \
            out + err
    assert copy.query("SELECT count(*) FROM runs")[0][0] == runs_before, "no replay run was made"
    empty = start_run(OptimizeConfig(game="pong", iterations=1), copy, "scripted")
    code, out, err = _run(capsys, "audit", empty, "--json", "--store", str(copy.path))
    assert code == 2 and "has no iteration to audit" in err and out == "", out + err
    none_planned = start_run(OptimizeConfig(game="pong", iterations=0), copy, "scripted")
    code, out, _ = _run(capsys, "runs", "--store", str(copy.path))
    row = next(line for line in out.splitlines() if line.startswith(none_planned[:8]))
    assert " 0/0 " in f" {row} " and " 0/1 " in out, out  # planned 0 was shown as "?"


def test_resume_takes_the_runs_own_settings_given_again_and_refuses_changed_ones(filled):
    """A resume named with the run's own command line (``--game pong`` again) was refused as a change."""
    from pipeline.optimizer.loop import plan_resume

    store, opt_id, _ = filled
    recorded = json.loads(store.query("SELECT config FROM runs WHERE run_id = ?", [opt_id])[0][0])
    assert recorded["game"] == "pong"
    for given in ({"game": "pong"}, {"game": "pong", "seed": recorded["seed"]}, {"iterations": 5, "game": "pong"}):
        plan = plan_resume(store, opt_id, dict(given))
        assert plan.config.game == "pong" and plan.config.iterations == given.get("iterations", 2), given
    for given, flag in (({"game": "breakout"}, "--game"), ({"seed": recorded["seed"] + 1}, "--seed"),
                        ({"policy": str(EXAMPLES / "pong.py")}, "policy")):
        with pytest.raises(ValueError, match=f"{flag} cannot change when resuming"):
            plan_resume(store, opt_id, dict(given))


def test_the_report_headline_gives_each_side_of_the_audit_its_score_or_its_forfeit(filled):
    """The headline's held-out audit: the best's score and the starter's, each with its interval or the word
    forfeit (a starter that forfeited its audit showed as "–", read as not audited), for each side that forfeits."""
    from viewers.report import collect, render_markdown

    store, run_id, _ = filled
    data = collect(store, run_id)
    assert {(a["role"], a["protocol"]) for a in data["audits"]} >= {("best", "standard"), ("starter", "standard")}
    for best_forfeits in (False, True):
        for starter_forfeits in (False, True):
            audits = [{**a, "score": None, "forfeit": "RuntimeError at step 251 (policy_error)"}
                      if a["protocol"] == "standard" and {"best": best_forfeits, "starter": starter_forfeits}[a["role"]]
                      else a for a in data["audits"]]
            best = next(a for a in audits if a["role"] == "best" and a["protocol"] == "standard")
            summary = {**data["summary"], "audit_score": best["score"], "overfit": None}
            headline = next(line for line in render_markdown({**data, "audits": audits, "summary": summary},
                                                             {}).splitlines() if "held-out audit" in line)
            said = headline.split("held-out audit ")[1]
            assert said.startswith("**forfeit**" if best_forfeits else "**"), headline
            if not best_forfeits:
                assert "n=" in said.split("(standard protocol")[0], headline
            starter = said.split("starter ")[1]
            assert starter.startswith("forfeit)") if starter_forfeits else "n=" in starter, headline
            assert "–" not in said, headline
