"""The budgeted bandit of an ensemble: which model makes the next call, by improvement per unit of the budget that
binds the run. Pure functions of the numbers it is given (``pipeline/optimizer/ensemble.py`` reads them from the
store); written from the papers, no code copied.

**The method** is Budgeted Thompson Sampling (BTS: Xia, Li, Qin, Yu and Liu, "Thompson Sampling for Budgeted
Multi-armed Bandits", IJCAI 2015): each model's chance to improve has a Beta posterior, and the model with the
largest ``reward / cost per pull`` wins, ``reward`` drawn from its posterior (``thompson``) or, deterministically,
its upper quantile (``ucb``: the Bayes-UCB index of Kaufmann, Cappé and Garivier, "On Bayesian Upper Confidence
Bounds for Bandit Problems", AISTATS 2012, over the same cost per pull). BTS samples the cost too; here a call's
cost is known to within its token count, so the cost per pull is its posterior mean (one reference pull as the
prior, then what the model's calls actually used).

**The budget that binds** is the unit of cost: calls under ``--max-llm-calls``, dollars under ``--max-cost``,
tokens under ``--max-total-tokens``, seconds under ``--max-wall``; with several, the one that leaves the fewest
pulls at the models' mean cost per pull (the one nearest to running out); with none, calls. Under a call budget
every model costs one call per pull (repair turns add theirs), whatever its price: cheapness buys nothing there.

**What keeps it honest over a short run** (24 calls, a 16.7x price ratio: ``tests/test_ensemble.py`` sweeps it):

- *a skeptical prior*, Beta(:data:`PRIOR`) on the share of the run's largest improvement a pull brings (mean 0.25):
  a model that never improves falls behind one that does after its first pull or two;
- *the optimism of ucb grows with the budget spent, not with the pulls*: its quantile is ``1 - 1/(1 + tau)``
  where ``tau`` is the budget spent so far counted in pulls of the dearest model (under a call budget, the calls:
  Bayes-UCB's own ``1 - 1/t``). Counting cheap pulls as time would make the cheap model's index ever more
  optimistic the more it is pulled; the old rule (a UCB1 bonus divided by the price, fractional KUBE's index)
  explored a 16.7x cheaper model for hundreds of calls;
- *a floor*: a model is pulled whenever, even after this pull, its part of the budget spent would be at most
  :data:`FLOOR` / (number of models) (5% each for two), so a model that starts improving late is tried again;
- *near ties go to the cheaper model in dollars*: among the models whose index is within :data:`TIE` of the
  best, the one with the lowest price per reference call wins (so two equally good models give most calls to
  the cheaper even under a call budget, where the index itself ignores prices);
- every model is pulled once first, in the order given.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping, Sequence

if TYPE_CHECKING:  # numpy is imported where a choice is drawn: the CLI imports this module for every verb
    import numpy as np

BUDGETS = ("calls", "dollars", "tokens", "seconds")
"""The units a choice can be counted in, in the order that breaks a tie between budgets."""

BUDGET_FLAGS = {"calls": "--max-llm-calls", "dollars": "--max-cost", "tokens": "--max-total-tokens",
                "seconds": "--max-wall"}

PRIOR = (0.5, 1.5)
"""Beta prior (successes, failures) of a model's reward: mean 0.25, worth two pulls."""

FLOOR = 0.1
"""The part of the budget kept for exploration, shared equally by the models (see the module docstring)."""

TIE = 0.1
"""Indices within this fraction of the best count as tied; the cheaper model in dollars wins a tie."""

COST_PRIOR_PULLS = 1.0
"""How many pulls the reference cost of a call counts for in a model's cost per pull."""


@dataclass
class Arm:
    """One model as a choice sees it. ``pulls`` and ``rewards`` (sum of rewards in [0, 1]) include the choices made
    before this one and not yet played (the iteration's earlier candidates, a pool's calls in flight)."""

    model: str
    pulls: float
    rewards: float
    cost: float
    """Estimated cost of one pull, in the unit of the binding budget."""
    price: float | None = None
    """Dollars of a reference call (None: unpriced): what breaks a near tie."""
    improvement: float = 0.0
    """Mean improvement of its played pulls, in points of score (a forfeited parent's counts as the largest)."""

    @property
    def spent(self) -> float:
        return self.pulls * self.cost

    def posterior(self) -> tuple[float, float]:
        return PRIOR[0] + self.rewards, PRIOR[1] + max(self.pulls - self.rewards, 0.0)

    def mean_reward(self) -> float:
        a, b = self.posterior()
        return a / (a + b)


@dataclass
class Choice:
    """One model chosen, and why: what the store records (``llm_calls.model_choice``, :meth:`record`)."""

    pick: int
    rule: str
    budget: str
    why: str
    """``index`` (the largest), ``tie`` (within :data:`TIE` of the largest, and cheaper), ``untried``, ``floor``,
    ``share`` (``fixed``)."""
    arms: list[Arm]
    index: list[float]
    level: float | None = None
    pulls_left: float | None = None

    def record(self) -> dict[str, Any]:
        """The JSON the store keeps: the estimates compared, per model in the order given."""
        return {
            "rule": self.rule, "budget": self.budget, "why": self.why, "model": self.arms[self.pick].model,
            "level": _round(self.level), "pulls_left": _round(self.pulls_left),
            "models": [{"model": a.model, "pulls": _round(a.pulls), "mean_reward": _round(a.mean_reward()),
                        "mean_improvement": _round(a.improvement), "cost": _round(a.cost), "index": _round(i)}
                       for a, i in zip(self.arms, self.index)],
        }


def _round(value: float | None) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return float(f"{value:.6g}")


def seeded(seed_key: str, iteration: int, candidate: int) -> np.random.Generator:
    """The generator of one choice: from the run's key, the iteration and the candidate (the same after a resume
    and in a replay)."""
    import numpy as np

    digest = hashlib.sha256(f"{seed_key}:model:{iteration}:{candidate}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "big"))


def pick(rule: str, arms: Sequence[Arm], budget: str = "calls", rng: np.random.Generator | None = None,
         pulls_left: float | None = None) -> Choice:
    """The model of the next pull by ``ucb`` or ``thompson`` (module docstring); ``rng`` draws thompson's samples."""
    import numpy as np

    k = len(arms)
    zeros = [0.0] * k
    untried = [i for i, a in enumerate(arms) if a.pulls <= 0]
    if untried:
        return Choice(untried[0], rule, budget, "untried", list(arms), zeros, pulls_left=pulls_left)
    spent = sum(a.spent for a in arms)
    share = FLOOR / k
    below = [i for i, a in enumerate(arms) if a.spent + a.cost <= share * (spent + a.cost)]
    if below:
        first = min(below, key=lambda i: (arms[i].spent / spent if spent else 0.0, i))
        return Choice(first, rule, budget, "floor", list(arms), zeros, pulls_left=pulls_left)
    level = None
    if rule == "ucb":
        tau = spent / max(a.cost for a in arms)
        level = 1.0 - 1.0 / (1.0 + tau)
        a, b = np.array([arm.posterior() for arm in arms]).T
        from scipy import stats  # here: importing it takes ~1 s, which every command paid (the CLI imports this)

        reward = stats.beta.ppf(level, a, b)
    elif rule == "thompson":
        a, b = np.array([arm.posterior() for arm in arms]).T
        reward = (rng or np.random.default_rng(0)).beta(a, b)
    else:
        raise ValueError(f"no bandit rule {rule!r}")
    index = [float(r) / arm.cost for r, arm in zip(reward, arms)]
    best = max(range(k), key=lambda i: (index[i], -i))
    near = [i for i in range(k) if index[i] >= index[best] * (1.0 - TIE)]
    why = "index"
    if len(near) > 1 and all(arms[i].price is not None for i in near):
        cheapest = min(near, key=lambda i: (arms[i].price, -index[i], i))
        if cheapest != best:
            best, why = cheapest, "tie"
    return Choice(best, rule, budget, why, list(arms), index, level=level, pulls_left=pulls_left)


def fixed_pick(arms: Sequence[Arm], weights: Sequence[float]) -> Choice:
    """``fixed``: the model furthest below its share of the calls (``weight / sum``; ties to the first)."""
    total, pulled = sum(weights), sum(a.pulls for a in arms)
    deficit = [w / total * (pulled + 1) - a.pulls for w, a in zip(weights, arms)]
    best = max(range(len(arms)), key=lambda i: (deficit[i], -i))
    return Choice(best, "fixed", "calls", "share", list(arms), deficit)


# ------------------------------------------------------------------------------------ costs and the budget


@dataclass(frozen=True)
class CallUsage:
    """What one LLM call of the committed history used (None where not reported)."""

    model: str
    tokens: int | None
    dollars: float | None
    seconds: float | None


def unit(call: CallUsage, budget: str, reference: float) -> float:
    """One call's cost in ``budget``'s unit (``reference`` where it reported none)."""
    if budget == "calls":
        return 1.0
    value = {"dollars": call.dollars, "tokens": call.tokens, "seconds": call.seconds}[budget]
    return reference if value is None else float(value)


def costs_per_pull(budget: str, models: Sequence[str], calls: Sequence[CallUsage], pulls: Mapping[str, float],
                   reference: Sequence[float], overhead: float = 0.0) -> list[float]:
    """Each model's cost per pull in ``budget``'s unit: ``reference`` (a model's cost of one reference call) counted
    as :data:`COST_PRIOR_PULLS` pulls, with the calls its played pulls made (repair turns included); plus
    ``overhead``, what every pull costs whichever model makes it (seconds: the games played for a candidate)."""
    refs = dict(zip(models, reference))
    used = {m: 0.0 for m in models}
    for call in calls:
        if call.model in used:
            used[call.model] += unit(call, budget, refs[call.model])
    return [(COST_PRIOR_PULLS * ref + used[m]) / (COST_PRIOR_PULLS + pulls.get(m, 0.0)) + overhead
            for m, ref in zip(models, reference)]


def binding_budget(limits: Mapping[str, float | None], spent: Mapping[str, float],
                   per_pull: Mapping[str, Sequence[float]]) -> tuple[str, float | None]:
    """The budget that binds and the pulls it leaves: of the budgets set (``limits``), the one whose remaining
    amount buys the fewest pulls at the models' mean cost per pull; none set: calls, unlimited."""
    best: tuple[float, int, str] | None = None
    for order, budget in enumerate(BUDGETS):
        limit = limits.get(budget)
        if limit is None:
            continue
        costs = per_pull[budget]
        mean = sum(costs) / len(costs) if costs else 1.0
        left = max(limit - spent.get(budget, 0.0), 0.0) / mean if mean > 0 else math.inf
        if best is None or (left, order) < best[:2]:
            best = (left, order, budget)
    return ("calls", None) if best is None else (best[2], best[0])
