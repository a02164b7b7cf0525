"""Model ensembles: several models in one run, and the rule that picks the model of each LLM call.

An ensemble is ``--model`` given more than once (or a batch entry's ``models = [...]``). Each entry is a litellm
model string, optionally followed by comma-separated options (commas never appear in litellm model strings)::

    --model 'openai/gpt-4o-mini,weight=2' --model 'anthropic/claude-sonnet-4-5,api_base=http://proxy:4000'

``weight`` (a number above 0, default 1) is the model's share under ``--model-choice fixed``; ``api_base`` is
its own endpoint (default: ``--api-base``). In a batch file an entry is such a string or a table
``{model = "...", weight = 2, api_base = "..."}``. Each model may appear once: a call's model is how its
``llm_calls`` row (``request_model``) says which arm it pulled.

**The rule, written once.** Every proposal (candidate) of an iteration is one pull of one model, chosen before
the call, in candidate order, from the run's committed history alone (the ``candidates`` of earlier iterations
and the model of each one's ``llm_calls`` row) and a seed derived from the run (its ``rng_key``, the iteration
and the candidate). A resumed iteration therefore chooses again exactly what the killed attempt chose, and
``codearcade replay`` (which plays the same history and uses the original's ``rng_key``) chooses the same.

- A pull's **improvement** is how much its candidate's score beats its parent's (``store.scores.beats``): 0 when
  not better, when it was rejected, unchanged, failed or forfeited, or a version the run already had (a copy of
  an elite or an ancestor its prompt showed: nothing new); a played-out candidate of a forfeited parent
  counts as the largest improvement seen. Its **reward** is the improvement divided by the largest improvement
  any candidate of the run has brought so far (so rewards lie in [0, 1]; all 0 until something improves).
- ``fixed``: each call goes to the model furthest below its share of the calls so far (``weight / sum of
  weights``; ties to the first listed): weights 2 and 1 give exactly 2 of every 3 calls to the first.
- ``ucb`` and ``thompson``: the budgeted bandit of ``pipeline/optimizer/bandit.py`` (Budgeted Thompson Sampling,
  and its Bayes-UCB twin): improvement per unit of the budget that binds the run (calls, dollars, tokens or
  seconds; :func:`budget_costs`), each model's cost per pull estimated from its reference call (prices recorded
  in the run's config when it starts, ``models[i].price``, so a later litellm does not change a run's choices)
  and what its calls of the committed iterations used (``store.readers.bandit_usage``: a replay counts its
  original's, whose calls cost something).

Within one iteration (best-of-n, beam) the earlier choices count as pulls at the model's mean reward, and so do a
proposal pool's calls in flight, so an iteration's calls spread over the models as the rule would spread them one
at a time. Each choice's reason (the estimates it compared) is recorded with its call (``llm_calls.model_choice``).
Nothing here speaks SQL or calls a model: ``store/readers.py`` has the readers.
"""

from __future__ import annotations

import math
import reprlib
from dataclasses import dataclass, replace
from typing import Any, Iterable, Mapping, Sequence

from pipeline.optimizer.bandit import BUDGETS, Arm, CallUsage, Choice, binding_budget, costs_per_pull, fixed_pick, \
    pick, seeded
from store.scores import beats

MODEL_CHOICES = ("fixed", "ucb", "thompson")
"""How each call's model is chosen in an ensemble (module docstring)."""

ENTRY_OPTIONS = ("weight", "api_base")

MAX_PRICE = 1.0
"""The most a recorded price may be, in USD per token (the dearest models ask ~1e-4): more is a damaged store."""


def parse_model_entry(value: Any) -> dict[str, Any]:
    """One ensemble entry as a dict ``{"model", "weight", "api_base"}`` (and ``price`` where recorded), from
    ``'MODEL[,weight=W][,api_base=URL]'`` or a dict; ValueError with one line saying what to fix."""
    if isinstance(value, str):
        model, *options = [part.strip() for part in value.split(",")]
        entry: dict[str, Any] = {"model": model}
        for option in options:
            key, sep, text = option.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or key not in ENTRY_OPTIONS:
                raise ValueError(f"--model {value!r}: {option!r} is not an option of a model; write "
                                 "MODEL[,weight=W][,api_base=URL]")
            if key in entry:
                raise ValueError(f"--model {value!r}: {key} is given twice; give it once")
            if not text.strip():
                raise ValueError(f"--model {value!r}: {key} is empty; give a value or leave it out")
            entry[key] = text.strip()
    elif isinstance(value, Mapping):
        unknown = sorted(set(value) - {"model", "price", *ENTRY_OPTIONS})
        if unknown:
            raise ValueError(f"models: an entry takes model, weight and api_base, not {', '.join(unknown)}")
        entry = dict(value)
    else:
        raise ValueError(f"models: each entry is a model string or a table with model, weight and api_base, "
                         f"not {value!r}")
    model = entry.get("model")
    if not isinstance(model, str) or not model.strip() or any(c.isspace() for c in model.strip()):
        raise ValueError(f"--model {value!r}: give a litellm model string such as openai/gpt-4o")
    weight = entry.get("weight", 1.0)
    try:
        weight = float(weight)
    except (TypeError, ValueError):
        raise ValueError(f"--model {model}: weight must be a number above 0, not {entry.get('weight')!r}") from None
    if not math.isfinite(weight) or weight <= 0:
        raise ValueError(f"--model {model}: weight must be a number above 0, not {entry.get('weight')!r}")
    api_base = entry.get("api_base") or None
    if api_base is not None and not isinstance(api_base, str):
        raise ValueError(f"--model {model}: api_base must be a URL, not {api_base!r}")
    out = {"model": model.strip(), "weight": weight, "api_base": api_base}
    if "price" in entry:  # recorded by a run (``priced``): a store is anyone's file; a one-number price raised an
        # IndexError that marked a resumed run failed, texts were taken as rates (multiplied into strings by the
        # token budget), and NaN or 1e308 (infinite per call) broke the ties prices break
        rates = entry["price"]
        if rates is not None and (not isinstance(rates, list) or len(rates) != 2 or any(
                not isinstance(r, (int, float)) or isinstance(r, bool) or not 0 <= r <= MAX_PRICE for r in rates)):
            raise ValueError(f"models: {model}'s price must be null or [USD per input token, per output token], two "
                             f"numbers from 0 to {MAX_PRICE:g}, not {reprlib.repr(rates)}")
        out["price"] = rates
    return out


def entry_flag(entry: Mapping[str, Any]) -> str:
    """An entry as ``--model`` takes it back: ``MODEL[,weight=W][,api_base=URL]``."""
    text = entry["model"]
    if float(entry.get("weight", 1.0)) != 1.0:
        text += f",weight={float(entry['weight']):g}"
    if entry.get("api_base"):
        text += f",api_base={entry['api_base']}"
    return text


def model_entries(values: Iterable[Any]) -> list[dict[str, Any]]:
    """Every entry of an ensemble, parsed and checked (each model once)."""
    entries = [parse_model_entry(v) for v in values]
    seen = set()
    for entry in entries:
        if entry["model"] in seen:
            raise ValueError(f"--model {entry['model']} is given twice: give each model of an ensemble once "
                             "(its llm_calls rows say which model a call went to)")
        seen.add(entry["model"])
    return entries


def check_models(value: Any) -> None:
    """The ``models`` setting's check (``OptimizeConfig``)."""
    if not isinstance(value, list) or len(value) < 2:
        raise ValueError("models must list at least two models (one model is --model alone)")
    model_entries(value)


def split_model_flags(given: Mapping[str, Any]) -> dict[str, Any]:
    """The settings of the command line or a batch entry with ``--model`` given several times (a list) or a
    ``models`` list turned into ``models`` (parsed entries) and ``model`` (the first entry's, which counts the
    prompt's tokens); a single plain ``--model`` is left exactly as it always was."""
    out = dict(given)
    model = out.get("model")
    if isinstance(model, list):
        if len(model) == 1 and "," not in model[0]:
            out["model"] = model[0]
        elif len(model) == 1:
            entry = parse_model_entry(model[0])
            out["model"], out["api_base"] = entry["model"], entry["api_base"] or out.get("api_base")
        else:
            if out.get("models"):
                raise ValueError("give the ensemble either as --model several times or as models, not both")
            out["models"] = model
    if out.get("models") is not None:
        entries = model_entries(out["models"])
        if len(entries) < 2:
            raise ValueError("models must list at least two models (one model is --model alone)")
        default_base = out.get("api_base")
        out["models"] = [{**e, "api_base": e["api_base"] or default_base} for e in entries]
        out["model"] = entries[0]["model"]
        out["api_base"] = out["models"][0]["api_base"]
    return out


def check_choice(models: list | None, choice: str) -> None:
    """Errors between ``models`` and ``model_choice``: a rule needs several models; weights only mean something to
    ``fixed``."""
    if not models and choice != "fixed":
        raise ValueError(f"--model-choice {choice} chooses among several models: give --model more than once")
    if models and choice != "fixed":
        weighted = [e for e in model_entries(models) if e["weight"] != 1.0]
        if weighted:
            raise ValueError(f"--model {weighted[0]['model']},weight=...: weights are the shares of --model-choice "
                             f"fixed; --model-choice {choice} learns the shares itself")


def priced(entries: list[dict[str, Any]], price_of) -> list[dict[str, Any]]:
    """``entries`` with litellm's price recorded in each (``price``: [USD per input token, per output token], or
    None): what a run's config keeps, so that its choices do not move with litellm's price table."""
    out = []
    for entry in entries:
        rates = entry["price"] if "price" in entry else price_of(entry["model"])
        if rates is not None and not isinstance(rates, (list, tuple)):
            rates = [rates.input, rates.output]
        out.append({**entry, "price": list(rates) if rates is not None else None})
    return out


# ------------------------------------------------------------------------------------------------ the rule


@dataclass(frozen=True)
class Pull:
    """One earlier proposal of the run: which model made it, and the improvement it brought (>= 0, or
    ``math.inf`` for a played-out candidate of a forfeited parent)."""

    model: str
    improvement: float


def pulls(history_candidates: Sequence[Mapping[str, Any]], call_models: Mapping[str, str]) -> list[Pull]:
    """The pulls of a run's committed history: each candidate with an LLM call, in (iteration, candidate) order,
    with the improvement over its parent's score (module docstring)."""
    scores = {(c["iteration"], c["candidate"]): c["score"] for c in history_candidates}
    out = []
    seen: set[str] = set()  # the versions of the candidates before this one
    for c in history_candidates:
        version = c.get("policy_version_id")
        copied = version is not None and version in seen
        if version is not None:
            seen.add(version)
        model = call_models.get(c.get("llm_call_id") or "")
        if model is None or c.get("parent_iteration") is None:
            continue
        parent = scores.get((c["parent_iteration"], c["parent_candidate"] or 0))
        improvement = 0.0
        # a version the run already had (an elite or ancestor copied from the prompt's memory) is nothing new:
        # its score is the cached one, and counting it credited the copier with another model's gain
        if c["update_status"] == "accepted" and not copied and beats(c["score"], parent):
            improvement = math.inf if parent is None else float(c["score"] - parent)
        out.append(Pull(model, improvement))
    return out


def rewards(history: Sequence[Pull]) -> list[tuple[str, float]]:
    """(model, reward in [0, 1]) of each pull: its improvement over the largest one seen."""
    finite = [p.improvement for p in history if math.isfinite(p.improvement)]
    scale = max(finite, default=0.0)
    out = []
    for p in history:
        if math.isinf(p.improvement):
            out.append((p.model, 1.0))
        else:
            out.append((p.model, p.improvement / scale if scale > 0 else 0.0))
    return out


def relative_costs(entries: Sequence[Mapping[str, Any]], prompt_tokens: int, reply_tokens: int) -> list[float]:
    """Each model's price of a reference call relative to the cheapest (all 1 when any has no price)."""
    costs = []
    for entry in entries:
        rates = entry.get("price")
        if not rates or not (rates[0] or rates[1]):
            return [1.0] * len(entries)
        costs.append(prompt_tokens * rates[0] + reply_tokens * rates[1])
    cheapest = min(costs)
    return [c / cheapest for c in costs]


def _arms(entries: Sequence[Mapping[str, Any]], history: Sequence[Pull], costs: Sequence[float],
          prices: Sequence[float | None]) -> list[Arm]:
    """Each model's pulls, rewards and mean improvement in ``history``, at its cost per pull and price."""
    index = {e["model"]: i for i, e in enumerate(entries)}
    arms = [Arm(e["model"], 0.0, 0.0, float(c), p) for e, c, p in zip(entries, costs, prices)]
    finite = [p.improvement for p in history if math.isfinite(p.improvement)]
    largest = max(finite, default=0.0)
    gains = [0.0] * len(arms)
    for pull, (model, reward) in zip(history, rewards(history)):
        if model in index:
            arm = arms[index[model]]
            arm.pulls += 1
            arm.rewards += reward
            gains[index[model]] += largest if math.isinf(pull.improvement) else pull.improvement
    for arm, gain in zip(arms, gains):
        arm.improvement = gain / arm.pulls if arm.pulls else 0.0
    return arms


def decide(rule: str, entries: Sequence[Mapping[str, Any]], history: Sequence[Pull], candidates: Sequence[int],
           seed_key: str, iteration: int, costs: Sequence[float] | None = None, in_flight: Sequence[str] = (),
           budget: str = "calls", prices: Sequence[float | None] | None = None,
           pulls_left: float | None = None) -> list[Choice]:
    """The model of each of ``candidates`` (an iteration's proposals, in order) with the reason for it.
    ``costs``: each model's cost per pull in the unit of ``budget``, the budget that binds (default: 1 each, a call
    budget); ``prices``: each model's dollars per reference call, which break near ties (``pipeline/optimizer/
    bandit.py``); ``in_flight``: the models of calls started before these and not yet in ``history`` (the proposal
    pool's). Those, and the iteration's earlier choices, count as pulls at the model's mean reward so far."""
    if rule not in MODEL_CHOICES:
        raise ValueError(f"--model-choice must be one of {', '.join(MODEL_CHOICES)}, not {rule!r}")
    costs = list(costs) if costs is not None else [1.0] * len(entries)
    prices = list(prices) if prices is not None else [None] * len(entries)
    arms = _arms(entries, history, costs, prices)
    index = {arm.model: i for i, arm in enumerate(arms)}

    def pending(i: int) -> None:  # a pull not played yet, at the model's mean reward
        arm = arms[i]
        arm.rewards += arm.mean_reward() if rule != "fixed" else (arm.rewards / arm.pulls if arm.pulls else 0.0)
        arm.pulls += 1

    for model in in_flight:
        if model in index:
            pending(index[model])
    chosen = []
    weights = [float(e.get("weight", 1.0)) for e in entries]
    for candidate in candidates:
        snapshot = [replace(arm) for arm in arms]
        if rule == "fixed":
            choice = fixed_pick(snapshot, weights)
        else:
            choice = pick(rule, snapshot, budget, seeded(seed_key, iteration, candidate), pulls_left)
        chosen.append(choice)
        pending(choice.pick)
    return chosen


def choose(rule: str, entries: Sequence[Mapping[str, Any]], history: Sequence[Pull], candidates: Sequence[int],
           seed_key: str, iteration: int, costs: Sequence[float] | None = None, in_flight: Sequence[str] = (),
           **options: Any) -> list[int]:
    """The index (in ``entries``) of the model of each of ``candidates``: :func:`decide` without the reasons."""
    return [c.pick for c in decide(rule, entries, history, candidates, seed_key, iteration, costs, in_flight,
                                   **options)]


def reference_prices(entries: Sequence[Mapping[str, Any]], prompt_tokens: int, reply_tokens: int) -> list[float | None]:
    """Each model's dollars for a reference call (a prompt of ``prompt_tokens``, a reply of ``reply_tokens``) at
    its recorded price; all None when any model has none (then no price breaks a tie)."""
    out = []
    for entry in entries:
        rates = entry.get("price")
        if not rates or not (rates[0] or rates[1]):
            return [None] * len(entries)
        out.append(prompt_tokens * rates[0] + reply_tokens * rates[1])
    return out


def budget_costs(config, entries: Sequence[Mapping[str, Any]], history: Sequence[Pull],
                 usage: Mapping[str, Any]) -> tuple[str, float | None, list[float], list[float | None]]:
    """The budget that binds the run, the pulls it leaves, each model's cost per pull in its unit and each
    model's price of a reference call, from the committed history's ``usage`` (``store.readers.bandit_usage``)."""
    models = [e["model"] for e in entries]
    pulled: dict[str, float] = {}
    for p in history:
        pulled[p.model] = pulled.get(p.model, 0.0) + 1
    prices = reference_prices(entries, config.token_budget, config.max_tokens)
    calls = [CallUsage(*row) for row in usage["calls"]]
    limits = {"calls": config.max_llm_calls, "dollars": config.max_cost_usd, "tokens": config.max_total_tokens,
              "seconds": config.max_wall_minutes * 60 if config.max_wall_minutes is not None else None}
    played = sum(pulled.values())
    latency = sum(c.seconds or 0.0 for c in calls)
    reference = {
        "calls": [1.0] * len(models),
        "dollars": [p if p is not None else 1.0 for p in prices],
        "tokens": [float(config.token_budget + config.max_tokens)] * len(models),
        "seconds": [latency / played if played else 1.0] * len(models),
    }
    overhead = {"seconds": usage["play_s"] / played if played else 0.0}
    per_pull = {b: costs_per_pull(b, models, calls, pulled, reference[b], overhead.get(b, 0.0))
                for b in BUDGETS if b == "calls" or limits[b] is not None}
    spent = {"calls": float(len(calls)), "dollars": sum(c.dollars or 0.0 for c in calls),
             "tokens": float(sum(c.tokens or 0 for c in calls)), "seconds": usage["wall_s"]}
    budget, left = binding_budget(limits, spent, per_pull)
    return budget, left, per_pull[budget], prices


def member_picks(store, state, history, iteration: int, candidates: Sequence[int],
                 in_flight: Sequence[str] = ()) -> list[str] | None:
    """The model chosen for each of ``candidates`` (an iteration's proposals, in order) by the run's rule and its
    recorded ``models``, from the committed ``history``; ``in_flight``: the models of the proposal pool's calls
    started before these and not in ``history``. None for a run of one model. The reason of each choice is kept
    in ``state.model_choices[iteration, candidate]`` until its call is recorded (``llm_calls.model_choice``)."""
    entries = state.config.models
    if not entries:
        return None
    from store.readers import bandit_usage, call_models

    with store.read() as con:
        models = call_models(con, state.run_id)
        usage = bandit_usage(con, state.run_id, len(history.iterations))
    c = state.config
    history_pulls = pulls(history.candidates, models)
    budget, left, costs, prices = budget_costs(c, entries, history_pulls, usage)
    choices = decide(c.model_choice, entries, history_pulls, candidates, state.rng_key or state.run_id, iteration,
                     costs, in_flight, budget=budget, prices=prices, pulls_left=left)
    for candidate, choice in zip(candidates, choices):
        state.model_choices[iteration, candidate] = choice.record()
    return [entries[choice.pick]["model"] for choice in choices]


def choose_members(store, state, history, iteration: int, client, items: Sequence[Any]) -> None:
    """Set ``item.client`` to the member of ``client`` (an ``EnsembleClient``) that answers each of ``items``
    (propose's requests): :func:`member_picks`; a single model's client is left alone. Every request of the
    iteration is chosen for (those answered from the store too), so a resumed iteration chooses as before."""
    if not hasattr(client, "member"):
        return
    picks = member_picks(store, state, history, iteration, [item.request.candidate for item in items])
    for item, model in zip(items, picks or ()):
        item.client = client.member(model)
