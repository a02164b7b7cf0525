"""The optimization loop against a scripted model behind a real HTTP endpoint, called through litellm."""

from __future__ import annotations

import json

import pytest

from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from tests.conftest import COMPETENT_PREDICT, COMPETENT_REPLY, COMPETENT_SELECT, json_reply

TABLES = ("runs", "iterations", "policy_versions", "episodes", "steps", "nodes", "llm_calls", "feedback")


def _client(model, **kwargs):
    return LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05, **kwargs)


def _config(**kwargs):
    defaults = dict(game="pong", iterations=3, eval_max_steps=4000, workers=2, token_budget=8000, rng_key="optimize",
                    repairs=0)  # one scripted reply per update (repairs: tests/test_repairs.py)
    return OptimizeConfig(**{**defaults, **kwargs})


@pytest.mark.slow
def test_competent_update_makes_the_score_jump(store, scripted):
    model = scripted([COMPETENT_REPLY, "Sorry, I cannot help with that.",
                      json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return obs['Nope']\n"})])
    result = optimize(_config(), store, _client(model))
    assert result.status == "finished"
    rows = store.query("SELECT iteration, update_status, score, best_iteration FROM iterations ORDER BY iteration")
    assert [r[0] for r in rows] == [0, 1, 2, 3], "the starter's evaluation, then 3 optimization iterations"
    assert [r[1] for r in rows] == ["initial", "accepted", "rejected", "rejected"]
    assert rows[0][2] <= -15 and rows[1][2] >= 15, rows
    assert rows[2][2] == rows[1][2] and rows[3][3] == 1
    for table in TABLES:
        assert store.query(f"SELECT count(*) FROM {table}")[0][0] > 0, table
    # the prompts the loop sent are the ones stored, and the next feedback carries the rejection reasons
    assert len(model.requests()) == 3
    feedback = dict(store.query("SELECT iteration, text FROM feedback"))
    assert "not usable" in feedback[2] and "KeyError" in feedback[3] and "'Nope'" in feedback[3]
    calls = store.query("SELECT iteration, input_tokens, output_tokens, request_model, provider_name, error_type "
                        "FROM llm_calls ORDER BY iteration")
    assert [c[0] for c in calls] == [1, 2, 3] and all(c[1] > 0 and c[2] > 0 for c in calls)
    assert calls[0][3] == "openai/scripted" and calls[0][4] == "openai" and calls[0][5] is None
    versions = store.query("SELECT iteration, produced_by, validation, validation_error FROM policy_versions "
                           "ORDER BY iteration, produced_by")
    assert versions[0][:3] == (0, "initial", "accepted") and versions[1][:3] == (1, "llm", "accepted")
    assert versions[-1][2] == "rejected" and "KeyError" in versions[-1][3]
    # the paper's Table 3 from one query
    table3 = store.query("SELECT i.iteration, v.loc, v.complexity, v.max_if_depth FROM iterations i JOIN policy_versions v "
                         "ON v.run_id = i.run_id AND v.policy_version_id = i.policy_version_id AND v.validation = 'accepted' "
                         "ORDER BY i.iteration")
    assert table3[1][2] > table3[0][2], "the competent version is more complex than the starter"


@pytest.mark.slow
def test_both_reply_formats_and_hostile_candidates(store, scripted):
    fenced = f"Here you go:\n```python\n{COMPETENT_SELECT}```\nand\n```python\n{COMPETENT_PREDICT}```"
    replies = [
        fenced,
        json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    while True:\n        pass\n"}),
        json_reply({"select_action": "def select_action(self, obs):\n    return 0\n"}),
        json_reply({"fly": "def fly(self):\n    return 0\n"}),
        json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    import os\n    return 0\n"}),
        json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return 7\n"}),
    ]
    model = scripted(replies)
    result = optimize(_config(iterations=6, eval_max_steps=300, call_time_limit_s=0.3), store, _client(model))
    assert result.status == "finished"
    statuses = [r[0] for r in store.query("SELECT update_status FROM iterations ORDER BY iteration")]
    assert statuses == ["initial", "accepted", "rejected", "rejected", "rejected", "rejected", "rejected"]
    feedback = [r[0] for r in store.query("SELECT text FROM feedback ORDER BY iteration")]
    assert "time limit" in feedback[2]
    assert "must keep its parameters" in feedback[3]
    assert "does not have" in feedback[4] and "predict_ball_trajectory, select_action" in feedback[4]
    assert "import of 'os'" in feedback[5]
    assert "illegal action 7" in feedback[6]


@pytest.mark.slow
def test_transient_errors_are_retried_and_fatal_ones_stop_cleanly(store, scripted):
    model = scripted([{"status": 503, "times": 2}, COMPETENT_REPLY, {"status": 401}])
    result = optimize(_config(iterations=3, eval_max_steps=200), store, _client(model))
    assert result.status == "failed" and "AuthenticationError" in result.error
    calls = store.query("SELECT iteration, attempts, error_type FROM llm_calls ORDER BY iteration")
    assert calls[0] == (1, 3, None), "two 503s, then the reply"
    assert calls[1][0] == 2 and calls[1][2] == "AuthenticationError"
    assert store.query("SELECT max(iteration) FROM iterations")[0][0] == 1
    assert store.query("SELECT status, error FROM runs")[0][0] == "failed"


@pytest.mark.slow
def test_rollback_after_a_regression(store, scripted):
    bad = json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return 2\n"})
    model = scripted([COMPETENT_REPLY, bad, COMPETENT_REPLY])
    optimize(_config(iterations=3, eval_max_steps=1500), store, _client(model))
    rows = store.query("SELECT iteration, policy_version_id, base_version_id, rolled_back, best_iteration "
                       "FROM iterations ORDER BY iteration")
    assert rows[2][3] is True, "iteration 2 regressed below the best"
    assert rows[3][2] == rows[1][1], "iteration 3 starts again from iteration 1's version"
    assert rows[3][1] == rows[1][1] and rows[3][3] is False, "the same code as the best: unchanged, no rollback"
    assert store.query("SELECT count(*) FROM policy_versions WHERE produced_by = 'rollback'")[0][0] == 1
    prompt = model.requests()[2][1]["content"]
    assert "rolled back" in prompt


@pytest.mark.slow
def test_offline_json_shape_of_prompt_sections(store, scripted):
    model = scripted([json_reply({})])
    optimize(_config(iterations=1, eval_max_steps=200, token_budget=4000), store, _client(model))
    system, user = model.requests()[0]
    for section in ("#Instruction", "#Code", "#Documentation", "#Variables", "#Constraints", "#Inputs", "#Others",
                    "#Outputs", "#Feedback", "#Memory"):
        assert section in user["content"]
    assert store.query("SELECT update_status FROM iterations WHERE iteration = 1")[0][0] == "unchanged"
    counted = store.query("SELECT prompt_tokens_counted FROM llm_calls")[0][0]
    assert counted <= 4000
    stored = store.query("SELECT b.text FROM llm_calls c JOIN blobs b ON b.hash = c.prompt_hash")[0][0]
    assert json.loads(stored) == [system, user], "the stored prompt is exactly what was sent"


def test_bad_options_are_clear():
    from store import Store

    with pytest.raises(ValueError, match="--feedback"):
        optimize(OptimizeConfig(game="pong", feedback="vibes"), Store("/nonexistent/x.duckdb"), None)


@pytest.mark.slow
def test_rollout_only_feedback_for_the_ablation(store, scripted):
    model = scripted([json_reply({})])
    optimize(_config(iterations=1, eval_max_steps=200, feedback="rollout"), store, _client(model))
    rows = store.query("SELECT iteration, mode, score, text FROM feedback ORDER BY iteration")
    train = dict(store.query("SELECT iteration, train_return FROM iterations"))
    assert all(r[1] == "rollout" and r[2] == train[r[0]] and "Training rollout" in r[3] for r in rows)
    assert "Evaluation (full game)" not in model.requests()[0][1]["content"].split("#Feedback")[1]


@pytest.mark.slow
def test_offline_default_model_runs_the_loop(tmp_path):
    """The README's main job, shortened: no --model starts SmolLM2 locally and calls it through litellm."""
    import os
    import subprocess
    import sys

    from tests.conftest import ROOT

    exe = os.path.join(os.path.dirname(sys.executable), "codearcade")
    store_path = tmp_path / "offline.duckdb"
    # no held-out audit: its 12 games at the run's end are tests/test_audit.py's, and nothing here looks at them
    done = subprocess.run([exe, "optimize", "--game", "pong", "--iterations", "1", "--eval-max-steps", "300",
                           "--token-budget", "2200", "--max-tokens", "96", "--audit-episodes", "0",
                           "--store", str(store_path), "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "only exercises the pipeline" in done.stderr
    result = json.loads(done.stdout)
    assert result["status"] == "finished" and [i["iteration"] for i in result["iterations"]] == [0, 1]
    from store import Store

    call = Store(store_path).query("SELECT request_model, provider_name, input_tokens, output_tokens, error_type "
                                   "FROM llm_calls")
    assert call[0][0] == "openai/smollm2-135m-instruct" and call[0][2] > 0 and call[0][4] is None


@pytest.mark.parametrize("game", ["pong", "breakout", "space_invaders"])
def test_a_budget_no_prompt_fits_is_refused_before_anything_plays(store, scripted, game):
    """``--token-budget 500`` was found too small only after iteration 0 had played (minutes at the authors'
    caps), and the run was left failed. The prompt's fixed part (code, instructions, documentation) is counted
    first now: a budget below it is refused with the tokens it needs, before a run is made; a budget that fits it
    is what the loop's own check counts the same way (``smallest_prompt_tokens`` is a lower bound of it)."""
    from pipeline.llm.tokens import TokenCounter
    from pipeline.optimizer.prompt import PromptBudgetError, smallest_prompt_tokens
    from pipeline.optimizer.task import resolve_start, task_settings

    model = scripted([COMPETENT_REPLY])
    config = _config(game=game, token_budget=500, iterations=1)
    with pytest.raises(PromptBudgetError, match=r"alone need (\d+) tokens, more than the budget of 500") as refused:
        optimize(config, store, _client(model))
    assert not store.exists() or store.query("SELECT count(*) FROM runs") == [(0,)], "no run was made"
    assert model.requests() == []
    info, name = resolve_start(config)
    need = smallest_prompt_tokens(name, task_settings(info, name).instruction, info, TokenCounter(model.model), 1.0)
    assert f"need {need} tokens" in str(refused.value)


@pytest.mark.parametrize("command", ["optimize", "batch"])
def test_a_budget_no_prompt_fits_is_refused_before_anything_plays_whichever_command_makes_the_run(
        tmp_path, scripted, command):
    """The command line and a batch make their runs themselves, and the check above ran only in ``optimize()``:
    ``codearcade optimize --token-budget 600`` made its run, played iteration 0 (minutes at the authors' caps) and
    failed at iteration 1's prompt; a batch's run the same. Now each is refused before its run is made, with the
    tokens the prompt needs, and nothing is asked of the model."""
    from tests.conftest import run_main

    model = scripted([COMPETENT_REPLY])
    store = tmp_path / "s.duckdb"
    if command == "optimize":
        code, out, err = run_main("optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base,
                                  "--token-budget", 600, "--iterations", 1, "--store", store)
        assert code == 2 and "alone need" in err and "more than the budget of 600" in err, err
    else:
        (tmp_path / "e.toml").write_text(f'[defaults]\nmodel = "{model.model}"\napi_base = "{model.api_base}"\n'
                                         'token_budget = 600\niterations = 1\n[matrix]\ngame = ["pong"]\n')
        code, out, err = run_main("batch", tmp_path / "e.toml", "--store", store)
        assert code != 0 and "alone need" in err, err
    played = duckdb_count(store, "SELECT count(*) FROM episodes") if store.exists() else 0
    assert played == 0 and model.requests() == [], "no episode played, no call made"
    if command == "optimize":
        assert not store.exists() or duckdb_count(store, "SELECT count(*) FROM runs") == 0, "no run was made"


def duckdb_count(path, sql: str) -> int:
    from store import Store

    return Store(path).query(sql)[0][0]


@pytest.mark.slow
@pytest.mark.parametrize("budget, given", [("--max-llm-calls", "1"), ("--max-total-tokens", "9000"),
                                           ("--max-wall", "0.0001")])
def test_a_run_stopped_by_a_budget_says_a_command_that_goes_on_with_a_larger_one(budget, given, tmp_path, scripted,
                                                                                  capsys, monkeypatch):
    """The line said ``codearcade optimize --resume RUN --max-... --store S``: pasted, the parser refused
    ``--max-...`` and suggested --max-wall, whatever budget had stopped the run. It names the budget now, twice
    what was spent, and runs as printed, from anywhere."""
    import re
    import shlex

    from pipeline.cli import main
    from store import Store

    model = scripted([COMPETENT_REPLY] * 6)
    store = Store(tmp_path / "s.duckdb")
    code = main(["optimize", "--game", "pong", "--model", model.model, "--api-base", model.api_base, "--iterations",
                 "3", "--eval-max-steps", "200", "--rollout-steps", "40", "--audit-episodes", "0", "--repairs", "0",
                 budget, given, "--store", str(store.path)])
    err = capsys.readouterr().err
    assert code == 0 and store.query("SELECT status FROM runs") == [("budget",)], err
    (command,) = re.findall(r"continue it with a larger one: `([^`]*)`", err)
    words = shlex.split(command)
    doubled = f"{float(given) * 2:g}" if "." in given else str(int(given) * 2)
    assert words[2:6] == ["--resume", words[3], budget, doubled] and words[-2:] == ["--store", str(store.path)], words
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(words[1:]) == 0, capsys.readouterr().err
    setting = {"--max-llm-calls": "max_llm_calls", "--max-total-tokens": "max_total_tokens",
               "--max-wall": "max_wall_minutes"}[budget]
    assert store.query(f"SELECT status IN ('budget', 'finished'), config->>'$.{setting}' FROM runs") == [
        (True, doubled if "." not in given else str(float(doubled)))]


_OPENS_THE_FILE = """
import sys, time
import duckdb
end = time.monotonic() + float(sys.argv[2])
while True:
    try:
        duckdb.connect(sys.argv[1], read_only=True).close()
        print("opened")
        break
    except duckdb.Error:  # locked by the run's process
        if time.monotonic() > end:
            print("locked")
            break
        time.sleep(0.05)
"""


@pytest.mark.slow
def test_other_processes_open_the_store_while_a_clients_first_use_waits(store, scripted, monkeypatch):
    """A client's first use waits for litellm's import (2-5 s of CPU, on a thread of its own since the run began), and
    the run held the store's file all that while: a batch's progress, `codearcade runs` and the batch's other runs
    waited for it ("is locked by another process"). The run lets the file go before that wait, as it does for the
    model's reply. Checked by its effect: while the first use waits, another process opens the file."""
    import subprocess
    import sys

    seen = []
    first_use = LiteLLMClient.request_params

    def request_params(self):
        if not seen:  # the client's first use, the moment the import is waited for
            seen.append(subprocess.run([sys.executable, "-c", _OPENS_THE_FILE, str(store.path), "10"],
                                       capture_output=True, text=True, timeout=60).stdout.strip())
        return first_use(self)

    monkeypatch.setattr(LiteLLMClient, "request_params", request_params)
    model = scripted([COMPETENT_REPLY])
    result = optimize(_config(iterations=1, eval_max_steps=60, rollout_steps=30), store, _client(model))
    assert result.status == "finished", result.error
    assert seen == ["opened"]


@pytest.mark.parametrize("cap, budget", [(-448, None), (0, None), (384, None), (499, None), (500, 500), (4266, 4266),
                                         (20_000, 16_000)])
def test_a_model_s_context_holds_the_budget_or_says_which_setting_leaves_no_room(cap, budget):
    """``--max-tokens 9000`` with the offline model (8,192 tokens of context) said "--token-budget must be at least
    500, got -448", a setting the user had not given; now the reply's room is named. A cap the least budget fits
    holds the budget to it; a larger one leaves it."""
    from pipeline.optimizer.config import fit_to_model

    config = OptimizeConfig(game="pong", max_tokens=9000)
    if budget is None:
        with pytest.raises(ValueError, match=f"^--max-tokens 9000 leaves the model's context room for a prompt of "
                                             f"{max(cap, 0):,} tokens, less than the least --token-budget"):
            fit_to_model(config, cap)
    else:
        fit_to_model(config, cap)
        assert config.token_budget == budget
