"""The protocol of ``codearcade serve``: one run, an episode budget, visible training instances, sealed pools.

A served run (``runs.kind = 'serve'``) is driven by an agent instead of the prompt loop. What it may do, whatever
the transport (``http.py``, ``tools.py``), is a method of :class:`ServeRun`:

- ``task``: the game's facts, the policy interface (the starting policy's text and its trainable methods), the
  budget and the rules;
- ``submit``: a policy file's text and the training instances to play it on (ids ``0..instances-1``). The text is
  checked as a policy file given to ``eval`` is (in a confined worker first: ``pipeline/play/validate.py``); a
  request refused there, or malformed, costs nothing. Otherwise it becomes a policy version of the run (iteration
  = the submission's number, its parent the submission it names, else the newest one: lineage is data, so
  ``blame`` names the submission that wrote each line) and its episodes are played by the game host with a
  confined policy process (``pipeline/play/episodes.py``, as ``eval`` and ``optimize`` play), traced, stored
  like any run's, and scored by the one rule (``store/scores.py``: a forfeit has no score). Every episode asked
  for costs one, whatever ends it;
- ``feedback``: a submission's summary, forfeits and errors, the feedback text the prompt loop would give (with,
  under ``#Printed``, what the policy printed to its stdout in each training episode: its first 4 KiB, all of
  them within :data:`PRINTED_SHOWN_BYTES`), and a
  bounded slice of one episode's steps and node calls chosen as the prompt chooses them
  (``pipeline.optimizer.prompt.trace_slice``);
- ``budget``; ``sql``: read-only SQL over the visible part of the run (``store/serve.py``);
- ``finalize`` (the budget spent, or ``codearcade serve --finalize RUN``): every accepted submission plays the
  **validation** pool, and the best by validation, beside the starter, plays the **held-out** pool
  (``pipeline/serve/finalize.py``).

**Instances and pools.** A training instance is a game seed drawn from the OS's entropy when the run is made,
below the audit's range (``games.base.AUDIT_SEED_BASE``), kept in the run's config and its episodes, and never
in a response: the agent names instances by id. The validation and held-out pools are drawn at finalize, like
the sealed audit (``games.base.draw_audit_seeds``), in one draw so they are disjoint, from the
audit's range so they never meet a training instance; no response carries them or their scores (a person reads
those in ``runs``, ``report`` and ``audit``). Every game is played under the standard protocol (sticky actions
0.25, up to 30 no-op starts): under the paper's deterministic one every seed is the same game, and instances
would be one.

**Where the results are.** Each submission is an ``iterations`` row and a ``candidates`` row (its training
episodes as the evaluation episodes, its score their score) and a ``feedback`` row; iteration 0 is the starter,
unplayed. Finalize writes ``audits`` rows (``finalize.py``), so ``runs`` and ``report`` show the held-out score
where they show an audit's.

**The budget** is counted in memory under a lock (a submission reserves its episodes before it plays, and gives
them back only if the server fails to play them), and read back from the store when a run is opened again: a
killed server's run resumes with what its committed submissions spent.
"""

from __future__ import annotations

import os
import secrets
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import duckdb

from games import UnknownGameError, get_game
from games.base import AUDIT_SEED_BASE, STANDARD_NOOP_MAX, STANDARD_STICKY, recorded_observation
from pipeline.boundary.policy import MAX_PRINTED_BYTES, PRINTED_TEXT_BYTES
from pipeline.boundary.untrusted import utf8_prefix
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.context import ROLLOUT_NODE_BYTES, VALUE_CHARS
from pipeline.optimizer.feedback import FeedbackBands, compose_feedback
from pipeline.optimizer.loop import start_run
from pipeline.optimizer.prompt import trace_slice  # the prompt's own choice of steps: feedback shows what it would
from pipeline.play.episodes import run_episodes
from pipeline.play.runinfo import episode_id
from pipeline.play.spec import EpisodeSpec
from pipeline.play.validate import checked_inspect
from pipeline.play.verify import checked_outcome
from pipeline.play.versions import policy_version_row
from pipeline.serve.config import ServeConfig, served_settings
from pipeline.serve.finalize import finalize_run
from store import Store, StoreError
from store.db import utcnow
from store.recorded import read_recorded
from store.readers import episode_steps, get_run, policy_text, step_nodes
from store.scores import score_data, score_episodes
from store.serve import (is_finalized, served_submissions, submission_episodes, submission_feedback,
                         submission_version, visible_query)
from store.views import QueryError
from store.writer import (EpisodeWriter, delete_episodes, insert_candidate, insert_feedback, insert_iteration,
                          insert_policy_version)
from tracing.policy_file import MAX_POLICY_CHARS, PolicyLoadError, python_newlines, read_policy_file
from viewers.safe_text import print_failure, terminal_text

KIND = "serve"
TRAIN_SEED_LOW = 100_000
"""Training seeds are drawn from ``TRAIN_SEED_LOW`` to ``AUDIT_SEED_BASE``: six digits, below every sealed seed."""
MAX_FEEDBACK_STEPS = 200
MAX_SQL_ROWS = 500
SQL_AT_ONCE = 2
"""The agent's queries run at once, each in a process of its own capped in memory (``store/agent_sql.py``): 16 at
once held 6.3 GB between them. One more waits for a turn, up to :data:`SQL_WAIT_S`, and is refused past it."""
SQL_WAIT_S = 30.0
MAX_SQL_BYTES = 1_000_000
"""The most JSON an answer of the agent's SQL holds (its rows past that are left out, and it says so)."""
PRINTED_SHOWN_BYTES = 2 * PRINTED_TEXT_BYTES
"""UTF-8 bytes of what a submission's policy printed that its feedback shows, its episodes together: two episodes'
whole (each keeps ``policy.MAX_PRINTED_BYTES`` and a line counting the rest), more share it."""
PRODUCED_BY = "agent"
"""``policy_versions.produced_by`` of a submission."""


class RequestError(ValueError):
    """A request refused before anything plays: it costs nothing, and the message says why."""


def failed_request(exc: Exception) -> str:
    """Say on the server's stderr why a request failed (``exc``, raised by the server, not refused), and return
    what its agent is told. A store that could not be written (its disk full, a lock, damage: ``StoreError``, whose
    message says what to do) is one line naming the store, as every command says it: it printed a traceback of 20
    lines on the person's terminal, and the agent read only "failed (StoreError)". The agent is not told the store's
    path (it may not read the store); anything else is the server's fault, printed with its traceback."""
    if isinstance(exc, StoreError):
        sys.stderr.write(terminal_text(f"codearcade serve: error: {exc}") + "\n")
        sys.stderr.flush()
        return ("the server could not store this request's results (its store: a full disk, a lock or damage; the "
                "person who runs the server has been told): nothing of it was kept; `budget` says what is spent")
    print_failure()  # the server's own log (stderr): the person sees what went wrong
    return f"the server failed on this request ({type(exc).__name__}); `budget` says what is spent"


def create_run(store: Store, config: ServeConfig, name: str | None = None) -> str:
    """Make a served run (its training instances drawn now) with its starter as iteration 0; return its id."""
    from store.writer import set_run_name

    opt = OptimizeConfig(game=config.game, policy=config.policy, iterations=0, eval_episodes=1,
                         audit_episodes=config.heldout_episodes, workers=config.workers,
                         rollout_steps=config.max_steps, eval_max_steps=config.max_steps,
                         call_time_limit_s=config.call_time_limit_s, episode_time_limit_s=config.episode_time_limit_s,
                         # the key of the policies' random streams is secret here, not the run id: the agent knows
                         # the run id, and a policy's draws (keyed by it and the game's seed) would give the seed away
                         rng_key=secrets.token_hex(16))
    seeds = secrets.SystemRandom().sample(range(TRAIN_SEED_LOW, AUDIT_SEED_BASE), config.instances)
    serve = {**asdict(config), "train_seeds": seeds, "sticky": STANDARD_STICKY, "noop_max": STANDARD_NOOP_MAX}
    run_id = start_run(opt, store, "agent", kind=KIND, extra={"serve": serve, "strategy": KIND})
    with store.write() as con:
        if name is not None:
            set_run_name(con, run_id, name)
        starter = get_run(con, run_id)["starter_version_id"]
        now = utcnow()
        insert_candidate(con, dict(run_id=run_id, iteration=0, candidate=0, strategy=KIND, policy_version_id=starter,
                                   proposed_version_id=starter, update_status="initial", evaluation="unplayed",
                                   decision="best", feedback=None))
        insert_feedback(con, dict(run_id=run_id, iteration=0, mode="staged", stage="unplayed", score=None,
                                  text="The starting policy, not played: submit it to see how it does."))
        insert_iteration(con, dict(run_id=run_id, iteration=0, candidate=0, policy_version_id=starter,
                                   update_status="initial", rolled_back=False, best_version_id=starter,
                                   best_iteration=0, started_at=now, finished_at=now))
    return run_id


class ServeRun:
    """A served run, open for requests (see the module docstring). Thread-safe: the budget is reserved under a
    lock, one submission plays at a time, and reads (task, feedback, sql) answer while one plays (the store serves
    a process's threads one at a time)."""

    def __init__(self, store: Store, run_id: str, on_episode: Callable[[dict[str, Any]], None] | None = None,
                 workspace: str | os.PathLike | None = None, finalize_when_spent: bool = True,
                 rerun: str | None = None, on_finalized: Callable[[], None] | None = None):
        with store.read() as con:
            run = get_run(con, run_id)
            if run is None:
                raise ValueError(f"no run {run_id} in {store.path}; `codearcade runs` lists the runs")
            if run["kind"] != KIND:
                raise ValueError(f"run {run_id} is a{'n' * (run['kind'][0] in 'aeiou')} {run['kind']} run, not a "
                                 "served one")
            subs = served_submissions(con, run_id)
            finalized = is_finalized(con, run_id, run["status"])
        self.store, self.run_id = store, run_id
        # read once, before the run is marked or a submission plays: a store is anyone's file, and settings or
        # bands it cannot read are one line naming the run and the setting
        record = read_recorded(run["config"], run_id)
        self.serve = served_settings(record, run_id)
        self.bands = FeedbackBands.from_record(record.get("feedback_bands"), run_id)
        self.game = get_game(run["game"])
        self.record = {**record, "serve": self.serve, "game": self.game.name}  # as checked: what finalize reads
        self.budget_total = self.serve["budget"]
        self.on_episode = on_episode
        self.workspace = Path(workspace).resolve() if workspace is not None else None
        self.finalize_when_spent = finalize_when_spent
        self.rerun = rerun
        self.on_finalized = on_finalized
        """Live Rerun recording of each training episode (``EpisodeSpec.rerun``: a directory or a gRPC url)."""
        """Finalize the run as the submission that spends the last of the budget ends (its answer then says so)."""
        self._spent = sum(len(s["eval_episode_ids"] or ()) for s in subs)
        self._reserved = 0
        self._next = (subs[-1]["iteration"] + 1) if subs else 1
        self._latest = subs[-1]["iteration"] if subs else 0
        self._committed = {0, *(x["iteration"] for x in subs)}
        self._best: tuple[float, int] | None = max(((s["score"], -s["iteration"]) for s in subs
                                                    if s["score"] is not None), default=None)
        self.finalized = finalized
        self._lock = threading.Lock()
        self._work = threading.Lock()
        self._parsing = threading.Lock()
        self._queries = threading.BoundedSemaphore(SQL_AT_ONCE)
        self.stopping = threading.Event()
        """Set when the server stops (:meth:`stop`): a submission playing then is neither stored nor charged."""

    # ------------------------------------------------------------------------------------------- reading

    def budget(self) -> dict[str, Any]:
        with self._lock:
            return {"budget": self.budget_total, "spent": self._spent, "in_play": self._reserved,
                    "remaining": self.budget_total - self._spent - self._reserved, "finalized": self.finalized}

    def task(self) -> dict[str, Any]:
        """What an agent needs to start: the game, the policy interface, the budget and the rules."""
        with self.store.read() as con:  # the store takes one thread at a time; reads need not wait for a play
            starter = policy_text(con, self.run_id, get_run(con, self.run_id)["starter_version_id"])
        from tracing.policy_file import inspect_policy

        info = inspect_policy(starter, "policy.py")
        s = self.serve
        return {
            "run": self.run_id, "game": self.game.name, "actions": list(self.game.actions),
            "lives": self.game.lives, "instruction": self.record.get("instruction") or "",
            "starter_policy": starter, "trainable_methods": [m.name for m in info.trainable],
            "instances": s["instances"], "per_submission": s["per_submission"], "max_steps": s["max_steps"],
            "call_time_limit_s": s["call_time_limit_s"], "budget": self.budget(),
            "rules": [
                "Submit a whole policy file (class Policy, as the starter) with the training instances to play it on "
                f"(ids 0..{s['instances'] - 1}, at most {s['per_submission']} per submission, each once).",
                "Every episode a submission asks for costs one episode of the budget, whatever ends it; a request "
                "refused before anything plays (malformed, code that does not parse) costs nothing.",
                "Games are played under the standard protocol: sticky actions 0.25 and up to 30 no-op starts.",
                "An episode the policy ends itself (an exception, a time or memory limit) is a forfeit: the "
                "submission then has no score.",
                "What the policy prints to stdout comes back in the submission's feedback (under #Printed): the "
                f"first {MAX_PRINTED_BYTES // 1024} KiB of each episode.",
                "When the budget is spent (or the person finalizes the run), every accepted submission is scored on "
                "a hidden validation pool, and the best of them on a hidden held-out pool: neither is ever shown.",
            ],
        }

    def feedback(self, submission: int, instance: int | None = None, steps: int = 40) -> dict[str, Any]:
        """A submission's summary, feedback text and a bounded slice of one of its episodes (``instance``: which;
        default the first), ``steps`` steps chosen as the prompt chooses them."""
        if not isinstance(submission, int) or isinstance(submission, bool):
            raise RequestError("submission: give the submission's number (an integer)")
        if not isinstance(steps, int) or isinstance(steps, bool) or not 0 <= steps <= MAX_FEEDBACK_STEPS:
            raise RequestError(f"steps: a whole number from 0 to {MAX_FEEDBACK_STEPS}")
        with self.store.read() as con:  # the store takes one thread at a time; reads need not wait for a play
            sub = next((s for s in served_submissions(con, self.run_id) if s["iteration"] == submission), None)
            if sub is None:
                newest = f"the newest is {self._latest}" if self._latest else "none is made yet"
                raise RequestError(f"no submission {submission} (submissions are numbered from 1; {newest})")
            episodes = submission_episodes(con, sub["eval_episode_ids"])
            text = submission_feedback(con, self.run_id, submission)
            chosen = next((e for e in episodes if instance is None or e["instance"] == instance), None)
            if chosen is None:
                raise RequestError(f"submission {submission} did not play instance {instance}; it played "
                                   f"{[e['instance'] for e in episodes]}")
            game = self.game.observing(recorded_observation(self.record))  # read back as the run played it
            rows = episode_steps(con, chosen["episode_id"], list_widths=game.list_widths, derive=game.derive)
            # read as the prompt reads a rollout: each value's head, the rollout's rows within a byte bound
            nodes = step_nodes(con, chosen["episode_id"], value_chars=VALUE_CHARS, max_bytes=ROLLOUT_NODE_BYTES)
        events, shown = trace_slice(rows, nodes, self.game.lives > 0, steps)
        return {**_summary(sub, episodes), "feedback": text,
                "trace": {"instance": chosen["instance"], "length": chosen["length"],
                          "events": [f"{what} at step {step}" for step, what in events][:100],
                          "steps": shown}}

    def sql(self, query: str) -> dict[str, Any]:
        """Read-only SQL over the visible part of the run (``store/serve.py``)."""
        if not isinstance(query, str) or not query.strip() or len(query) > 20_000:
            raise RequestError("sql: give one query of at most 20,000 characters")
        if not self._queries.acquire(timeout=SQL_WAIT_S):
            raise RequestError(f"sql: {SQL_AT_ONCE} queries were running for {SQL_WAIT_S:g} s; ask again when one "
                               "has answered")
        try:
            return visible_query(self.store, self.run_id, query, MAX_SQL_ROWS, MAX_SQL_BYTES)
        except (duckdb.Error, QueryError) as exc:
            raise RequestError(f"sql: {str(exc).splitlines()[0][:500]}") from None
        finally:
            self._queries.release()

    # ------------------------------------------------------------------------------------------- submitting

    def stop(self, wait_s: float = 60.0) -> None:
        """Take no more submissions, and wait up to ``wait_s`` for one that is playing to end. Its episodes ended
        with the server (a Ctrl-C reaches its workers too), not with its policy: it is not stored, and costs
        nothing (it was saved as forfeited games and charged to the budget)."""
        self.stopping.set()
        if self._work.acquire(timeout=wait_s):
            self._work.release()

    def _refuse_if_closed(self, episodes: int) -> None:
        """RequestError if the run takes no more submissions, or not one of ``episodes`` episodes (under
        ``_lock``)."""
        if self.stopping.is_set():
            raise RequestError("the server is stopping: nothing was played, and it cost nothing")
        if self.finalized:
            raise RequestError("the run is finalized: it takes no more submissions")
        left = self.budget_total - self._spent - self._reserved
        if episodes > left:
            raise RequestError(f"budget: {episodes} episodes asked, {left} left")

    def submit(self, instances: list[int], policy: str | None = None, parent: int | None = None,
               path: str | None = None) -> dict[str, Any]:
        """Play ``policy`` (the file's text, or ``path``: a file of the workspace) on ``instances`` (see the module
        docstring); the submission's summary and budget."""
        s = self.serve
        if (policy is None) == (path is None):
            raise RequestError("give the policy's text (policy) or a file of the workspace (path), one of them")
        if path is not None:
            policy = self._workspace_file(path)
        if not isinstance(policy, str) or not policy.strip():
            raise RequestError("policy: give the whole policy file's text")
        policy = python_newlines(policy)  # a file written on Windows: its methods are parsed on their own
        if len(policy) > MAX_POLICY_CHARS:
            raise RequestError(f"policy: {len(policy):,} characters; at most {MAX_POLICY_CHARS:,}")
        if not isinstance(instances, list) or not instances or \
                any(not isinstance(i, int) or isinstance(i, bool) for i in instances):
            raise RequestError("instances: give a list of training instance ids (integers)")
        if len(set(instances)) != len(instances):
            raise RequestError("instances: each instance once (an instance played twice is the same game twice)")
        outside = [i for i in instances if not 0 <= i < s["instances"]]
        if outside:
            raise RequestError(f"instances: {outside[0]} is not an instance; they are 0 to {s['instances'] - 1}")
        if len(instances) > s["per_submission"]:
            raise RequestError(f"instances: {len(instances)} asked, at most {s['per_submission']} per submission")
        if parent is not None and (not isinstance(parent, int) or isinstance(parent, bool) or parent < 0):
            raise RequestError("parent: a submission's number (0: the starting policy)")
        with self._lock:  # refused before its text is parsed, which costs this process ~1 KB a character
            self._refuse_if_closed(len(instances))
        try:
            with self._parsing:  # one at a time: concurrent submissions' parse trees would add up (32 of 200,000
                # characters held 2 GB)
                info = checked_inspect(policy, "policy.py")
        except (PolicyLoadError, SyntaxError, ValueError) as exc:
            raise RequestError(f"policy: {str(exc)[:2000]}") from None
        try:  # a GAME no game has: refused like any other mistake (it ended in a traceback quoting its text)
            game = get_game(info.game) if info.game is not None else self.game
        except UnknownGameError as exc:
            raise RequestError(f"policy: {str(exc)[:2000]}") from None
        if game.name != self.game.name:
            raise RequestError(f"policy: its GAME is {info.game}, and this run plays {self.game.name}")
        with self._lock:
            self._refuse_if_closed(len(instances))
            if parent is not None and parent not in self._committed:
                raise RequestError(f"parent: submission {parent} has no result (yet)")
            self._reserved += len(instances)
            parent = self._latest if parent is None else parent
        try:
            with self._work:  # one submission plays at a time: it takes the next number when it starts, and the
                # numbers stay dense (an iteration per number) even when a submission fails while it plays
                result = self._play(self._next, info, policy, instances, parent)
                self._next += 1
        except BaseException:
            with self._lock:
                self._reserved -= len(instances)
            raise
        with self._lock:
            self._reserved -= len(instances)
            self._spent += len(instances)
            self._latest = max(self._latest, result["submission"])
            self._committed.add(result["submission"])
            spent = self._spent == self.budget_total and not self._reserved and not self.finalized
        if spent and self.finalize_when_spent:
            try:
                self.finalize()
            except RequestError:  # another request finalized it meanwhile
                pass
            except Exception as exc:  # noqa: BLE001 - the submission stands; `codearcade serve --finalize` ends the run
                failed_request(exc)
        return {**result, "budget": self.budget()}

    def _workspace_file(self, path: Any) -> str:
        """The text of a policy file inside the workspace (the server's ``--workspace``), read within bounds."""
        if self.workspace is None:
            raise RequestError("path: this server has no workspace (give the policy's text)")
        if not isinstance(path, str) or not path or "\0" in path:
            raise RequestError("path: a file name relative to the workspace")
        try:
            target = (self.workspace / path).resolve()
        except (OSError, ValueError, UnicodeError):  # a lone surrogate cannot name a file (nor can a name too long)
            raise RequestError("path: a file name relative to the workspace") from None
        if not target.is_relative_to(self.workspace) or not target.is_file():
            raise RequestError(f"path: no file {path!r} in the workspace")
        try:  # read as every policy file is: within MAX_POLICY_CHARS, UTF-8, line ends as Python reads them
            return read_policy_file(target, kind="workspace file")
        except PolicyLoadError as exc:  # named as the agent named it, not by the server's own path
            raise RequestError(f"path: {str(exc).replace(str(target), path)}") from None

    def _play(self, iteration: int, info, text: str, instances: list[int], parent: int) -> dict[str, Any]:
        s, started, t0 = self.serve, utcnow(), time.monotonic()
        with self.store.read() as con:
            parent_version = submission_version(con, self.run_id, parent)
        specs = [EpisodeSpec(episode_id=episode_id(self.run_id, iteration, "train", i), run_id=self.run_id,
                             game=self.game.name, policy_text=text, policy_version_id=info.version_id,
                             iteration=iteration, kind="train", index=i, seed=s["train_seeds"][i],
                             max_steps=s["max_steps"], sticky=s["sticky"], noop_max=s["noop_max"], trace=True,
                             call_time_limit_s=s["call_time_limit_s"],
                             episode_time_limit_s=s["episode_time_limit_s"],
                             observation=self.record["observation"], rng_key=self.record.get("rng_key"),
                             rerun=self.rerun, keep_printed=True)
                 for i in instances]
        episodes: list[dict[str, Any]] = [{}] * len(specs)
        printed: list[str | None] = [None] * len(specs)
        with EpisodeWriter(self.store, replace=True) as writer:
            for i, outcome in run_episodes(specs, workers=max(1, min(s["workers"], len(specs)))):
                if self.stopping.is_set():  # no more games start (closing the episodes ends those playing): the
                    break  # submission is given back below, and the server stops at once, not a minute later
                outcome = checked_outcome(specs[i], outcome)
                writer.add(outcome.episode, outcome.steps, outcome.nodes)
                episodes[i], printed[i] = outcome.episode, outcome.printed
                if self.on_episode is not None:
                    self.on_episode(outcome.episode)
        if self.stopping.is_set():  # the server stopped under it: its games ended with the server, not the policy
            try:  # the games it finished before the stop were written as they ended: they go with it
                with self.store.write() as con:
                    delete_episodes(con, [spec.episode_id for spec in specs])
            except duckdb.Error:  # a store interrupted by the stop itself: they stay, named by no submission
                pass
            raise RequestError("the server stopped while this submission played: it is not stored and cost "
                               "nothing; submit it again when the run is served again")
        score = score_episodes(episodes)
        ranked = score.ranked
        if ranked is not None and (self._best is None or (ranked, -iteration) > self._best):
            self._best = (ranked, -iteration)
        best_score, best_iteration = (self._best[0], -self._best[1]) if self._best else (None, 0)
        train = episodes[0]
        stage, _, feedback = compose_feedback(
            "staged", self.bands, ranked, train["return"], train["length"], [],
            score.forfeit, score.partial if score.forfeit else None)
        feedback += printed_section(list(zip(instances, printed)))
        ids = [e["episode_id"] for e in episodes]
        row = dict(run_id=self.run_id, iteration=iteration, candidate=0, strategy=KIND, parent_iteration=parent,
                   parent_candidate=0, parent_version_id=parent_version, proposed_version_id=info.version_id,
                   policy_version_id=info.version_id, update_status="accepted", evaluation="played",
                   train_episode_id=ids[0], eval_episode_ids=ids, train_return=train["return"], score=ranked,
                   standard_score=ranked, forfeit=score.forfeit,
                   forfeit_score=score.partial if score.forfeit else None,
                   score_low=score.low if ranked is not None else None,
                   score_high=score.high if ranked is not None else None,
                   decision="best" if best_iteration == iteration else "kept", feedback=feedback)
        with self.store.write() as con:
            best_version = submission_version(con, self.run_id, best_iteration)
            insert_policy_version(con, policy_version_row(info, self.run_id, iteration, PRODUCED_BY, "accepted",
                                                          parent_id=parent_version))
            insert_candidate(con, row)
            insert_feedback(con, dict(run_id=self.run_id, iteration=iteration, mode="staged", stage=stage,
                                      score=ranked if ranked is not None else score.partial, text=feedback))
            insert_iteration(con, dict(
                run_id=self.run_id, iteration=iteration, candidate=0, policy_version_id=info.version_id,
                base_version_id=parent_version, update_status="accepted", rolled_back=False,
                train_episode_id=ids[0], eval_episode_ids=ids, train_return=train["return"], score=ranked,
                best_score=best_score, best_version_id=best_version or info.version_id,
                best_iteration=best_iteration, started_at=started, finished_at=utcnow(), llm_s=0.0,
                train_s=time.monotonic() - t0, eval_s=time.monotonic() - t0, wall_s=time.monotonic() - t0))
        return {"submission": iteration, "parent": parent, "version": info.version_id[:12],
                **_summary(row, submission_view(episodes)), "feedback": feedback}

    # ------------------------------------------------------------------------------------------- finalize

    @property
    def submissions(self) -> int:
        """How many submissions the run has committed (the starting policy, iteration 0, is none)."""
        with self._lock:
            return len(self._committed) - 1

    def finalize(self, progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
        """Play every accepted submission on the validation pool and the best by validation (with the starter)
        on the held-out pool, store both (``audits``) and finish the run. What it returns names no seed and
        no score of either pool: the agent learns only that the run is finalized."""
        with self._lock:
            if self._reserved:
                raise RequestError(f"{self._reserved} episodes are still playing; finalize when they end")
            if self.finalized:
                raise RequestError("the run is finalized already")
            if len(self._committed) == 1:  # the starter alone: there is no submission to score
                raise RequestError("no submission yet: there is nothing to finalize")
            self.finalized = True
        with self._work:
            try:
                rows = finalize_run(self.store, self.run_id, self.record, progress, self.stopping)
            except BaseException:
                with self._lock:  # before the work is let go: a stopping server reads it next
                    self.finalized = False
                raise
        if self.on_finalized is not None:
            self.on_finalized()
        return {"finalized": True, "submissions_validated": sum(r["protocol"] == "validation" for r in rows),
                "note": "the validation and held-out results are sealed: the person who runs the server reads them "
                        "with `codearcade runs`, `report` and `audit`"}


def printed_section(printed: list[tuple[int, str | None]]) -> str:
    """The feedback's section of what the policy printed to its stdout, per training instance (each episode's
    text as the host kept it: ``EpisodeSpec.keep_printed``), all of them within :data:`PRINTED_SHOWN_BYTES`
    UTF-8 bytes; empty when it printed nothing."""
    shown = [(instance, text) for instance, text in printed if text]
    if not shown:
        return ""
    share = PRINTED_SHOWN_BYTES // len(shown)
    parts = []
    for instance, text in shown:
        head = utf8_prefix(text, share)
        cut = f"\n… [cut: {len(text.encode('utf-8')) - len(head.encode('utf-8')):,} more bytes]" if head != text else ""
        parts.append(f"instance {instance}:\n{head}{cut}")
    return "\n\n#Printed (what your policy printed to stdout, per training instance)\n" + "\n\n".join(parts)


def submission_view(episodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Episode rows as an agent sees them: instance, return, length, lives lost, end, error (no seed)."""
    return [{"instance": e["episode_index"] if "episode_index" in e else e["instance"], "return": e["return"],
             "length": e["length"], "lives_lost": e["lives_lost"], "end_reason": e["end_reason"],
             "error": e.get("error")} for e in episodes]


def _summary(sub: dict[str, Any], episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """A submission as the agent reads it: its score, the score's interval as every interval is shown (``interval``:
    ``-20.7 [-21.0, -20.3] 95% t, n=3``, or the value and why there is none, ``store.scores.score_data``; None
    with a forfeit) with its bounds, the forfeit and its episodes."""
    scored = score_data(score_episodes(episodes))
    return {"submission": sub["iteration"], "score": sub["score"], "interval": scored["interval"],
            "low": scored["low"], "high": scored["high"], "forfeit": sub["forfeit"],
            "episodes": submission_view(episodes)}
