"""What the optimization loop carries from one iteration to the next (:class:`RunState`), apart from the loop
itself, so that *propose* and *assess* can read it without importing the loop that imports them."""

from __future__ import annotations

import threading
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any, Callable, ContextManager

from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.strategies import History, Strategy, make_strategy


@dataclass
class RunState:
    """What the loop carries from one iteration to the next (all of it derivable from the store)."""

    run_id: str
    game: str
    config: OptimizeConfig
    settings: dict[str, Any]
    next_iteration: int = 0
    best_score: float | None = None
    best_iteration: int = 0
    best_version_id: str | None = None
    llm_failures: int = 0
    wall_deadline: float | None = None
    """When the run's time budget (``--max-wall``) runs out, on ``time.monotonic()``'s clock, as last worked out by
    ``budgets.check_wall``: an LLM call still in flight then is given up on. None without a time budget."""
    rng_key: str | None = None
    """The key of the run's random stream for policies (``EpisodeSpec.rng_key``; None: a run recorded before it)."""
    history: History | None = None
    """The run's completed iterations as stored: read from the store once, then extended by each commit with
    the rows it wrote (``test_strategies.py`` checks it against the store)."""
    pool_bases: dict[tuple[int, int], tuple[int, tuple[tuple[int, int], ...]]] | None = None
    """The proposal pool's recorded bases to start candidates from (``store.readers.pool_bases``: the iterations
    committed and the candidates assessed but not committed that each first call's prompt was built from): a
    replay's are its original run's; None: the run's own (``--resume``)."""
    model_choices: dict[tuple[int, int], dict[str, Any]] = field(default_factory=dict, repr=False, compare=False)
    """An ensemble's reason for each (iteration, candidate) chosen and not yet asked (``ensemble.member_picks``):
    what its first call's ``llm_calls.model_choice`` records."""
    rerun: str | None = None
    """Live Rerun recordings of this invocation's episodes (``EpisodeSpec.rerun``); an output option, not recorded."""
    waiting: Callable[[int, str], ContextManager[Callable[[str], None] | None]] = lambda it, model: nullcontext()
    """Wrapped around each iteration's LLM calls (iteration, model label); what it yields gets the streamed text,
    if any. The CLI shows how long it has been waiting and how much text has arrived."""

    # the proposal pool's calls in flight: their worst case reserved (calls, tokens, cost), and a condition that a
    # call waits on while only those reservations stand between it and the budget
    budget_lock: threading.Condition = field(default_factory=threading.Condition, repr=False, compare=False)
    in_flight: list[float] = field(default_factory=lambda: [0, 0, 0.0], repr=False, compare=False)
    """The worst case of the calls checked against the budgets and not yet recorded: calls, tokens, USD (the
    proposal pool's threads check theirs while others are in flight: ``budgets.check_budgets``)."""
    budget_turn: int = field(default=0, repr=False, compare=False)
    """The proposal pool's candidates check the budgets in the order they started (their *ticket*): the next
    ticket whose check may go. Without the order a candidate started later, whose thread built its prompt faster,
    could take the last call of the budget from one before it, and leave that one's iteration never committed."""
    budget_turns_passed: set[int] = field(default_factory=set, repr=False, compare=False)
    """Tickets past their turn (checked, or ended without a call) that ``budget_turn`` has not reached yet."""

    @property
    def strategy(self) -> Strategy:
        c = self.config
        return make_strategy(c, self.settings.get("eval_max_steps"))
