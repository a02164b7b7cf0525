"""``codearcade replay RUN``: re-run an optimization with the replies stored in the store, not the model.

The replay starts a new run (kind ``replay``) from the original's starting policy and settings, and answers
each LLM call with the stored reply whose prompt hash matches. Since prompts are deterministic, a faithful
re-run sends exactly the original prompts; the first prompt the original run never sent is where the two
diverge (a changed environment, policy code, prompt builder or dependency), and the replay stops there. The
report lists, per iteration, both prompt hashes and both scores.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from pipeline.llm.client import EnsembleClient, ReplayClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import load_state, run_loop, start_run
from store import Store
from store.readers import blob_text, get_run, iteration_prompts, pool_bases, replay_replies
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

    def as_dict(self) -> dict:
        return {
            "original_run_id": self.original_run_id, "replay_run_id": self.replay_run_id, "status": self.status,
            "diverged_at": self.diverged_at,
            "iterations": [dict(iteration=r.iteration, original_prompt=r.original_prompt,
                                replay_prompt=r.replay_prompt, original_score=r.original_score,
                                replay_score=r.replay_score, matches=r.matches) for r in self.rows],
        }


def replay(store: Store, run_id: str, log=lambda s: None) -> ReplayReport:
    with store.read() as con:
        run = get_run(con, run_id)
        if run is None:
            raise ValueError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
        if run["kind"] not in ("optimize", "replay"):
            raise ValueError(f"run {run_id} is an {run['kind']} run; only optimize runs can be replayed")
        starter = inspect_policy(blob_text(con, run["starter_policy_hash"]), "policy.py")
        replies = replay_replies(con, run_id)
        bases = pool_bases(con, run_id)
    recorded = json.loads(run["config"])
    config = OptimizeConfig.from_record(recorded)
    client = ReplayClient(replies, model=run["model"] or "replay")
    if config.models:  # an ensemble: each call is answered as the model the rule chooses again
        client = EnsembleClient([ReplayClient(replies, model=e["model"]) for e in config.models])
        client.label = run["model"]  # its first model counts the prompts' tokens, as in the original
    new_run = start_run(config, store, client.label, kind="replay", extra={"replay_of": run_id, "rng_key": recorded.get("rng_key")}, starter=starter)
    state = load_state(store, new_run)
    state.pool_bases = bases  # the proposal pool starts each candidate from the iterations its original saw
    state.config.audit_episodes = 0  # a replay checks that the loop reproduces; its audit is `codearcade audit`
    result = run_loop(store, state, client, log)

    with store.read() as con:
        original, again = iteration_prompts(con, run_id), iteration_prompts(con, new_run)
    report = ReplayReport(run_id, new_run, result.status)
    for it in sorted(set(original) | set(again)):
        o_hash, o_score = original.get(it, (None, None))
        r_hash, r_score = again.get(it, (None, None))
        row = ReplayRow(it, o_hash, r_hash, o_score, r_score)
        report.rows.append(row)
        if report.diverged_at is None and not row.matches:
            report.diverged_at = it
    if result.error and "ReplayMiss" in result.error:
        report.status = "diverged"
        with store.write() as con:
            finish_run(con, new_run, "diverged", result.error)
    return report
