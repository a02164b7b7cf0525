"""Real models, end to end: `codearcade optimize` through litellm's own adapter for each provider's wire
protocol (tests/scripted_llm.py speaks Anthropic Messages, OpenAI chat, Ollama and Gemini), honest failures,
credentials, budgets, resume semantics and the dry run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from pipeline.llm.providers import KNOWN_PROVIDERS, PROVIDER_KEYS, REPLY_SCHEMA, MissingCredentialsError, \
    check_credentials, with_cache_breakpoint
from tests.conftest import COMPETENT_REPLY, ROOT, pong_policy

EXE = os.path.join(os.path.dirname(sys.executable), "codearcade")
KEYS = {"ANTHROPIC_API_KEY": "sk-ant-scripted", "GEMINI_API_KEY": "gm-scripted", "MISTRAL_API_KEY": "ms-scripted"}
# no held-out audit: it plays 12 whole games at a run's end (~9 s, most of a 1-iteration run), which no test
# here looks at (tests/test_audit.py does)
FAST = ("--rollout-steps", "60", "--workers", "2", "--audit-episodes", "0")


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if not k.endswith("_API_KEY")}
    env.update(KEYS, CODEARCADE_LLM_BACKOFF_S="0.05", LITELLM_LOCAL_MODEL_COST_MAP="True", **extra)
    return env


def _cli(*argv, env=None, timeout=600):
    return subprocess.run([EXE, *argv], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          env=env or _env())


def _optimize(store, model, provider, name, *extra, env=None):
    route, base = model.route(provider, name)
    return _cli("optimize", "--game", "pong", "--model", route, "--api-base", base, "--store", str(store.path),
                *extra, env=env)


def _runs(store):
    return store.query("SELECT run_id, status, error FROM runs ORDER BY created_at")


PROVIDERS = [
    # (provider, model name, priced by litellm)
    ("anthropic", "claude-sonnet-4-5", True),
    ("openai", "gpt-4o", True),
    ("ollama_chat", "qwen2.5-coder", False),
    ("hosted_vllm", "Qwen2.5-Coder-7B-Instruct", False),
    ("gemini", "gemini-2.5-pro", True),
]


@pytest.mark.slow
@pytest.mark.parametrize("provider,name,priced", PROVIDERS, ids=[p[0] for p in PROVIDERS])
def test_each_provider_protocol_wins_pong_in_one_iteration(store, scripted, provider, name, priced):
    model = scripted([COMPETENT_REPLY])
    done = _optimize(store, model, provider, name, "--iterations", "1", *FAST)
    assert done.returncode == 0, done.stderr
    scores = store.query("SELECT iteration, score, update_status FROM iterations ORDER BY iteration")
    assert scores[0][1] < 0 and scores[1][1] >= 15 and scores[1][2] == "accepted", scores
    (request,) = model.raw_requests()
    assert request["protocol"] == {"anthropic": "anthropic", "ollama_chat": "ollama", "gemini": "gemini"}.get(
        provider, "openai")
    call = store.query("SELECT provider_name, request_model, request_params, input_tokens, output_tokens, cost_usd, "
                       "finish_reasons, error_type, reply_reading FROM llm_calls")
    assert len(call) == 1
    provider_name, request_model, params, input_tokens, output_tokens, cost, finish, error, reading = call[0]
    assert provider_name == provider and request_model == f"{provider}/{name}" and error is None
    # the reply schema reached the server in the provider's own form, and litellm's adapter read the structured
    # reply back (Anthropic's is a tool_use block): the reply was the schema's JSON object as is
    assert reading == "structured"
    assert input_tokens > 1000 and output_tokens > 50
    assert finish == ["stop"]
    assert (cost is not None and cost > 0) == priced
    params = json.loads(params)
    body = request["body"]
    if provider == "anthropic":
        # Anthropic takes no seed: it is neither sent nor recorded as sent; the key travels in x-api-key
        assert "seed" not in body and "seed" not in params
        assert request["headers"]["x-api-key"] == KEYS["ANTHROPIC_API_KEY"]
        assert body["max_tokens"] == params["max_tokens"] == 4096
        assert body["system"][0]["cache_control"] == {"type": "ephemeral"}
        # said once, on its own line before the call's wait is shown (litellm says it at the first call)
        lines = done.stderr.splitlines()
        notice = [i for i, line in enumerate(lines) if "no 'seed' parameter" in line]
        assert len(notice) == 1 and lines[notice[0]] == \
            f"codearcade: {provider}/{name} takes no 'seed' parameter; it is not sent", done.stderr
        assert notice[0] < lines.index("iteration 1: waiting for anthropic/claude-sonnet-4-5"), done.stderr
        # a forced tool call whose input is the reply, answered by a tool_use block
        assert body["tool_choice"] == {"type": "tool", "name": body["tools"][0]["name"]}
        assert body["tools"][0]["input_schema"] == REPLY_SCHEMA and "response_format" not in body
        assert request["reply_blocks"] == ["tool_use"]
    elif provider == "ollama_chat":
        assert body["options"]["seed"] == params["seed"] == 0 and body["stream"] is False
        assert body["format"] == REPLY_SCHEMA
    elif provider == "gemini":
        assert request["headers"]["x-goog-api-key"] == KEYS["GEMINI_API_KEY"]
        assert body["generationConfig"]["seed"] == 0
        assert body["generationConfig"]["response_mime_type"] == "application/json"
        assert body["generationConfig"]["response_json_schema"] == REPLY_SCHEMA
    else:
        assert body["seed"] == params["seed"] == 0 and body["max_tokens"] == params["max_tokens"]
        assert body["response_format"] == {"type": "json_schema", "json_schema": {
            "name": "policy_update", "schema": REPLY_SCHEMA, "strict": False}}
    assert params["response_format"]["json_schema"]["schema"] == REPLY_SCHEMA, "recorded as litellm was given it"


@pytest.mark.slow
def test_reasoning_model_gets_max_completion_tokens_and_no_temperature(store, scripted):
    model = scripted(["Nothing to change."])
    done = _optimize(store, model, "openai", "o3-mini", "--iterations", "1", "--eval-max-steps", "200", *FAST)
    assert done.returncode == 0, done.stderr
    body = model.raw_requests()[0]["body"]
    assert body["max_completion_tokens"] == 4096 and "max_tokens" not in body and "temperature" not in body
    params = json.loads(store.query("SELECT request_params FROM llm_calls")[0][0])
    assert "temperature" not in params and params["max_completion_tokens"] == 4096


def test_the_reply_schema_goes_where_the_model_can_take_one():
    from pipeline.llm.client import LiteLLMClient

    for model, api_base, structured in [("openai/gpt-4o", None, True), ("anthropic/claude-sonnet-4-5", None, True),
                                        ("gemini/gemini-2.5-pro", None, True), ("ollama_chat/qwen2.5-coder", None, True),
                                        ("hosted_vllm/any", "http://127.0.0.1:1/v1", True),
                                        ("openai/own-model", "http://127.0.0.1:1/v1", True),
                                        # hosted models litellm does not know to take a schema: the prompt asks
                                        ("groq/llama-3.1-70b-versatile", None, False), ("xai/grok-2", None, False)]:
        client = LiteLLMClient(model, api_base=api_base)
        assert client.structured == structured, model
        assert ("response_format" in client.request_params()) == structured, model


@pytest.mark.slow
def test_a_server_that_refuses_the_reply_schema_is_asked_again_without_it(store, scripted):
    """An OpenAI-compatible server of the user's own that does not take response_format: the call is made again
    without it (not counted as a retry), and every later call leaves it out; llm_calls records what was sent."""
    refusal = {"status": 400, "message": "Unsupported parameter: 'response_format' is not supported here"}
    model = scripted([refusal, COMPETENT_REPLY, "No change."])
    done = _optimize(store, model, "openai", "my-local-model", "--iterations", "2", "--eval-max-steps", "300",
                     "--repairs", "0", *FAST)  # one call per update: the bodies below are the updates
    assert done.returncode == 0, done.stderr
    bodies = [r["body"] for r in model.raw_requests()]
    assert ["response_format" in b for b in bodies] == [True, False, False]
    calls = store.query("SELECT iteration, attempts, reply_reading, request_params FROM llm_calls ORDER BY iteration")
    assert [c[:3] for c in calls] == [(1, 2, "parsed"), (2, 1, "unusable")]
    assert all("response_format" not in json.loads(c[3]) for c in calls)
    assert store.query("SELECT update_status FROM iterations WHERE iteration = 1") == [("accepted",)]


@pytest.mark.slow
def test_anthropic_prompt_caching_is_recorded(store, scripted):
    model = scripted(["No change this time."])
    done = _optimize(store, model, "anthropic", "claude-sonnet-4-5", "--iterations", "2", "--eval-max-steps", "200",
                     *FAST)
    assert done.returncode == 0, done.stderr
    calls = store.query("SELECT iteration, cached_input_tokens, cache_creation_input_tokens FROM llm_calls "
                        "ORDER BY iteration")
    assert calls[0][2] > 500 and calls[0][1] == 0, "the first call writes the stable prefix to the cache"
    assert calls[1][1] == calls[0][2], "the second call reads the same prefix back"
    usage = store.query("SELECT cached_input_tokens FROM llm_usage")[0][0]
    assert usage == calls[1][1]


def test_cache_breakpoint_keeps_the_text():
    messages = [{"role": "system", "content": "S"}, {"role": "user", "content": "#Instruction\nI\n\n#Variables\nV"}]
    sent = with_cache_breakpoint("anthropic", messages)
    assert "".join(b["text"] for b in sent[1]["content"]) == messages[1]["content"]
    assert sent[1]["content"][0]["cache_control"] and "cache_control" not in sent[1]["content"][1]
    assert with_cache_breakpoint("openai", messages) is messages


def test_credential_table_agrees_with_litellm(monkeypatch):
    from pipeline.llm.tokens import import_litellm

    litellm = import_litellm()
    for name in [k for k in os.environ if k.endswith(("_API_KEY", "_API_BASE"))]:
        monkeypatch.delenv(name)
    for provider, names in PROVIDER_KEYS.items():
        missing = litellm.validate_environment(f"{provider}/some-model")["missing_keys"]
        assert set(missing) == set(names), provider
        with pytest.raises(MissingCredentialsError, match=names[0]):
            check_credentials(f"{provider}/some-model", environ={})
        check_credentials(f"{provider}/some-model", environ={names[-1]: "x"})
    check_credentials("openai/local", api_base="http://127.0.0.1:1/v1", environ={})  # own server: no key
    check_credentials("ollama_chat/qwen", environ={})


def test_known_providers_are_placed_by_litellm_as_their_prefix_says():
    """A client for a model of these prefixes is made before litellm is imported (its provider is the prefix)."""
    from pipeline.llm.tokens import import_litellm

    litellm = import_litellm()
    for provider in KNOWN_PROVIDERS:
        for api_base in (None, "http://127.0.0.1:1/v1"):
            assert litellm.get_llm_provider(f"{provider}/some-model", api_base=api_base)[1] == provider


LITELLM_WITHOUT_COLLECTIONS = """
import gc, sys
from pipeline.llm.tokens import import_litellm, import_litellm_soon
collections = []


def importing_litellm():  # litellm's package is running its own code (importlib's mark of a module being made)
    module = sys.modules.get("litellm")
    return module is not None and getattr(module.__spec__, "_initializing", False)


gc.callbacks.append(lambda phase, info: phase == "start" and collections.append(importing_litellm()))
if sys.argv[1] == "off":
    gc.disable()
if sys.argv[2] == "soon":
    import_litellm_soon()
litellm = import_litellm()
print(sum(collections), gc.isenabled(), litellm.suppress_debug_info)
"""


@pytest.mark.parametrize("how", ["here", "soon"])
@pytest.mark.parametrize("collector", ["on", "off"])
def test_litellm_is_imported_without_garbage_collections_and_the_collector_left_as_it_was(collector, how):
    """litellm's import makes hundreds of thousands of lasting objects: with the collector on, each collection
    they start walks everything made so far (a quarter of the import's 3.3 s). ``import_litellm`` pauses the
    collector for the import, on whichever thread imports, and leaves it as it found it."""
    done = subprocess.run([sys.executable, "-c", LITELLM_WITHOUT_COLLECTIONS, collector, how], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, env=_env())
    assert done.returncode == 0, done.stderr
    during, enabled, set_up = done.stdout.split()
    assert during == "0", f"{during} collections started while litellm's package ran (942 without the pause)"
    assert (enabled, set_up) == (str(collector == "on"), "True"), done.stdout


LITELLM_ON_FIRST_USE = """
import sys
sys.modules["litellm"] = None  # any import of litellm fails from here
from pipeline.llm.client import LiteLLMClient, open_client
from pipeline.llm.tokens import TokenCounter
client, _, _ = open_client("anthropic/claude-sonnet-4-5", None, 0.0, 100, 0)
ensemble, _, _ = open_client(None, None, 0.0, 100, 0, models=[{"model": "openai/a", "api_base": "http://h:1/v1"},
                                                                 {"model": "gemini/b", "api_base": None}])
counter = TokenCounter(client.model)
print("made", client.label, ensemble.label)
for use in (client.request_params, lambda: client.structured, lambda: ensemble.provider, lambda: counter("text")):
    try:
        use()
    except ImportError:
        print("needs litellm")
try:
    LiteLLMClient("gpt-4o")  # no prefix: only litellm can place it, so it is asked at once
except ImportError:
    print("asked at once")
"""


def test_a_client_asks_litellm_on_first_use_unless_only_litellm_can_place_its_model():
    done = subprocess.run([sys.executable, "-c", LITELLM_ON_FIRST_USE], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=_env())
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["made anthropic/claude-sonnet-4-5 openai/a + gemini/b", *["needs litellm"] * 4,
                                        "asked at once"], done.stdout


def test_no_key_fails_at_once_naming_the_variable(tmp_path):
    store = tmp_path / "s.duckdb"
    env = {k: v for k, v in _env().items() if k != "ANTHROPIC_API_KEY"}
    argv = ["optimize", "--game", "pong", "--model", "anthropic/claude-sonnet-4-5", "--store", str(store)]
    done = _cli(*argv, env=env)
    assert done.returncode != 0 and "ANTHROPIC_API_KEY" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not store.exists(), "nothing is evaluated or stored before the key is there"
    # at once: before litellm (~5 s to import) or the offline model is loaded, whatever the machine's load
    traced = subprocess.run([sys.executable, "-X", "importtime", "-m", "pipeline.cli", *argv], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=600)
    imported = {line.rsplit("|", 1)[-1].strip() for line in traced.stderr.splitlines() if line.startswith("import ")}
    assert traced.returncode == done.returncode and "pipeline.cli.optimize" in imported, traced.stderr[-2000:]
    assert not {"litellm", "xllamacpp", "gymnasium", "ale_py"} & imported, "nothing slow is loaded first"


def test_an_ensemble_without_its_keys_names_every_missing_key_at_once(tmp_path, monkeypatch, capsys):
    """The README's ensemble (Anthropic and OpenAI) with neither key: one line naming both keys, not ANTHROPIC_API_KEY
    alone and then, once it is set, OPENAI_API_KEY; a model on its own server needs none and is not named."""
    from pipeline.cli import main

    for name in ("ANTHROPIC_API_KEY", "OPENAI_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    store = tmp_path / "s.duckdb"
    argv = ["optimize", "--game", "pong", "--model", "anthropic/claude-sonnet-4-5", "--model", "openai/gpt-4o-mini",
            "--model", "ollama_chat/qwen2.5-coder,api_base=http://gpu:11434", "--store", str(store)]
    assert main(argv) == 2
    said = capsys.readouterr().err.strip()
    assert "ANTHROPIC_API_KEY" in said and "OPENAI_API_KEY" in said and "ollama" not in said, said
    assert len(said.splitlines()) == 1 and not store.exists()
    monkeypatch.setenv("ANTHROPIC_API_KEY", "x")
    assert main(argv) == 2
    said = capsys.readouterr().err.strip()
    assert said.startswith("codearcade: error: openai/gpt-4o-mini needs an API key: set OPENAI_API_KEY"), said


@pytest.mark.slow
def test_fatal_error_mid_run_fails_then_resume_finishes_each_iteration_once(store, scripted):
    model = scripted([COMPETENT_REPLY, {"status": 401}, "No change."])
    done = _optimize(store, model, "anthropic", "claude-sonnet-4-5", "--iterations", "2", "--eval-max-steps", "300",
                     *FAST)
    assert done.returncode == 1, done.stderr
    (run_id, status, error), = _runs(store)
    assert status == "failed" and "AuthenticationError" in error and "invalid api key" in error
    assert "--resume" in done.stderr
    errors = store.query("SELECT error_type, attempts FROM llm_calls WHERE error_type IS NOT NULL")
    assert errors == [("AuthenticationError", 1)], "a fatal error is not retried"
    # the user fixes the cause (here the server answers again) and resumes by a short prefix of the id
    again = _cli("optimize", "--resume", run_id[:10], "--store", str(store.path))
    assert again.returncode == 0, again.stderr
    rows = store.query("SELECT iteration, count(*) FROM iterations GROUP BY iteration ORDER BY iteration")
    assert rows == [(0, 1), (1, 1), (2, 1)]
    assert _runs(store)[0][1] == "finished"


def test_an_error_a_wrong_address_gives_names_the_url_without_its_credentials(scripted):
    """A server that answers 404 (a path it does not serve, a model it does not have) or is gone since the check
    before iteration 0 is named by the URL the request went to, as the provider's own text does not; a key in the
    URL is left out."""
    from pipeline.llm.client import LiteLLMClient, LLMError

    model = scripted([{"status": 404}])
    _, base = model.route("openai")
    with_key = base.replace("http://", "http://user:sk-secret@") + "?key=sk-query"
    for api_base in (base, with_key):
        client = LiteLLMClient(model.model, api_base=api_base, backoff_s=0.01)
        with pytest.raises(LLMError) as raised:
            client.complete([{"role": "user", "content": "hello"}])
        assert raised.value.error_type == "NotFoundError" and raised.value.fatal
        assert raised.value.message.endswith(f"(asked at {base})"), raised.value.message
        assert "sk-" not in str(raised.value)
    model.stop()
    client = LiteLLMClient(model.model, api_base=base, retries=1, backoff_s=0.01, timeout_s=5)
    with pytest.raises(LLMError) as raised:
        client.complete([{"role": "user", "content": "hello"}])
    # litellm calls a refused connection an InternalServerError, saying "Connection error." and nothing more
    assert raised.value.error_type == "InternalServerError" and raised.value.attempts == 2
    assert raised.value.message == f"Connection error. (asked at {base})"


@pytest.mark.slow
def test_a_run_whose_every_update_failed_is_not_a_success(store, scripted):
    model = scripted([{"status": 503}])
    done = _optimize(store, model, "openai", "gpt-4o", "--iterations", "1", "--eval-max-steps", "200", *FAST,
                     env=_env(OPENAI_API_KEY="sk-scripted"))
    assert done.returncode == 1, done.stderr
    (run_id, status, error), = _runs(store)
    assert status == "failed" and "every LLM call failed" in error and "scripted error 503" in error
    attempts = store.query("SELECT attempts, error_type FROM llm_calls")
    assert attempts == [(4, "ServiceUnavailableError")], "transient errors are retried (3 retries) and recorded"
    # its one iteration is played: the way on is more iterations, which the hint says (a plain --resume played
    # nothing, failed again and said to resume again)
    assert f"--resume {run_id[:8]}" in done.stderr.replace(run_id, run_id[:8]) and "--iterations 2" in done.stderr, \
        done.stderr
    again = _cli("optimize", "--resume", run_id, "--store", str(store.path), env=_env(OPENAI_API_KEY="sk-scripted"))
    assert again.returncode == 2 and "after playing all 1 of its iterations" in again.stderr, again.stderr
    assert "give --iterations N (more than 1)" in again.stderr and len(model.requests()) == 4
    more = _cli("optimize", "--resume", run_id, "--iterations", "2", "--store", str(store.path),
                env=_env(OPENAI_API_KEY="sk-scripted"))
    assert store.query("SELECT count(*) FROM iterations WHERE run_id = ?", [run_id])[0][0] == 3, more.stderr
    # the replay answers each call with what the run got, its errors too: nothing diverged (it stopped at the
    # first failed call, "first divergence at iteration 1")
    replayed = _cli("replay", run_id, "--json", "--store", str(store.path))
    report = json.loads(replayed.stdout)
    assert replayed.returncode == 0 and report["diverged_at"] is None and report["record_ends"] is None, \
        replayed.stdout + replayed.stderr
    assert [r["matches"] for r in report["iterations"]] == [True, True, True], report


@pytest.mark.slow
def test_cost_budget_stops_at_the_right_iteration_and_resumes(store, scripted):
    # every reply costs 5000 input + 500 output tokens at claude-sonnet-4-5's $3/$15 per M: $0.0225; before a
    # call its worst case (a prompt of at most 4000 tokens and a 1000-token reply) is at most $0.027. With
    # $0.06: call 1 (0 + 0.027) and call 2 (0.0225 + 0.027) fit, call 3 (0.045 + >= 0.025) does not.
    model = scripted([{"content": "No change.", "usage": {"input": 5000, "output": 500}}])
    args = ("--iterations", "4", "--eval-max-steps", "200", "--token-budget", "4000", "--max-tokens", "1000", *FAST)
    done = _optimize(store, model, "anthropic", "claude-sonnet-4-5", *args, "--max-cost", "0.06")
    assert done.returncode == 0, done.stderr
    (run_id, status, error), = _runs(store)
    assert status == "budget" and "--max-cost" in error, error
    assert [r[0] for r in store.query("SELECT iteration FROM iterations ORDER BY 1")] == [0, 1, 2]
    spent = store.query("SELECT sum(cost_usd) FROM llm_calls")[0][0]
    assert 0.04 < spent <= 2 * 0.0225, "two calls, the second partly at the cheaper cache-read price"
    assert len(model.requests()) == 2, "the third call was never made"
    again = _cli("optimize", "--resume", run_id, "--max-cost", "1", "--store", str(store.path))
    assert again.returncode == 0, again.stderr
    assert [r[0] for r in store.query("SELECT iteration FROM iterations ORDER BY 1")] == [0, 1, 2, 3, 4]
    assert _runs(store)[0][1] == "finished"
    assert json.loads(store.query("SELECT config FROM runs")[0][0])["max_cost_usd"] == 1


@pytest.mark.slow
def test_token_budget_needs_no_price(store, scripted):
    model = scripted([{"content": "No change.", "usage": {"input": 100, "output": 10}}])
    done = _optimize(store, model, "ollama_chat", "qwen2.5-coder", "--iterations", "3", "--eval-max-steps", "200",
                     "--token-budget", "3000", "--max-tokens", "500", "--max-total-tokens", "3000", *FAST)
    assert done.returncode == 0, done.stderr
    assert _runs(store)[0][1] == "budget"
    assert store.query("SELECT count(*) FROM llm_calls")[0][0] == 0, "a 3000-token prompt + 500 never fits 3000"


@pytest.mark.slow
def test_dry_run_prices_the_first_update_without_calling_the_model(tmp_path, scripted):
    model = scripted(["never sent"])
    store = tmp_path / "s.duckdb"
    route, base = model.route("anthropic", "claude-sonnet-4-5")
    done = _cli("optimize", "--game", "pong", "--model", route, "--api-base", base, "--dry-run", "--show-prompt",
                "--eval-max-steps", "200", "--rollout-steps", "50", "--iterations", "10", "--json",
                "--store", str(store))
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["prompt_tokens"] > 1000 and report["priced"]
    typical, most = report["update_cost_usd"]["typical"], report["update_cost_usd"]["at_most"]
    assert 0 < typical < most
    # at most: 10 updates filling the budget, and a repair turn for each (--repairs 1), of up to the budget, a
    # reply of --max-tokens and the error (repair_limit)
    repair = 16000 + 4096 + 1000
    assert report["repair_calls"] == 10
    assert report["run_cost_usd"]["at_most"] == pytest.approx(10 * (16000 * 3e-6 + 4096 * 15e-6)
                                                             + 10 * (repair * 3e-6 + 4096 * 15e-6))
    assert "#Instruction" in report["prompt"][1]["content"]
    assert model.raw_requests() == [] and not store.exists()


@pytest.mark.slow
def test_resume_of_a_finished_run_changes_nothing(store, scripted):
    model = scripted(["No change."])
    assert _optimize(store, model, "openai", "scripted", "--iterations", "1", "--eval-max-steps", "200",
                     *FAST).returncode == 0
    before, asked = store.query("SELECT * FROM runs"), len(model.requests())
    done = _cli("optimize", "--resume", before[0][0], "--store", str(store.path))
    assert done.returncode == 0 and "nothing to do" in done.stdout, done.stdout + done.stderr
    assert store.query("SELECT * FROM runs") == before
    assert len(model.requests()) == asked == 2, "the update and its repair turn; the resume asked nothing"


@pytest.mark.slow
def test_eval_runs_cannot_be_resumed_and_a_killed_one_shows_interrupted(tmp_path):
    store_path = tmp_path / "s.duckdb"
    slow = tmp_path / "slow.py"  # ~10 ms a step: the episode outlasts the checks below
    slow.write_text(pong_policy("    return 2 if sum(range(600000)) % 2 else 3\n"))
    proc = subprocess.Popen([EXE, "eval", str(slow), "--episodes", "1", "--max-steps", "100000",
                             "--store", str(store_path)], cwd=ROOT, env=_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while True:  # the run row exists once the first episode plays
            listed = _cli("runs", "--json", "--store", str(store_path))
            if listed.returncode == 0 and json.loads(listed.stdout or "[]"):
                break
            assert time.monotonic() < deadline, listed.stderr
            time.sleep(0.3)
        run = json.loads(listed.stdout)[0]
        assert run["status"] == "running"
        doctor = _cli("doctor", "--json", "--store", str(store_path))
        assert "interrupted" not in doctor.stdout, "a live eval run is not called interrupted"
        refused = _cli("optimize", "--resume", run["run_id"][:8], "--store", str(store_path))
        assert refused.returncode == 2 and "eval run" in refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    listed = json.loads(_cli("runs", "--json", "--store", str(store_path)).stdout)
    assert listed[0]["status"] == "interrupted"
    doctor = _cli("doctor", "--json", "--store", str(store_path))
    assert any("interrupted" in f["check"] for f in json.loads(doctor.stdout)["findings"])


@pytest.mark.slow
@pytest.mark.parametrize("provider,name", [("anthropic", "claude-sonnet-4-5"), ("openai", "gpt-4o")])
def test_streamed_replies_land_like_whole_ones(store, scripted, provider, name):
    model = scripted([COMPETENT_REPLY])
    done = _optimize(store, model, provider, name, "--iterations", "1", "--stream", *FAST,
                     env=_env(OPENAI_API_KEY="sk-scripted"))
    assert done.returncode == 0, done.stderr
    assert model.raw_requests()[0]["body"]["stream"] is True
    assert store.query("SELECT update_status, score >= 15 FROM iterations WHERE iteration = 1") == [("accepted", True)]
    params, input_tokens, output_tokens, finish = store.query(
        "SELECT request_params, input_tokens, output_tokens, finish_reasons FROM llm_calls")[0]
    assert json.loads(params)["stream"] is True and input_tokens > 1000 and output_tokens > 50 and finish == ["stop"]
    assert store.query("SELECT reply_reading FROM llm_calls") == [("structured",)], "a streamed tool call too"


_COUNT_LOOPS = """
import asyncio, json, sys, time
sys.path.insert(0, sys.argv[1])
from pipeline.llm.client import LiteLLMClient
from pipeline.llm.tokens import import_litellm
from litellm.litellm_core_utils.thread_pool_executor import executor

import_litellm()
made = []
new_event_loop = asyncio.events.new_event_loop
asyncio.events.new_event_loop = lambda: made.append(1) or new_event_loop()
read = {}
for model, api_base in json.loads(sys.argv[2]):
    before = len(made)
    client = LiteLLMClient(model, api_base=api_base, api_key="sk-test", retries=0, structured=False, stream=True)
    text = client.complete([{"role": "user", "content": "hi"}]).text
    while executor._pending_slots._value < executor._max_pending_tasks:  # what litellm queued for the call, done
        time.sleep(0.01)
    read[model] = [len(text), len(made) - before]
print(json.dumps(read))
"""


@pytest.mark.slow
def test_a_streamed_reply_is_read_without_an_event_loop_for_each_event(scripted):
    """litellm hands each streamed event to its logging callbacks, on a thread of its own in an event loop made for
    it: 1,600 pieces took 5.5 s of CPU to read, 2.3 without (bench/stream_read.py). codearcade registers no litellm
    callback: a reply of 600 pieces, through the OpenAI and the Anthropic adapter, is read whole with a handful of
    event loops made, not one an event."""
    reply = "def select_action(self, obs):\n" + "    x = 1\n" * 200
    model = scripted([{"content": reply}])
    routes = [model.route(provider) for provider in ("openai", "anthropic")]
    done = subprocess.run([sys.executable, "-c", _COUNT_LOOPS, str(ROOT), json.dumps(routes)], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "LITELLM_LOCAL_MODEL_COST_MAP": "True"})
    assert done.returncode == 0, done.stderr[-2000:]
    read = json.loads(done.stdout.strip().splitlines()[-1])
    for (name, _), (length, loops) in zip(routes, read.values()):
        assert length == len(reply), f"{name}: the whole reply was read"
        assert loops < 10, f"{name}: {loops} event loops made to read a stream of ~600 events"
    assert len(read) == 2, read


def test_waiting_line_shows_time_and_streamed_tokens():
    import io

    from pipeline.cli.optimize import _llm_waiting

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    screen = Terminal()
    with _llm_waiting(screen)(3, "anthropic/claude-sonnet-4-5") as on_text:
        for piece in ("def ", "select_action", "(self):"):
            on_text(piece)
        time.sleep(1.2)
    shown = screen.getvalue()
    assert "iteration 3: waiting for anthropic/claude-sonnet-4-5 ... 1 s" in shown
    assert "receiving: 3 tokens (24 characters)" in shown
    assert shown.endswith("\r\033[K"), "the line is cleared when the reply is in"


_ASK = """
import json, os, sys
sys.path.insert(0, sys.argv[1])
from pipeline.llm.client import LiteLLMClient, LLMError
from pipeline.llm.tokens import import_litellm

import_litellm()  # once (~5 s of CPU) for a module's tests: each call is made in a child forked from here, on its own
for line in sys.stdin:
    name, base, streams = json.loads(line)
    answers = []
    for stream in streams:
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                os.close(read)  # VmHWM below: this child's own peak RSS, from the pages it shares with its parent
                client = LiteLLMClient(name, api_base=base, api_key="sk-test", retries=0, backoff_s=0.01,
                                       structured=False, stream=stream)
                try:
                    answer = {"text": client.complete([{"role": "user", "content": "hi"}]).text[:100]}
                except LLMError as exc:
                    answer = {"error_type": exc.error_type, "message": exc.message}
                with open("/proc/self/status") as f:
                    answer["peak_mb"] = next(int(l.split()[1]) for l in f if l.startswith("VmHWM:")) / 1024
                with os.fdopen(write, "w") as out:
                    out.write(json.dumps(answer))
                code = 0
            finally:
                os._exit(code)
        os.close(write)
        with os.fdopen(read) as got:
            said = got.read()
        _, status = os.waitpid(pid, 0)
        if status != 0 or not said:
            answers.append({"child_failed": f"the child of call {len(answers) + 1} ended with status {status}"})
            break
        answers.append(json.loads(said))
    print("ANSWERS " + json.dumps(answers), flush=True)
"""


class _Asker:
    """``asker(name, base, *streams)``: one call of the model for each of ``streams`` (whether to stream it), in
    turn, through :data:`_ASK`: each call's answer or error and the peak RSS of the process it was made in (a child
    of its own, forked from one process that imported litellm: the import is paid once a module, not once a test or
    a call)."""

    def __init__(self, log_path):
        self.log = open(log_path, "w+")
        self.process = subprocess.Popen([sys.executable, "-c", _ASK, str(ROOT)], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, stderr=self.log, text=True,
                                        env={**os.environ, "LITELLM_LOCAL_MODEL_COST_MAP": "True"})

    def __call__(self, name: str, base: str, *streams: bool) -> list[dict]:
        import threading

        self.process.stdin.write(json.dumps([name, base, list(streams)]) + "\n")
        self.process.stdin.flush()
        stuck = threading.Timer(300, self.process.kill)  # a hung call ends the asker, and the test, not the suite
        stuck.start()
        try:
            line = ""
            while not line.startswith("ANSWERS "):
                line = self.process.stdout.readline()
                if not line:
                    self.log.seek(0)
                    raise AssertionError(f"the asker ended ({self.process.poll()}): {self.log.read()[-2000:]}")
        finally:
            stuck.cancel()
        answers = json.loads(line[len("ANSWERS "):])
        assert len(answers) == len(streams) and "child_failed" not in answers[-1], answers
        return answers

    def close(self) -> None:
        self.process.stdin.close()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.log.close()


@pytest.fixture(scope="module")
def ask(tmp_path_factory):
    asker = _Asker(tmp_path_factory.mktemp("asker") / "stderr.log")
    yield asker
    asker.close()


@pytest.mark.slow
@pytest.mark.parametrize("provider", ["openai", "anthropic", "ollama_chat", "gemini"])
def test_an_endpoint_s_answer_is_read_within_its_byte_limit_compressed_or_not(scripted, ask, provider):
    """litellm reads a whole HTTP answer, and inflates a gzip one, before codearcade sees a reply: 416 KB of gzip
    that inflates to 200 MB held ~1.9 GB in optimize's process. Through each provider's real adapter (the OpenAI
    SDK's httpx2, litellm's own httpx handler), against a server that compresses whatever it is asked: a small
    gzip answer is read as ever; one that inflates to 4 times MAX_ANSWER_BYTES, or a plain answer that long, is a
    failed call that says why, read no further than the limit (the child's peak RSS, against the small answer's)."""
    from pipeline.llm.capped import MAX_ANSWER_BYTES

    filler = "def a(): pass\n"
    repeat = 4 * MAX_ANSWER_BYTES // len(filler)
    model = scripted([{"content": "small and compressed", "gzip": True},
                      {"content": filler, "repeat": repeat, "gzip": True},
                      {"content": filler, "repeat": repeat}])
    small, *hostile = ask(*model.route(provider), False, False, False)
    assert small.get("text") == "small and compressed", small
    for how, answer in zip(("gzip", "plain"), hostile):
        assert answer.get("error_type") == "AnswerTooLarge", (how, answer)
        assert f"passed {MAX_ANSWER_BYTES:,} bytes" in answer["message"] and "asked at" in answer["message"], answer
        assert answer["peak_mb"] < small["peak_mb"] + 4 * MAX_ANSWER_BYTES / 2**20, (how, answer, small)


@pytest.mark.slow
@pytest.mark.parametrize("provider", ["openai", "anthropic"])
def test_an_answer_s_parse_is_bounded_by_its_elements_and_a_stream_by_its_events(scripted, ask, provider):
    """Bytes alone do not bound a parse: 16 KB of gzip inflating to 5.5 million `{}` (16 MB, inside the byte
    limit) held ~1 GB a call, and 300,000 empty stream events (6 KB of gzip) took 115 s and 830 MB. A JSON answer
    holds at most MAX_ANSWER_ELEMENTS elements and a stream at most max_events() events (litellm reads past empty
    ones without a chunk: they are counted as they arrive), and EVENT_ELEMENTS elements more an event (one event
    of 4 million `{}`, 12 MB, was read whole, and held 700 MB: litellm keeps an event's fields): past them the call
    fails saying why, its child's peak near a small answer's; an honest stream still reads."""
    from pipeline.llm.capped import MAX_ANSWER_ELEMENTS

    model = scripted([{"content": "a small reply"}, {"content": "a small reply"},
                      {"content": "a small reply", "extra_dicts": 2 * MAX_ANSWER_ELEMENTS, "gzip": True},
                      {"content": "a small reply", "empty_events": 80_000},
                      {"content": "a small reply", "extra_dicts": 4_000_000}])
    small, streamed, elements, events, wide = ask(*model.route(provider), False, True, False, True, True)
    assert small.get("text") == streamed.get("text") == "a small reply", (small, streamed)
    assert elements.get("error_type") == "AnswerTooLarge", elements
    assert f"more than {MAX_ANSWER_ELEMENTS:,} JSON elements" in elements["message"], elements
    assert elements["peak_mb"] < small["peak_mb"] + 150, (elements, small)
    assert events.get("error_type") == "AnswerTooLarge" and "stream passed 20,000 events" in events["message"], \
        events
    assert events["peak_mb"] < streamed["peak_mb"] + 150, (events, streamed)
    assert wide.get("error_type") == "AnswerTooLarge" and "stream holds more than" in wide["message"], wide
    assert wide["peak_mb"] < streamed["peak_mb"] + 150, (wide, streamed)


@pytest.mark.slow
@pytest.mark.parametrize("part", ["choices", "tool_calls"])
def test_a_stream_event_of_more_than_one_choice_or_tool_call_ends_the_call(scripted, ask, part):
    """One choice is asked for, but litellm built an object for each choice (and tool call) an event carried and kept
    every event for the reply: 19,900 events of seven choices each (6.7 MB) held 330 MB more and took 65 s, of seven
    tool calls 250 MB. An event with more than one now ends the call, saying so, the child's peak near an honest
    stream's."""
    model = scripted([{"content": "a small reply"}, {"content": "a " * 12_000, part: 7}])
    streamed, hostile = ask(*model.route("openai"), True, True)
    assert streamed.get("text") == "a small reply", streamed
    assert hostile.get("error_type") == "AnswerTooLarge", hostile
    assert f"7 {part.replace('_', ' ')} in one event" in hostile["message"] and "asked at" in hostile["message"], \
        hostile
    assert hostile["peak_mb"] < streamed["peak_mb"] + 60, (hostile, streamed)


@pytest.mark.slow
def test_an_answer_s_elements_are_counted_outside_its_strings(scripted, ask):
    """A reply's text is one JSON string, whose commas were counted as elements: the limit had to let 250,000 by,
    and an answer of 40,000 choices (2.7 MB, 20 KB of gzip) within it held 146 MB more and took 8 s (litellm builds
    ~3.6 KB of objects a choice). Counted outside strings, an honest answer's structure is a few dozen elements, and
    MAX_ANSWER_ELEMENTS is 10,000: that answer now fails saying why, its child's peak near a small answer's, while a
    reply of 100,000 commas still reads."""
    from pipeline.llm.capped import MAX_ANSWER_ELEMENTS

    model = scripted([{"content": "a small reply"}, {"content": "a small reply", "choices": 40_000, "gzip": True},
                      {"content": "f(a, b)" * 100_000}])
    small, choices, commas = ask(*model.route("openai"), False, False, False)
    assert small.get("text") == "a small reply", small
    assert choices.get("error_type") == "AnswerTooLarge", choices
    assert f"more than {MAX_ANSWER_ELEMENTS:,} JSON elements" in choices["message"], choices
    assert choices["peak_mb"] < small["peak_mb"] + 60, (choices, small)
    assert commas.get("text") == ("f(a, b)" * 100_000)[:100], commas


def test_the_capped_decoder_inflates_as_zlib_does_in_any_split_and_stops_at_each_limit():
    """pipeline.llm.capped's decoder, without a server: gzip, deflate (zlib) and identity bodies split at random
    points decode to exactly the body; each limit (bytes raw or inflated, JSON elements outside strings, server-sent
    events or JSON lines) stops it once passed, never before; an encoding it does not inflate is refused."""
    import gzip
    import random
    import zlib

    from pipeline.llm.capped import AnswerTooLarge, CappedDecoder

    def structure(body: bytes) -> tuple[int, bool]:
        """The `{`, `[` and `,` of `body` outside JSON strings, one character at a time, and whether a string was
        cut by a line end (no JSON: a parse stops there, and the decoder may count more after it, never fewer)."""
        count, in_string, cut, i = 0, False, False, 0
        while i < len(body):
            char, after = body[i:i + 1], body[i + 1:i + 2]
            if in_string and char == b"\\" and after not in (b"", b"\n"):
                i += 2
                continue
            if in_string and char in b'"\n':
                in_string, cut = False, cut or char == b"\n"
            elif not in_string and char == b'"':
                in_string = True
            elif not in_string and char in b"{[,":
                count += 1
            i += 1
        return count, cut

    rng = random.Random(11)
    for n in range(300):
        alphabet = b'{}[],"ab \\' + (b"\n" if n % 2 else b"")
        body = bytes(rng.choice(alphabet) for _ in range(rng.randint(0, 5000)))
        encoding, packed = rng.choice([("gzip", gzip.compress(body)), ("deflate", zlib.compress(body)),
                                       ("identity", body)])
        cuts = sorted(rng.sample(range(len(packed) + 1), min(rng.choice([4, 40]), len(packed) + 1)))
        pieces = [packed[a:b] for a, b in zip([0] + cuts, cuts + [len(packed)])]
        decoder = CappedDecoder([encoding], 10**9, None)
        assert b"".join(b"".join(decoder.chunks(p)) for p in pieces) + decoder.rest() == body
        elements, cut = structure(body)
        for limit in (elements, elements - 1):
            decoder = CappedDecoder([encoding], 10**9, limit)
            try:
                b"".join(b"".join(decoder.chunks(p)) for p in pieces) + decoder.rest()
                passed = False
            except AnswerTooLarge:
                passed = True
            assert passed == (elements > limit >= 0) or (cut and limit == elements), (elements, limit, cut)
    for mark, event in ((b"data:", b"data: {}\n\n"), (b"\n", b'{"done": false}\n')):
        decoder = CappedDecoder([], 10**9, None, 3, mark)
        assert list(decoder.chunks(event * 3))
        with pytest.raises(AnswerTooLarge, match="stream passed 3 events"):
            list(decoder.chunks(event))
        # a stream's elements: `elements`, and `event_elements` more for each event it has sent
        decoder = CappedDecoder([], 10**9, 10, 100, mark, event_elements=2)
        bare = {b"data:": b"data: 1\n\n", b"\n": b"1\n"}[mark]  # an event of no elements
        list(decoder.chunks(bare * 11 + b"[" * 32))  # 11 events: 10 + 2 * 11 elements
        with pytest.raises(AnswerTooLarge, match="more than 32 JSON elements"):
            list(decoder.chunks(b"["))
    with pytest.raises(AnswerTooLarge, match="passed 1,000 bytes"):
        list(CappedDecoder(["gzip"], 1000).chunks(gzip.compress(b" " * 10**6)))
    with pytest.raises(AnswerTooLarge, match="content encoding 'br'"):
        CappedDecoder(["br"], 1000)


@pytest.mark.slow
@pytest.mark.parametrize("stream", [False, True])
def test_an_endpoint_that_trickles_its_answer_is_given_up_on_at_the_call_s_time_limit(stream):
    """httpx's time limit is per read: an endpoint that sends its answer a byte at a time, each just inside it,
    held a call (and `optimize`, past its --max-wall) for as long as it liked; 480 s and on, measured. The call
    now ends at its time limit in all, whole answer or stream, and says so."""
    import socket
    import threading
    import time

    from pipeline.llm.client import CALL_TIME_GRACE_S, LiteLLMClient, LLMError

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    stop = threading.Event()

    def trickle() -> None:  # a whole answer's headers at once, then its body a byte every 0.2 s
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            conn.recv(65536)
            body = json.dumps({"id": "x", "object": "chat.completion", "created": 0, "model": "m", "choices": [
                {"index": 0, "message": {"role": "assistant", "content": "y" * 400}, "finish_reason": "stop"}]})
            conn.sendall(f"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {len(body)}\r\n"
                         "\r\n".encode())
            for byte in body.encode():
                if stop.wait(0.2):
                    break
                try:
                    conn.send(bytes([byte]))
                except OSError:
                    break
            conn.close()

    server = threading.Thread(target=trickle, daemon=True)
    server.start()
    try:
        client = LiteLLMClient("openai/trickle", api_base=f"http://127.0.0.1:{listener.getsockname()[1]}/v1",
                               api_key="none", retries=0, timeout_s=2, stream=stream, structured=False)
        began = time.monotonic()
        with pytest.raises(LLMError) as raised:
            client.complete([{"role": "user", "content": "hello"}])
        took = time.monotonic() - began
    finally:
        stop.set()
        listener.close()
    # the answer would have taken 100 s and more; the limit is 2 s, then the grace for httpx's own word
    assert took < 2 + CALL_TIME_GRACE_S + 20, took
    assert raised.value.error_type == "Timeout" and "time limit of 2 s" in raised.value.message, raised.value


def test_a_call_is_given_up_on_at_its_deadline_and_no_retry_starts_after_it(tmp_path):
    """The run's time budget (``deadline``) ends a call in flight, however long the call's own limit, and no
    retry of a failed call starts past it: an endpoint slow to answer, and one that fails at once."""
    from pipeline.llm.client import OUT_OF_TIME, LiteLLMClient, LLMError
    from tests.scripted_llm import ScriptedModel

    for script, deadline_s, slow in (([{"sleep": 120, "content": "late"}], 2.0, True),
                                     ([{"status": 503, "times": 100}], 1.5, False)):
        with ScriptedModel(script, tmp_path / f"model-{slow}") as model:
            client = LiteLLMClient(model.model, api_base=model.api_base, retries=1000, backoff_s=0.2,
                                   timeout_s=300, structured=False)
            began = time.monotonic()
            with pytest.raises(LLMError) as raised:
                client.complete([{"role": "user", "content": "hello"}], deadline=began + deadline_s)
            took = time.monotonic() - began
            asked = len(model.raw_requests())
        assert raised.value.error_type == OUT_OF_TIME, raised.value
        assert took < deadline_s + 10, took  # the slow answer came after 120 s; the retries were 1,000
        if slow:
            assert asked == 1
        else:  # retried until the deadline, then no more: waits of 0.2, 0.4, 0.8 s ... within 1.5 s
            assert 2 <= asked <= 4, asked


@pytest.mark.slow
def test_a_stream_given_up_on_at_the_deadline_is_billed(tmp_path):
    """A stream that began was being generated, and is billed, when the run's deadline ends it: the call's error
    carries that attempt (its usage unknown: the optimizer charges it its worst case, as a stream that broke), so
    the run's budgets count it. It was dropped, and a run that resumed had spent less than it was billed."""
    from pipeline.llm.client import OUT_OF_TIME, LiteLLMClient, LLMError
    from tests.scripted_llm import ScriptedModel

    script = [{"content": "def a(): pass\n"}, {"content": "def a(): pass\n" * 20, "stall": [3, 120]}]
    with ScriptedModel(script, tmp_path / "model") as model:
        client = LiteLLMClient(model.model, api_base=model.api_base, retries=3, backoff_s=0.01, timeout_s=300,
                               structured=False, stream=True)
        client.complete([{"role": "user", "content": "hello"}])  # litellm's first call imports its adapter
        with pytest.raises(LLMError) as raised:
            client.complete([{"role": "user", "content": "hello"}], deadline=time.monotonic() + 8.0)
        assert len(model.raw_requests()) == 2, "the stalled stream was asked for once"
    assert raised.value.error_type == OUT_OF_TIME, raised.value
    billed = raised.value.answer
    assert billed is not None and billed.attempts == 1, billed
    assert billed.input_tokens is None and billed.output_tokens is None and billed.cost_usd is None, billed


RATE_LIMITED_PROVIDERS = ["anthropic", "openai", "ollama_chat", "hosted_vllm", "gemini"]


def _asked(tmp_path, cases: list[tuple[str, dict, list]]):
    """One scripted endpoint for every case (it answers each protocol at its own path), its script each case's
    429 with the case's headers and then what the case is answered next, in order; and per case a client of the
    case's provider. The clients' own backoff is 0.01 s, so any longer gap between two requests is a wait the
    provider asked for."""
    from pipeline.llm.client import LiteLLMClient
    from tests.scripted_llm import ScriptedModel

    model = ScriptedModel([entry for _, headers, then in cases for entry in [{"status": 429, "headers": headers}]
                           + then], tmp_path / "model").start()
    clients = []
    for provider, _, _ in cases:
        route, base = model.route(provider)
        clients.append(LiteLLMClient(route, api_base=base, api_key="sk-scripted", retries=3, backoff_s=0.01,
                                     timeout_s=30, structured=False))
    return model, clients


def _gap(model) -> float:
    """Seconds between the last two requests the endpoint received."""
    earlier, later = [request["received_at"] for request in model.raw_requests()[-2:]]
    return later - earlier


@pytest.mark.slow
def test_a_rate_limit_is_waited_out_as_long_as_the_provider_asks(tmp_path):
    """A 429's ``Retry-After`` (seconds, OpenAI's ``retry-after-ms``, an HTTP date) is how long the next request
    waits, through each provider's adapter (litellm keeps the response's headers on its exception): with the
    client's own backoff (0.01 s here, 2 s by default) the retries came before the limit reset and a rate-limited
    update was lost after 14 s of retrying."""
    # the date: 3 s after the server answers, to the second (so 2-3 s after)
    # (the headers reach the client the same way whatever their name: retry-after-ms keeps the waits short)
    cases = [("anthropic", {"retry-after": "1"}, 1.0), ("openai", {"retry-after-ms": "1500"}, 1.5)] + \
        [(provider, {"retry-after-ms": "400"}, 0.4) for provider in RATE_LIMITED_PROVIDERS] + \
        [("anthropic", {"Retry-After": {"date_in_s": 3}}, 1.5)]
    model, clients = _asked(tmp_path, [(provider, headers, ["the reply"]) for provider, headers, _ in cases])
    try:
        for (provider, headers, at_least), client in zip(cases, clients):
            reply = client.complete([{"role": "user", "content": "hello"}])
            assert reply.text.strip() == "the reply" and reply.attempts == 2, (provider, headers, reply)
            assert _gap(model) >= at_least, (provider, headers, _gap(model))
    finally:
        model.stop()


@pytest.mark.slow
def test_a_wait_longer_than_a_call_waits_stops_at_once_and_junk_is_not_a_wait(tmp_path):
    """A provider that asks for longer than :data:`MAX_ASKED_WAIT_S` (a day's quota; a hostile endpoint's
    ``1e308``) is not waited out, silently, for hours: the call fails at once, as an error retrying cannot fix,
    saying how long it was asked to wait. A value that is not a wait (negative, not a number, not finite, over
    long) leaves the client's own backoff in charge."""
    import email.utils

    from pipeline.llm.client import LLMError
    from pipeline.llm.errors import MAX_ASKED_WAIT_S

    next_year = email.utils.formatdate(time.time() + 366 * 86_400, usegmt=True)
    too_long = [({"retry-after": "86400"}, "86,400 s"), ({"retry-after-ms": "1e308"}, "s before"),
                ({"retry-after": next_year}, "s before"),
                ({"retry-after": str(int(MAX_ASKED_WAIT_S) + 1)}, f"{int(MAX_ASKED_WAIT_S) + 1} s")]
    junk = ["-5", "nan", "inf", "soon", "1" * 100, "", "Thu, 99 Foo 2026 99:99:99 GMT"]
    model, clients = _asked(tmp_path, [("anthropic", headers, []) for headers, _ in too_long]
                            + [("openai", {"retry-after": value, "retry-after-ms": value}, ["the reply"])
                               for value in junk])
    try:
        for (headers, asked), client in zip(too_long, clients):
            before = len(model.raw_requests())
            with pytest.raises(LLMError) as raised:
                client.complete([{"role": "user", "content": "hello"}])
            assert raised.value.fatal and raised.value.attempts == 1, headers
            assert len(model.raw_requests()) == before + 1, "no second request"
            assert "the provider asks to wait" in raised.value.message and asked in raised.value.message, \
                raised.value
            assert "resume the run" in raised.value.message
        for value, client in zip(junk, clients[len(too_long):]):
            reply = client.complete([{"role": "user", "content": "hello"}])
            assert reply.attempts == 2 and _gap(model) < MAX_ASKED_WAIT_S, value
    finally:
        model.stop()


ADAPTERS = [("openai", False), ("openai", True), ("anthropic", False), ("anthropic", True), ("ollama_chat", False),
            ("gemini", False)]
"""(provider, streamed): each adapter of the scripted server, streamed where it streams."""


def _client(tmp_path, provider: str, stream: bool, script: list, retries: int = 2):
    """A client of ``provider``'s scripted endpoint answering ``script``; quick retries."""
    from pipeline.llm.client import LiteLLMClient
    from tests.scripted_llm import ScriptedModel

    model = ScriptedModel(script, tmp_path / f"model-{provider}-{len(list(tmp_path.iterdir()))}").start()
    route, base = model.route(provider)
    return model, LiteLLMClient(route, api_base=base, api_key="sk-scripted", retries=retries, backoff_s=0.01,
                                timeout_s=30, structured=False, stream=stream)


def _outcome(model, client):
    """(reply or LLMError, requests the endpoint got) of one call; the server stopped."""
    from pipeline.llm.client import LLMError

    try:
        return client.complete([{"role": "user", "content": "hello"}]), len(model.raw_requests())
    except LLMError as exc:
        return exc, len(model.raw_requests())
    finally:
        model.stop()


@pytest.mark.parametrize("provider,stream", ADAPTERS, ids=[f"{p}-{'stream' if s else 'whole'}" for p, s in ADAPTERS])
def test_an_answer_without_text_is_retried_and_never_a_reply(tmp_path, provider, stream):
    """An answer with no text (empty, only whitespace; a 200 whose body is an error object, which litellm reads as
    an empty stream) was a successful call with reply '' (then read as "the reply is empty"), or, for Gemini, whose
    adapter calls an error body a bad request, a fatal error that stopped the run: each is retried, and one that
    never brings text is a non-fatal ``EmptyReply``, after every attempt."""
    from pipeline.llm.answers import EMPTY_REPLY
    from pipeline.llm.client import LLMError

    shapes = ["", "   \n  ", {"error_body": 529}]
    for shape in shapes:
        reply, asked = _outcome(*_client(tmp_path, provider, stream, [shape, "the reply"]))
        assert not isinstance(reply, LLMError), (shape, reply)
        assert reply.text.strip() == "the reply" and reply.attempts == 2 and asked == 2, (shape, reply)
    for shape in shapes[:2]:
        error, asked = _outcome(*_client(tmp_path, provider, stream, [shape]))
        assert isinstance(error, LLMError) and error.error_type == EMPTY_REPLY, (shape, error)
        assert not error.fatal and error.attempts == 3 and asked == 3, (shape, error)
        assert "no text" in error.message
        # billed all the same: its usage goes with the error, for llm_calls and the budgets
        assert error.answer is not None and error.answer.finish_reasons == ["stop"] and error.answer.input_tokens


@pytest.mark.parametrize("provider,stream", ADAPTERS, ids=[f"{p}-{'stream' if s else 'whole'}" for p, s in ADAPTERS])
def test_an_answer_cut_off_or_withheld_before_any_text_fails_at_once(tmp_path, provider, stream):
    """A reply that stopped at the token limit before any text (a reasoning model's budget spent on thinking;
    Anthropic's ``max_tokens``, Ollama's ``done_reason: length``, Gemini's ``MAX_TOKENS``) was a successful call
    with no text; it is an ``EmptyReply`` that says to raise --max-tokens, not retried (the same limit gets the
    same). Gemini's ``SAFETY``/``RECITATION`` without text is ``ContentFiltered``, not retried either, and neither
    stops the run. A reply cut off after some text stays a reply, recorded as ``length``."""
    from pipeline.llm.answers import CONTENT_FILTERED, EMPTY_REPLY
    from pipeline.llm.client import LLMError

    error, asked = _outcome(*_client(tmp_path, provider, stream, [{"content": "", "finish": "length"}, "late"]))
    assert isinstance(error, LLMError) and error.error_type == EMPTY_REPLY, error
    assert not error.fatal and error.attempts == 1 and asked == 1 and "raise --max-tokens" in error.message
    reply, _ = _outcome(*_client(tmp_path, provider, stream, [{"content": "def half(self):", "finish": "length"}]))
    assert reply.text.strip() == "def half(self):" and reply.finish_reasons == ["length"] and reply.cut_off
    if provider == "gemini":
        for reason in ("SAFETY", "RECITATION"):
            error, asked = _outcome(*_client(tmp_path, provider, stream, [{"content": "", "finish": reason}, "x"]))
            assert isinstance(error, LLMError) and error.error_type == CONTENT_FILTERED, (reason, error)
            assert not error.fatal and error.attempts == 1 and asked == 1, (reason, error)


@pytest.mark.parametrize("provider", ["openai", "anthropic"])
def test_a_stream_that_fails_midway_is_retried_and_its_part_never_kept(tmp_path, provider):
    """A stream that breaks after some text (Anthropic's ``event: error`` with ``overloaded_error``, an OpenAI
    error event, a connection closed before the stop reason or ``[DONE]``) is a transient error, retried from the
    start: its part of the text is never the reply (litellm's adapters raise ServiceUnavailableError for each)."""
    from pipeline.llm.client import LLMError

    text = "one two three four five six"
    for shape in ({"content": text, "stream_error": 3}, {"content": text, "stream_cut": 3}):
        reply, asked = _outcome(*_client(tmp_path, provider, True, [shape, text]))
        assert not isinstance(reply, LLMError), (shape, reply)
        assert reply.text == text and reply.attempts == 2 and asked == 2, (shape, reply)
        error, asked = _outcome(*_client(tmp_path, provider, True, [shape]))
        assert isinstance(error, LLMError) and not error.fatal and error.attempts == 3 and asked == 3, (shape, error)


@pytest.mark.parametrize("provider", ["ollama_chat", "gemini"])
def test_an_error_object_in_a_200_is_retried_and_its_message_holds_no_traceback(tmp_path, provider):
    """A 200 whose body is an error object, always: Ollama's adapter fails reading it and litellm put its own
    traceback into the message (stored in ``llm_calls.error_message``, printed); Gemini's called it a fatal bad
    request. Both are retried, non-fatal, with a one-line message."""
    from pipeline.llm.client import LLMError

    error, asked = _outcome(*_client(tmp_path, provider, False, [{"error_body": 529}]))
    assert isinstance(error, LLMError) and not error.fatal and error.attempts == 3 and asked == 3, error
    assert "Traceback" not in error.message and 'File "' not in error.message, error.message


EMPTY_OR_UNREADABLE = [
    # (provider, the script, extra flags, update status, the first call's error type)
    ("openai", [""], ("--stream",), "llm_error", "EmptyReply"),
    ("gemini", [{"content": "", "finish": "SAFETY"}], (), "llm_error", "ContentFiltered"),
    ("gemini", [{"error_body": 529}, COMPETENT_REPLY], (), "accepted", None),
]


@pytest.mark.slow
@pytest.mark.parametrize("provider,script,extra,status,error_type", EMPTY_OR_UNREADABLE,
                         ids=["empty-stream", "gemini-safety", "gemini-error-body"])
def test_optimize_records_an_answer_without_text_as_the_error_it_is(store, scripted, provider, script, extra,
                                                                     status, error_type):
    """`codearcade optimize`: an empty reply (or Gemini's SAFETY with no text) was stored as a successful call whose
    reply '' was "unusable", and a repair turn sent that empty reply back as the assistant's turn (which Anthropic
    refuses as a bad request); now it is an ``llm_calls`` error, with the answer's usage (billed) and finish
    reasons, no reply text and no repair turn. Gemini's 200 with an error object stopped the run as a fatal
    BadRequestError; it is retried, and the next answer is played."""
    model = scripted(script)
    name = {"openai": "gpt-4o", "gemini": "gemini-2.5-pro"}[provider]
    done = _optimize(store, model, provider, name, "--iterations", "1", *extra, *FAST,
                     env=_env(OPENAI_API_KEY="sk-scripted"))
    assert "Traceback" not in done.stderr, done.stderr
    assert store.query("SELECT update_status FROM iterations WHERE iteration = 1") == [(status,)], done.stderr
    calls = store.query("SELECT error_type, attempts, finish_reasons, input_tokens > 1000, reply_hash IS NULL, "
                        "repair_turn FROM llm_calls ORDER BY created_at")
    if error_type is None:
        assert done.returncode == 0 and calls == [(None, 2, ["stop"], True, False, 0)], (calls, done.stderr)
    else:  # the run's only update failed: the run is failed, and says why
        assert done.returncode == 1 and error_type in done.stderr, done.stderr
        attempts = 4 if error_type == "EmptyReply" else 1  # retried 3 times; a withheld one is not
        finish = ["stop"] if error_type == "EmptyReply" else ["content_filter"]
        assert calls == [(error_type, attempts, finish, True, True, 0)], calls
