"""What the optimizer's prompt shows, read from the store: the context of one update (:class:`PromptContext`).

:func:`context_for` reads, for the candidate being improved, the policy text of its version, its traced training
rollout (steps and node calls), its evaluation episodes and feedback, and the candidates its strategy chose as
memory; :func:`read_context` does it for the paper's (``greedy``) update. Everything comes from the store, never
from objects in memory: if it is not stored, the optimizer cannot see it. ``pipeline/optimizer/prompt.py``
renders a context under the token budget.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import duckdb

from games import get_game, list_widths
from games.base import recorded_observation
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.strategies import Greedy, History, Ref
from pipeline.settings import EpisodeLimits, recorded_settings
from store.held_values import held_bytes
from store.readers import candidates, episode_steps, episode_summaries, get_run, iterations, policy_texts, step_nodes
from tracing.policy_file import PolicyInfo, inspect_policy


@dataclass
class MemoryEntry:
    iteration: int
    score: float | None
    update_status: str
    feedback: str
    sources: dict[str, str]


@dataclass
class PromptContext:
    """What a prompt is made of, as read from the store."""

    game: str
    instruction: str
    info: PolicyInfo
    train_episode: dict[str, Any]
    train_steps: list[dict[str, Any]]
    train_nodes: list[dict[str, Any]]
    eval_episodes: list[dict[str, Any]]
    feedback: str
    memory: list[MemoryEntry] = field(default_factory=list)
    call_time_limit_s: float = EpisodeLimits.call_time_limit_s
    collapse_repeats: bool = False
    """Show runs of steps whose calls, outputs and actions repeat as one line each (``OptimizeConfig``)."""


def read_context(
    con: duckdb.DuckDBPyConnection,
    run_id: str,
    next_iteration: int,
    memory: int,
    call_time_limit_s: float = EpisodeLimits.call_time_limit_s,
    collapse_repeats: bool = False,
) -> PromptContext:
    """The context of the paper's (``greedy``) update that starts iteration ``next_iteration`` of ``run_id``.

    The update improves the version of the previous iteration, or, if that iteration rolled back, the best
    version: its rollout, evaluation and feedback are shown, with a note on the rollback. Memory holds up to
    ``memory`` earlier iterations, newest first.
    """
    history = History(iterations(con, run_id, before_iteration=next_iteration),
                      candidates(con, run_id, before_iteration=next_iteration))
    if len(history.iterations) < next_iteration:
        raise KeyError(f"run {run_id} has no iteration {next_iteration - 1}")
    (request,) = Greedy(memory=memory).plan(history, next_iteration)
    return context_for(con, run_id, history, request.parent, request.memory, request.note, call_time_limit_s,
                       collapse_repeats)


def context_for(
    con: duckdb.DuckDBPyConnection,
    run_id: str,
    history: History,
    parent: Ref,
    memory: list[Ref],
    note: str = "",
    call_time_limit_s: float = EpisodeLimits.call_time_limit_s,
    collapse_repeats: bool = False,
) -> PromptContext:
    """The context of an update that improves the candidate ``parent``, from the store alone: its code, its
    traced training rollout, its evaluation and feedback (after ``note``), and the candidates in ``memory``."""
    base = history.candidate(parent)
    run = get_run(con, run_id)
    config = recorded_settings(OptimizeConfig, run["config"], run_id, ("observation",))  # anyone's file: checked
    game = get_game(run["game"]).observing(recorded_observation(config))  # read back as the run played it
    rows = [history.candidate(ref) for ref in memory]
    texts = policy_texts(con, run_id, [base["policy_version_id"]] + [row["policy_version_id"] for row in rows])
    info = inspect_policy(texts[base["policy_version_id"]], "policy.py")
    train_steps, train_nodes = _rollout(con, base["train_episode_id"], game)
    entries = [MemoryEntry(row["iteration"], row["score"], row["update_status"], row["feedback"] or "",
                           dict(_trainable_sources(texts[row["policy_version_id"]]))) for row in rows]
    train_episode, *eval_episodes = episode_summaries(con, [base["train_episode_id"], *(base["eval_episode_ids"] or [])])
    return PromptContext(
        game=game.name,
        instruction=config.get("instruction") or "",
        info=info,
        train_episode=train_episode,
        train_steps=train_steps,
        train_nodes=train_nodes,
        eval_episodes=eval_episodes,
        feedback=note + (base["feedback"] or ""),
        memory=entries,
        call_time_limit_s=call_time_limit_s,
        collapse_repeats=collapse_repeats,
    )


@lru_cache(maxsize=256)
def _trainable_sources(text: str) -> tuple[tuple[str, str], ...]:
    """(name, source) of the trainable methods of a stored policy file (memory shows earlier versions again
    and again: each is parsed once)."""
    return tuple((m.name, m.source) for m in inspect_policy(text, "policy.py").trainable)


_ROLLOUTS: dict[str, tuple[list[dict[str, Any]], list[dict[str, Any]], int]] = {}
ROLLOUTS_KEPT = 8
VALUE_CHARS = 300
"""Characters of each node value the prompt shows (``prompt.py``): all the store is asked for, so a kept rollout
holds a few kilobytes a call, whatever its policy stored (``store.readers.step_nodes``)."""
ROLLOUT_NODE_BYTES = 128 * 2**20
"""What one rollout's node calls may hold, as ``store.held_values.held_bytes`` estimates it (about twice what they
hold): an honest rollout's are a few MB (1.5 MB for 120 steps of Pong's starter, 800 calls; ~60 MB for a helper
called for each of Breakout's bricks, 300 steps); the calls past it are not read, and the prompt shows those
steps without calls."""
KEPT_NODE_BYTES = 2 * ROLLOUT_NODE_BYTES
"""What the kept rollouts' node calls may hold together: the oldest go first."""


def _rollout(con: duckdb.DuckDBPyConnection, episode_id: str, game) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The steps and node calls of a training rollout. A stored episode never changes and its id is unique (a
    ULID run id in it), and the same parent's rollout is shown to each of its children, iteration after
    iteration: the last few are kept in memory."""
    if episode_id not in _ROLLOUTS:
        nodes = step_nodes(con, episode_id, value_chars=VALUE_CHARS, max_bytes=ROLLOUT_NODE_BYTES)
        held = held_bytes(nodes)
        while _ROLLOUTS and (len(_ROLLOUTS) >= ROLLOUTS_KEPT
                             or held + sum(kept[2] for kept in _ROLLOUTS.values()) > KEPT_NODE_BYTES):
            _ROLLOUTS.pop(next(iter(_ROLLOUTS)))
        steps = episode_steps(con, episode_id, list_widths=list_widths(game), derive=game.derive)
        _ROLLOUTS[episode_id] = (steps, nodes, held)
    steps, nodes, _ = _ROLLOUTS[episode_id]
    return steps, nodes
