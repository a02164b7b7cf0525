"""``codearcade optimize --dry-run``: what one update and a whole run would cost, without calling a model.

The estimate is built from a real iteration 0: the starting policy is evaluated (a traced training rollout
and the evaluation episodes, exactly as a run does) into a temporary store that is thrown away afterwards,
and the prompt of the first update is built from it under the run's token budget and counted with the
model's tokenizer (``pipeline/llm/tokens.py``). Costs use litellm's price table (``pipeline/llm/providers.py``):

- one update: that prompt, plus a reply as long as ``--max-tokens`` (the most it can cost), and plus a
  typical reply of :data:`TYPICAL_REPLY_TOKENS`;
- the whole run: every update's prompt is at most the token budget (memory and trace grow until it is
  full), so ``iterations x (budget + max_tokens)`` bounds it, and ``iterations x`` the first update is the
  low end.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pipeline.optimizer.config import OptimizeConfig

from pipeline.llm.providers import Price, price
from pipeline.llm.tokens import TokenCounter
from pipeline.optimizer.context import read_context
from pipeline.optimizer.loop import load_state, run_iteration, start_run
from pipeline.optimizer.prompt import Prompt, build_prompt
from pipeline.optimizer.propose import repair_limit
from store import Store

TYPICAL_REPLY_TOKENS = 1_500
"""A reply that rewrites two or three methods with a short reasoning: the middle of the estimate."""


@dataclass
class Estimate:
    model: str
    iterations: int
    """LLM calls of the run: its iterations times the calls its strategy makes per iteration (at most)."""
    token_budget: int
    max_tokens: int
    prompt: Prompt
    price: Price | None
    starter_score: float | None
    """The starting policy's score; None when it forfeited (``starter_forfeit`` says what ended its game)."""
    mix: list[tuple[str, float, Price | None]] | None = None
    """An ensemble's models: (model, expected share of the calls, its price); ``price`` is then their blend, and
    the most a call can cost is at the dearest model's price."""
    repair_calls: int = 0
    """The most repair turns the run can make (``--repairs`` for every update, within a call budget)."""
    starter_forfeit: str | None = None
    repair_tokens: int = 0
    """The longest a repair conversation may be (``propose.repair_limit``)."""

    @property
    def dearest(self) -> Price | None:
        if not self.mix:
            return self.price
        return max((p for _, _, p in self.mix), key=lambda p: p.cost(self.token_budget, self.max_tokens))

    def update_cost(self, reply_tokens: int) -> float | None:
        return None if self.price is None else self.price.cost(self.prompt.tokens, reply_tokens)

    def run_cost_range(self) -> tuple[float, float] | None:
        if self.price is None:
            return None
        return (self.iterations * self.price.cost(self.prompt.tokens, TYPICAL_REPLY_TOKENS),
                self.iterations * self.dearest.cost(self.token_budget, self.max_tokens)
                + self.repair_calls * self.dearest.cost(self.repair_tokens, self.max_tokens))

    def as_dict(self, include_prompt: bool = False) -> dict[str, Any]:
        out: dict[str, Any] = {
            "model": self.model, "iterations": self.iterations, "token_budget": self.token_budget,
            "max_tokens": self.max_tokens, "starter_score": self.starter_score,
            "starter_forfeit": self.starter_forfeit, "repair_calls": self.repair_calls,
            "prompt_tokens": self.prompt.tokens, "token_count_method": self.prompt.token_method,
            "steps_shown": len(self.prompt.steps_shown), "priced": self.price is not None,
            "update_cost_usd": None if self.price is None else {
                "typical": self.update_cost(TYPICAL_REPLY_TOKENS),
                "at_most": self.dearest.cost(self.prompt.tokens, self.max_tokens)},
            "run_cost_usd": None if self.price is None else dict(zip(("typical", "at_most"), self.run_cost_range())),
        }
        if self.mix:
            out["models"] = [{"model": m, "share": share, "priced": p is not None,
                              "update_cost_usd": None if p is None else p.cost(self.prompt.tokens,
                                                                               TYPICAL_REPLY_TOKENS)}
                             for m, share, p in self.mix]
        if include_prompt:
            out["prompt"] = self.prompt.messages
        return out

    def lines(self) -> list[str]:
        scored = f"scored {self.starter_score:g}" if self.starter_score is not None else \
            f"forfeited ({self.starter_forfeit or 'no score'}): the loop would start from a policy that scores nothing"
        out = [f"dry run for {self.model}: starting policy {scored}",
               f"first prompt: {self.prompt.tokens:,} tokens of a {self.token_budget:,}-token budget "
               f"({len(self.prompt.steps_shown)} rollout steps shown; {self.prompt.token_method})"]
        for name, share, rates in self.mix or ():
            out.append(f"model {name}: {share:.0%} of the calls, " + (
                f"${rates.cost(self.prompt.tokens, TYPICAL_REPLY_TOKENS):.4f} an update" if rates is not None
                else "no price in litellm"))
        if self.price is None:
            most = (self.iterations * (self.token_budget + self.max_tokens)
                    + self.repair_calls * (self.repair_tokens + self.max_tokens))
            unpriced = [name for name, _, rates in self.mix if rates is None] if self.mix else [self.model]
            out.append(f"cost: litellm has no price for {', '.join(unpriced)} (a local or unknown model"
                       f"{'s' * (len(unpriced) > 1)}); tokens per update "
                       f"up to {self.token_budget + self.max_tokens:,}, for the run up to {most:,}{self._repairs()}")
            return out
        low, high = self.run_cost_range()
        out.append(f"one update: ${self.update_cost(TYPICAL_REPLY_TOKENS):.4f} with a typical "
                   f"{TYPICAL_REPLY_TOKENS:,}-token reply{' (the mix)' if self.mix else ''}, at most "
                   f"${self.dearest.cost(self.prompt.tokens, self.max_tokens):.4f} "
                   f"(a {self.max_tokens:,}-token reply)")
        out.append(f"whole run ({self.iterations} LLM calls): about ${low:.2f}, at most ${high:.2f} (every prompt "
                   f"filling the budget{self._repairs()}); cap it with --max-cost USD")
        return out

    def _repairs(self) -> str:
        return f"; with up to {self.repair_calls} repair turns" if self.repair_calls else ""


def estimate_run(config: OptimizeConfig, progress_log: Callable[[str], None] = lambda s: None) -> Estimate:
    """Evaluate the starting policy into a temporary store and price the first update (module docstring)."""
    from pipeline.llm.client import OFFLINE_MODEL_LABEL

    model = config.model or OFFLINE_MODEL_LABEL
    with tempfile.TemporaryDirectory(prefix="codearcade-dry-run-") as tmp:
        store = Store(Path(tmp) / "dry-run.duckdb")
        run_id = start_run(config, store, model)
        state = load_state(store, run_id)
        progress_log("dry run: evaluating the starting policy (iteration 0)...")
        first = run_iteration(store, state, 0, None, None, progress_log)
        with store.read() as con:
            ctx = read_context(con, run_id, 1, config.memory, config.call_time_limit_s, config.collapse_repeats)
        prompt = build_prompt(ctx, config.token_budget, TokenCounter(config.model or "offline"))
    calls = config.iterations * state.strategy.max_proposals
    repairs = calls * config.repairs  # at most: every update rejected, every repair too
    if config.max_llm_calls is not None:
        calls = min(calls, config.max_llm_calls)
        repairs = min(repairs, config.max_llm_calls - calls)
    if config.models:
        found = _ensemble_estimate(config, calls, prompt, first.score)
    else:
        found = Estimate(model, calls, config.token_budget, config.max_tokens, prompt,
                         price(config.model) if config.model else None, first.score)
    found.repair_calls, found.repair_tokens = repairs, repair_limit(config)
    found.starter_forfeit = first.forfeit
    return found


def _ensemble_estimate(config: OptimizeConfig, calls: int, prompt: Prompt, starter_score: float | None) -> Estimate:
    """An ensemble's estimate: each model's expected share of the calls (``fixed``: its weight's; a bandit
    learns its shares, so each model is taken at an equal share), the blended price, and the dearest model's
    for the most a call can cost. A model litellm cannot price leaves the mix unpriced (tokens only)."""
    weights = [float(e["weight"]) if config.model_choice == "fixed" else 1.0 for e in config.models]
    mix = [(e["model"], w / sum(weights), price(e["model"])) for e, w in zip(config.models, weights)]
    blend = None
    if all(p is not None for _, _, p in mix):
        blend = Price(sum(s * p.input for _, s, p in mix), sum(s * p.output for _, s, p in mix))
    label = " + ".join(e["model"] for e in config.models) + f" ({config.model_choice})"
    return Estimate(label, calls, config.token_budget, config.max_tokens, prompt, blend, starter_score, mix=mix)
