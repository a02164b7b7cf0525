"""``codearcade replay RUN``: re-run an optimization with the replies stored in the store, not the model.

The replay starts a new run (kind ``replay``) from the original's starting policy and settings, and answers
each LLM call with the stored reply whose prompt hash matches. Since prompts are deterministic, a faithful
re-run sends exactly the original prompts; the first prompt the original run never sent is where the two
diverge (a changed environment, policy code, prompt builder or dependency), and the replay stops there. The
report lists, per iteration, both prompt hashes and both scores.

A run that stopped before its end (killed and never resumed, stopped by a budget, failed) has a record that ends:
the replay reproduces it up to there and stops at the first call the original never made (or never got a reply
to). That is not a divergence: the report says where the record ends ("the run stopped after iteration 2
(interrupted); 4 calls were never recorded"), its status is ``incomplete``, and the replay run ends with its
original's status (``interrupted`` for a run whose process died). Iterations past the original's last committed
one are shown, not compared: the original never decided them (the proposal pool may have recorded every call of
the iterations it had started: then the replay goes on past the record, and says so).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Iterator

from pipeline.llm.client import EnsembleClient, ReplayClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import load_state, new_run, run_loop
from pipeline.optimizer.strategies import make_strategy
from store import Store
from store.readers import (blob_text, first_call_errors, get_run, iteration_prompts, last_iteration, pool_bases,
                           replay_errors, replay_replies)
from store.recorded import read_recorded
from store.runs import kind_phrase
from store.writer import finish_run
from tracing.policy_file import inspect_policy


@dataclass
class ReplayRow:
    iteration: int
    original_prompt: str | None
    replay_prompt: str | None
    original_score: float | None
    replay_score: float | None

    @property
    def matches(self) -> bool:
        return self.original_prompt == self.replay_prompt and self.original_score == self.replay_score


@dataclass
class ReplayReport:
    original_run_id: str
    replay_run_id: str
    status: str
    rows: list[ReplayRow] = field(default_factory=list)
    diverged_at: int | None = None
    record_ends: str | None = None
    """Where an unfinished original's record ends (then ``status`` is ``incomplete``), or None."""
    last_iteration: int | None = None
    """The original's last committed iteration; rows past it are shown, not compared."""
    unrecorded_calls: int = 0
    """Calls of the iterations the original had started but not committed that it never recorded."""

    def as_dict(self) -> dict:
        return {
            "original_run_id": self.original_run_id, "replay_run_id": self.replay_run_id, "status": self.status,
            "diverged_at": self.diverged_at, "record_ends": self.record_ends, "last_iteration": self.last_iteration,
            "unrecorded_calls": self.unrecorded_calls,
            "iterations": [dict(iteration=r.iteration, original_prompt=r.original_prompt,
                                replay_prompt=r.replay_prompt, original_score=r.original_score,
                                replay_score=r.replay_score, matches=r.matches) for r in self.rows],
        }


class StoredReplies(Mapping):
    """A run's replies by (iteration, prompt hash, candidate), each text read from the store when the replay asks
    for it: a run's replies together may be far larger than one (up to 16 MiB each: thirty iterations of a 12.9
    million-character reply held 1.7 GB when they were read at once), and the loop needs one at a time."""

    def __init__(self, store: Store, hashes: dict[tuple[int, str, int], str]):
        self.store = store
        self.hashes = hashes

    def __getitem__(self, key: tuple[int, str, int]) -> str:
        with self.store.read() as con:
            text = blob_text(con, self.hashes[key])
        if text is None:
            raise KeyError(key)
        return text

    def __contains__(self, key: object) -> bool:
        return key in self.hashes

    def __iter__(self) -> Iterator[tuple[int, str, int]]:
        return iter(self.hashes)

    def __len__(self) -> int:
        return len(self.hashes)


def replay(store: Store, run_id: str, log=lambda s: None, on_iteration=None) -> ReplayReport:
    """Replay ``run_id`` (the module docstring); ``on_iteration(IterationResult)`` after each iteration replayed."""
    with store.read() as con:
        run = get_run(con, run_id)
        if run is None:
            raise ValueError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
        if run["kind"] not in ("optimize", "replay"):
            raise ValueError(f"run {run_id} is {kind_phrase(run['kind'])}; only optimize runs can be "
                             "replayed")
        starter = inspect_policy(blob_text(con, run["starter_policy_hash"]), "policy.py")
        replies, errors = StoredReplies(store, replay_replies(con, run_id)), replay_errors(con, run_id)
        bases = pool_bases(con, run_id)
    recorded = read_recorded(run["config"], run_id)
    config = OptimizeConfig.from_record(recorded, run_id)
    client = ReplayClient(replies, model=run["model"] or "replay", errors=errors)
    if config.models:  # an ensemble: each call is answered as the model the rule chooses again
        client = EnsembleClient([ReplayClient(replies, model=e["model"], errors=errors) for e in config.models])
        client.label = run["model"]  # its first model counts the prompts' tokens, as in the original
    with new_run(store, client) as made:
        replay_id = made.start(config, client.label, kind="replay",
                               extra={"replay_of": run_id, "rng_key": recorded.get("rng_key")}, starter=starter)
        state = load_state(store, replay_id)
        state.pool_bases = bases  # the proposal pool starts each candidate from the iterations its original saw
        state.config.audit_episodes = 0  # a replay checks that the loop reproduces; its audit is `codearcade audit`
        result = run_loop(store, state, client, log, on_iteration)

    with store.read() as con:
        original, again = iteration_prompts(con, run_id), iteration_prompts(con, replay_id)
        asked, missed = first_call_errors(con, run_id), first_call_errors(con, replay_id)
        ended = last_iteration(con, run_id)
    last = ended["iteration"] if ended is not None else None
    report = ReplayReport(run_id, replay_id, result.status, last_iteration=last)
    for it in sorted(set(original) | set(again)):
        o_hash, o_score = original.get(it, (None, None))
        r_hash, r_score = again.get(it, (None, None))
        row = ReplayRow(it, o_hash, r_hash, o_score, r_score)
        report.rows.append(row)
        # a run killed before it committed iteration 0 has no record to compare with at all
        past_the_record = run["status"] != "finished" and (last is None or it > last)
        if report.diverged_at is None and not row.matches and not past_the_record:
            report.diverged_at = it
    if run["status"] != "finished" and (last is None or last < config.iterations):  # its record ends where it
        # stopped (a run that failed after its last iteration, every update's call failed, has a whole record)
        report.unrecorded_calls = _unrecorded(config, asked, last)
        s = "s" if report.unrecorded_calls != 1 else ""
        stopped = f"after iteration {last}" if last is not None else "during iteration 0"
        report.record_ends = (f"the run stopped {stopped} ({_status(run['status'])}); "
                              f"{report.unrecorded_calls} call{s} {'were' if s else 'was'} never recorded")
    if result.error and "ReplayMiss" in result.error:
        # a miss on a candidate the original never asked (or never got a reply for) is where its record ends; one
        # the original asked with another prompt is a divergence
        misses = [key for key, error in missed.items() if error == "ReplayMiss"]
        unasked = [key for key in misses if asked.get(key, "none") is not None]
        if report.record_ends and report.diverged_at is None and misses and len(unasked) == len(misses):
            report.status = "incomplete"
            with store.write() as con:
                finish_run(con, replay_id, _status(run["status"]),
                           f"replayed as far as the original's record goes: {report.record_ends}")
        else:
            report.status = "diverged"
            if report.diverged_at is None:
                report.diverged_at = min(it for it, _ in misses) if misses else None
            with store.write() as con:
                finish_run(con, replay_id, "diverged", result.error)
    return report


def _status(status: str) -> str:
    """How the original ended, for its replay: a run still marked running has no process left (it was killed)."""
    return "interrupted" if status == "running" else status


def _unrecorded(config: OptimizeConfig, asked: dict[tuple[int, int], str | None], last: int | None) -> int:
    """The first-turn calls without a recorded reply of the iterations after ``last`` up to where a replay stops:
    the last iteration with a recorded reply if one of its calls has none, else the one after it (its calls were
    never made: a run killed after an iteration's reply, before its commit, stops the replay at the next), at
    least the iteration after ``last`` and at most the run's last."""
    after = (last if last is not None else 0) + 1  # iteration 0 calls no model
    width = make_strategy(config).max_proposals

    def unreplied(iteration: int) -> int:
        return sum(1 for j in range(width) if asked.get((iteration, j), "none") is not None)

    started = max([it for (it, _), error in asked.items() if error is None], default=after - 1)
    end = min(started if started >= after and unreplied(started) else started + 1, config.iterations)
    return sum(unreplied(it) for it in range(after, end + 1))
