"""What a provider bills against what codearcade records and budgets: a fuzzer with a cost oracle.

A call is up to four HTTP attempts, and a provider bills every one it answered: an answer without text, a stream
that broke midway, a reply cut at the token limit, each retried answer; a rate limit or a 5xx is not billed. The
scripted model (tests/scripted_llm.py) keeps the ledger of what it billed for each request. Seeded random mixes of
all of these drive ``LiteLLMClient`` and ``codearcade optimize``, and the oracle holds over every seed:

1. what the call says it was billed (its reply's or error's usage; ``llm_calls`` for a run) is the ledger's total:
   every billed attempt counted, at the usage it reported; one whose usage never came (a broken stream) is charged
   its worst case, never less than it was billed;
2. the ledger's total never passes ``--max-total-tokens`` or ``--max-cost`` (priced as the project prices).
"""

from __future__ import annotations

import os
import random

import pytest

from tests.conftest import ROOT, run_main
from tests.test_providers import KEYS, _runs

MAX_TOKENS = 300
"""The reply length asked for in these tests: a reply cut at the token limit is billed this many tokens."""


def _entry(rng: random.Random, stream: bool, text: str = "No change.") -> dict:
    """One random answer of the mix: billed ones with their usage (a reply, an empty answer, a reply cut at the
    token limit, a stream that broke midway) and unbilled errors (429, 503)."""
    usage = {"output": rng.randint(5, MAX_TOKENS - 1)}  # MAX_TOKENS: a reply cut at the limit (the oracle's rule)
    if rng.random() < 0.5:  # else the prompt's words, as a provider bills the prompt it was sent (in optimize about
        usage["input"] = rng.randint(100, 900)  # what a call's worst case reserves for it: where retries press)
    kinds = ["reply", "empty", "empty", "length", "429", "503"] + (["cut", "broken"] if stream else [])
    kind = rng.choice(kinds)
    if kind == "reply":
        return {"content": text, "usage": usage}
    if kind == "empty":
        return {"content": "", "usage": usage}
    if kind == "length":
        return {"content": text, "finish": "length", "usage": {**usage, "output": MAX_TOKENS}}
    if kind in ("429", "503"):
        return {"status": int(kind)}
    # broken after 1-3 pieces of its text: one that ends before its first event litellm reads as an empty answer
    # that stopped, with a usage it counts itself (the prompt, by its tokenizer), which the client cannot tell apart
    return {"content": "one two three four five six", "usage": usage,
            "stream_cut" if kind == "cut" else "stream_error": rng.randint(1, 3)}


CLIENT_ROUTES = [("openai", False), ("openai", True), ("anthropic", True)]


def _counts(answer) -> list:
    """(input, output) of each attempt an answer says was billed; None for one whose usage never came."""
    return [(a.input_tokens, a.output_tokens) if a.input_tokens is not None else None for a in answer.billed]


@pytest.mark.parametrize("seed", range(12))
def test_a_call_s_usage_is_every_billed_attempt_s(tmp_path, seed):
    """Oracle 1 for ``LiteLLMClient``: a call retried after billed attempts (an empty answer, a broken stream)
    recorded only its last attempt's usage; it carries the sum of every attempt the ledger billed, each
    attempt's own usage, and the last one's finish reasons."""
    from pipeline.llm.client import LiteLLMClient, LLMError
    from tests.scripted_llm import ScriptedModel

    rng = random.Random(seed)
    provider, stream = CLIENT_ROUTES[seed % len(CLIENT_ROUTES)]
    script = [_entry(rng, stream) for _ in range(24)] + [{"content": "done", "usage": {"input": 7, "output": 3}}]
    with ScriptedModel(script, tmp_path / "model") as model:
        route, base = model.route(provider)
        client = LiteLLMClient(route, api_base=base, api_key="sk-scripted", retries=3, backoff_s=0.001,
                               timeout_s=30, structured=False, stream=stream, max_tokens=MAX_TOKENS)
        seen = 0
        for call in range(5):
            try:
                answer = client.complete([{"role": "user", "content": f"call {call}"}])
            except LLMError as exc:
                answer = exc.answer
            ledger = model.billed()[seen:]
            seen += len(ledger)
            billed = [line for line in ledger if line["billed"]]
            if not billed:
                assert answer is None, (seed, call, ledger)
                continue
            reported = [(line["input"], line["output"]) if line["reported"] else None for line in billed]
            what = (seed, call, script, ledger)
            if all(reported):  # every billed attempt said what it cost: the call's usage is their sum
                assert (answer.input_tokens, answer.output_tokens) == (
                    sum(r[0] for r in reported), sum(r[1] for r in reported)), what
            else:  # a broken stream's usage never came: the sum is not known, each attempt is
                assert answer.input_tokens is None, what
            assert _counts(answer) == reported, what
            last = billed[-1]
            assert answer.finish_reasons == ([] if not last["reported"] else
                                              ["length"] if last["output"] == MAX_TOKENS else ["stop"]), what


def test_a_retry_of_a_billed_attempt_is_asked_of_the_budget_and_a_refusal_ends_the_call(tmp_path):
    """``before_retry`` is asked before an answered (billed) attempt is retried, never before a rate limit's;
    when it refuses, the call ends there as ``BudgetSpent``, with the usage of what was billed."""
    from pipeline.llm.client import BUDGET_SPENT, LiteLLMClient, LLMError
    from tests.scripted_llm import ScriptedModel

    script = [{"status": 429}, {"content": "", "usage": {"input": 40, "output": 2}},
              {"content": "", "usage": {"input": 50, "output": 3}}, "never asked"]
    with ScriptedModel(script, tmp_path / "model") as model:
        route, base = model.route("openai")
        client = LiteLLMClient(route, api_base=base, api_key="sk-scripted", retries=3, backoff_s=0.001,
                               timeout_s=30, structured=False)
        asked = []

        def before_retry(attempt):
            asked.append((attempt.input_tokens, attempt.output_tokens))
            return None if len(asked) < 2 else "no room for another"

        with pytest.raises(LLMError) as caught:
            client.complete([{"role": "user", "content": "hello"}], before_retry=before_retry)
        assert len(model.raw_requests()) == 3
    error = caught.value
    assert asked == [(40, 2), (50, 3)]
    assert error.error_type == BUDGET_SPENT and not error.fatal and "no room for another" in error.message
    assert (error.answer.input_tokens, error.answer.output_tokens, error.attempts) == (90, 5, 3)


def _ledger_cost(lines: list[dict]) -> float:
    from pipeline.llm.providers import price

    rates = price("openai/gpt-4o")
    return sum(rates.cost(line["input"], line["output"]) for line in lines if line["billed"])


BUDGETS = [("--max-total-tokens", 9_000), ("--max-cost", 0.02), ("--max-total-tokens", 20_000), ("--max-cost", 0.05)]
"""Budgets of about three and eight calls' worst case (a prompt of up to 3,000 tokens, a reply of 300)."""


def _optimize_here(store, model, monkeypatch, capfd, *args: str):
    """``codearcade optimize`` of Pong against ``model`` (as gpt-4o, priced) with replies of :data:`MAX_TOKENS` and
    prompts of 3,000 tokens, and ``args``, run by the command line's main in this process (tests/conftest.py's
    run_main: a process of its own spent ~7 s of CPU importing litellm, which this process has imported for the
    tests above); nothing it or its game processes wrote is a traceback."""
    route, base = model.route("openai", "gpt-4o")
    for key in [k for k in os.environ if k.endswith("_API_KEY")]:
        monkeypatch.delenv(key)
    for key, value in {**KEYS, "OPENAI_API_KEY": KEYS["ANTHROPIC_API_KEY"], "CODEARCADE_LLM_BACKOFF_S": "0.05",
                       "LITELLM_LOCAL_MODEL_COST_MAP": "True"}.items():
        monkeypatch.setenv(key, value)
    monkeypatch.chdir(ROOT)
    capfd.readouterr()
    done = run_main("optimize", "--game", "pong", "--model", route, "--api-base", base, "--store", str(store.path),
                    "--eval-max-steps", "200", "--rollout-steps", "60", "--workers", "2", "--audit-episodes", "0",
                    "--token-budget", "3000", "--max-tokens", str(MAX_TOKENS), *args)
    children = capfd.readouterr().err  # what its game processes wrote to stderr
    assert "Traceback" not in done.stderr + children, done.stderr + children
    return done


@pytest.mark.slow
def test_optimize_retries_a_billed_attempt_only_if_the_budget_still_has_room(store, scripted, monkeypatch, capfd):
    """The optimizer's answer before a billed attempt is retried (``budgets.retry_budget``): an empty answer billed
    8,300 tokens leaves no room under --max-total-tokens 9,000, beside the call's worst case reserved (its prompt
    and a reply of 300), for a retry that may be billed as much; the call ends there, the run as ``budget``, and the
    ledger stays within the budget (retried, it would be billed 16,600). The fuzzer below, its
    bills then all smaller than a prompt, did not fail when this question went unasked."""
    model = scripted([{"content": "", "usage": {"input": 8_000, "output": 300}},
                      {"content": "No change.", "usage": {"input": 8_000, "output": 300}}])
    done = _optimize_here(store, model, monkeypatch, capfd, "--iterations", "2", "--max-total-tokens", "9000")
    ledger = model.billed()
    assert sum(line["input"] + line["output"] for line in ledger if line["billed"]) == 8_300, (ledger, done.stderr)
    assert _runs(store)[0][1] == "budget", done.stderr
    assert store.query("SELECT error_type, input_tokens, output_tokens FROM llm_calls") == \
        [("BudgetSpent", 8_000, 300)], done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(6))
def test_optimize_records_and_budgets_every_billed_attempt(store, scripted, seed, monkeypatch, capfd):
    """Oracles 1 and 2 for ``codearcade optimize`` under a budget, over seeded mixes: ``llm_calls`` recorded each
    call's last attempt only (an empty answer retried three times was a quarter of its bill), and the budget
    reserved one worst case per call while a call could be billed four: the ledger passed ``--max-total-tokens``
    and ``--max-cost``. Now each row is its call's attempts in the ledger (exactly, or at least where a broken
    stream's usage was estimated), and the ledger stays within the budget."""
    from tests.conftest import COMPETENT_REPLY

    rng = random.Random(1000 + seed)
    flag, limit = BUDGETS[seed % len(BUDGETS)]
    script = [_entry(rng, True, COMPETENT_REPLY if rng.random() < 0.2 else "No change.") for _ in range(80)]
    model = scripted(script)
    done = _optimize_here(store, model, monkeypatch, capfd, "--iterations", "8", "--stream", flag, str(limit))
    ledger = sorted(model.billed(), key=lambda line: line["request"])
    rows = store.query("SELECT attempts, input_tokens, output_tokens, cost_usd, usage_estimated FROM llm_calls "
                       "ORDER BY created_at")
    what = (seed, script, ledger, rows, _runs(store), done.stderr[-2000:])
    assert sum(r[0] for r in rows) == len(ledger), what  # each request is an attempt of one recorded call
    at = 0
    for attempts, inputs, outputs, cost, estimated in rows:
        lines = [line for line in ledger[at: at + attempts] if line["billed"]]
        at += attempts
        billed_tokens = sum(line["input"] + line["output"] for line in lines)
        if not lines:
            assert (inputs, outputs) == (None, None), what
        elif estimated:  # a broken stream's usage never came: charged its worst case, never less
            assert inputs + outputs >= billed_tokens and cost >= _ledger_cost(lines) - 1e-12, what
        else:
            assert (inputs, outputs) == (sum(line["input"] for line in lines),
                                         sum(line["output"] for line in lines)), what
            assert cost == pytest.approx(_ledger_cost(lines), rel=1e-9), what
    if flag == "--max-total-tokens":
        assert sum(line["input"] + line["output"] for line in ledger) <= limit, what
    else:
        assert _ledger_cost(ledger) <= limit, what
    status = _runs(store)[0][1]
    assert status in ("budget", "finished"), what
    ended = store.query("SELECT count(*) FROM llm_calls WHERE error_type = 'BudgetSpent'")[0][0]
    assert not ended or status == "budget", what  # a retry the budget had no room for ends the run as its budget
    print(f"seed {seed}: {len(rows)} calls, {len(ledger)} requests, {ended} ended by the budget, run {status}")
