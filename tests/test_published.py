"""The paper's table from a store: the authors' published figures (each game's module) in ``published_scores``, and
``examples/benchmarks.sql`` over a store made by a real short batch of ``examples/benchmarks.toml``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib

import pytest

from games import GAMES
from store.published import published_rows, refresh_published
from store.statistics import mean_interval
from tests.conftest import COMPETENT_REPLY, ROOT

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")


def test_every_curated_game_publishes_the_authors_figures():
    rows = {(game, setting): (score, stderr, trials, horizon)
            for game, _, setting, horizon, trials, score, stderr in published_rows()}
    assert {game for game, _ in rows} == set(GAMES)
    assert rows["pong", "paper"] == (21.0, None, 1, 400) and rows["breakout", "paper"][0] == 353.0
    assert rows["space_invaders", "h1"] == (570.0, 0.0, 4, 1), "their aggregate has four trials there"
    for game in ("asterix", "enduro", "freeway", "qbert", "seaquest"):
        assert (game, "h100") in rows and rows[game, "h100"][3] == GAMES[game].task.rollout_steps
    for game in ("pong", "breakout", "space_invaders"):
        assert rows[game, "default"][3] == GAMES[game].task.rollout_steps


def test_the_table_follows_the_game_modules(store):
    """published_scores holds exactly the modules' figures after a process first writes; a store whose copy
    differs (an older codearcade's figures) is rewritten, one that agrees is left alone."""
    from store import Store

    with store.write():
        pass
    columns = "game, source, setting, horizon, trials, score, stderr"
    assert set(store.query(f"SELECT {columns} FROM published_scores")) == set(published_rows())
    with store.write() as con:
        con.execute("UPDATE published_scores SET score = 1 WHERE game = 'pong' AND setting = 'paper'")
        con.execute("DELETE FROM published_scores WHERE game = 'qbert'")
    again = Store(store.path)
    with again.write():
        pass
    assert set(again.query(f"SELECT {columns} FROM published_scores")) == set(published_rows())
    with again.write() as con:
        assert refresh_published(con) is False, "nothing to rewrite"


@pytest.mark.slow
def test_benchmarks_sql_over_a_real_short_batch(tmp_path, store, scripted):
    """examples/benchmarks.toml cut to two games and one iteration, the scripted model standing in; then
    examples/benchmarks.sql prints our best beside theirs, for every game, and the protocol each was played
    under (Breakout as in the file: the authors' one-life protocol)."""
    model = scripted([COMPETENT_REPLY])
    data = tomllib.loads((ROOT / "examples" / "benchmarks.toml").read_text())
    assert data["name"] == "eight-games"
    defaults = data["defaults"]
    one_life = {run["game"]: run.get("one_life", False) for run in data["run"]}
    assert one_life["breakout"] == "continue" and one_life["pong"] is False
    path = tmp_path / "benchmarks.toml"
    path.write_text(f'name = "{data["name"]}"\n[defaults]\niterations = 1\nmemory = {defaults["memory"]}\n'
                    f'eval_episodes = 1\neval_max_steps = 300\nrng_key = "published"\nmodel = "{model.model}"\napi_base = "{model.api_base}"\n'
                    '[[run]]\ngame = "pong"\n[[run]]\ngame = "breakout"\none_life = "continue"\n')
    done = subprocess.run([EXE, "batch", str(path), "--store", str(store.path), "--workers", "2"], cwd=ROOT,
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr + done.stdout
    sql = (ROOT / "examples" / "benchmarks.sql").read_text()
    printed = subprocess.run([EXE, "sql", sql, "--store", str(store.path), "--json"], cwd=ROOT,
                             capture_output=True, text=True, timeout=300)
    assert printed.returncode == 0, printed.stderr
    table = {row["game"]: row for row in json.loads(printed.stdout)}
    assert set(table) == set(GAMES), "every game's published figures, ours where the batch ran it"
    best = dict(store.query("SELECT r.game, max(i.score) FROM runs r JOIN iterations i USING (run_id) GROUP BY 1"))
    for game, horizon, theirs, protocol in (("pong", 400, 12.0, "whole games"),
                                            ("breakout", 300, 123.0, "lives of one game")):
        row = table[game]
        assert row["runs"] == 1 and row["iterations"] == 1 and row["horizon"] == horizon
        # one run: the mean has no interval yet (ci_text prints it alone), the IQM is the one value
        assert row["best"] == best[game]
        assert row["mean_best"] == row["iqm_best"] == mean_interval([best[game]]).text(), row
        assert row["protocol"] == protocol and row["theirs"] == theirs
        audit = store.query("SELECT s.audit_score FROM run_summary s JOIN runs r USING (run_id) WHERE r.game = ?",
                            [game])[0][0]
        assert audit is not None and row["audit"] == mean_interval([audit]).text(), row
        assert row["audit"].endswith(" (n=1: too few for an interval)"), row
        assert row["overfit"] in (0, 1), row
    starter = store.query("SELECT i.score FROM runs r JOIN iterations i USING (run_id) "
                          "WHERE r.game = 'pong' AND i.iteration = 0")[0][0]
    assert table["pong"]["best"] > starter, "the best is the accepted competent policy's, not the starter's"
    assert table["pong"]["paper"] == "21.0" and table["pong"]["h1"] == "5.8 ± 2.5"
    assert table["asterix"]["runs"] is None and table["asterix"]["h100"] == "3466.7 ± 2107.7"
