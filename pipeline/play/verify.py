"""What the parent stores of an episode, and the replay that re-checks a stored one.

Scores need no check when they are made: the game host (``pipeline/play/rollout.py``) computes every reward,
score, life and step in a process where no policy code runs, so the policy cannot change them by any means
(DESIGN.md, "the game host and the policy process"). What still comes from policy code is text and trace data:
the error a policy raised, and the node rows its process recorded. :func:`checked_outcome`, called on every
outcome as it arrives (``pipeline/play/evaluate.py``, ``pipeline/optimizer/assess.py``), before it is stored:

1. rebuilds the episode row: the fields the parent decided (ids, seed, game, caps, protocol) come from the
   :class:`~pipeline.play.spec.EpisodeSpec`, the measured ones are type-checked, unknown keys are dropped, and
   text (the error message; what the policy printed, when its spec kept it) is cleaned
   (``pipeline/boundary/untrusted.py``: capped, secrets redacted);
2. cleans the node table's text columns, and the object names in the step table, the same way;
3. marks the episode ``verified = true`` when a game host played it (``verified`` NULL with ``--workers 0``,
   where the policy runs in the parent's own process and nothing can be trusted).

:func:`replay_outcome` re-checks an episode already stored (``codearcade doctor --replay RUN``): it replays the
recorded actions (the ``steps`` table's ``action`` column, up to the step where the policy failed, whose action
is NULL) in a fresh environment of this process with the same game, seed, sticky probability, no-op and one-life
setting (episodes are deterministic given those and the actions, under both protocols: the sticky and no-op
draws come from the environment's RNG seeded by ``reset(seed=...)``), built from raw ALE without the object
extraction, and compares per step the reward, the cumulative score, the terminated/truncated flags and the
lives, then the return, the length and the lives lost; the first disagreement, or None. An episode that
``continues`` another (the authors' one-life protocol, ``one_life = "continue"``) is replayed after it, in its
environment, from where its replay ended (:meth:`Replay.after`). A Breakout game under sticky actions that does
not replay in today's environment is replayed again without ``games.wrappers.ServeAgain``: stored before it existed,
a game whose serve was swallowed went on without a ball. Runs stored before the
game host (when the policy process held the emulator and every episode was replayed as it arrived) keep their
``verified`` flags, and end reason ``tampered`` for an episode whose replay disagreed.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc

from games import get_game
from games.base import ONE_LIFE_CONTINUE, one_life_setting
from pipeline.boundary.policy import PRINTED_TEXT_BYTES
from pipeline.boundary.untrusted import MESSAGE_LIMIT, clean_nodes, clean_step_objects, clean_untrusted_text
from pipeline.play.config import EvalConfig
from pipeline.play.rollout import EpisodeOutcome
from pipeline.play.spec import EpisodeSpec
from pipeline.settings import recorded_settings
from tracing.capture import NODE_SCHEMA
from tracing.steps import STEP_SCHEMA, StepLog

END_REASONS = ("terminated", "truncated", "policy_error", "timeout", "crashed")
"""End reasons a worker may report; ``tampered`` is set only here."""
FAILURE_END_REASONS = ("policy_error", "timeout", "crashed")
TAMPERED = "tampered"

_replay_envs: dict[tuple[str, float, int, bool | str, bool], list[Any]] = {}


def _acquire_env(game: str, sticky: float, noop_max: int, one_life: bool | str = False, serve_again: bool = True):
    """A raw-ALE environment (no object extraction) for one replay, from a pool per setting in this process
    (replays of episodes that play at the same time each need their own) and never handed to policy code:
    ``make_env``'s wrappers minus ``ObjectObservation`` (and minus ``ServeAgain`` when not ``serve_again``)."""
    key = (get_game(game).name, float(sticky), int(noop_max), one_life_setting(one_life), serve_again)
    free = _replay_envs.setdefault(key, [])
    from games.envs import make_env  # here: a command that replays nothing never imports the emulator stack

    return key, (free.pop() if free else make_env(key[0], sticky=key[1], noop_max=key[2], one_life=key[3],
                                                  objects=False, serve_again=serve_again))


class Replay:
    """Replaying an episode's actions from its reset, step by step: per step reward, flags and lives (before
    the step). Actions can be fed as they are played (:meth:`feed`, from a worker's progress reports), so that
    by the time the episode ends only its last few hundred steps are left to replay. ``after``: the replay of
    the episode this one continues, whose environment it takes over and resets without a seed (the game goes
    on: ``games.wrappers.EpisodicLife``)."""

    def __init__(self, spec: EpisodeSpec, after: "Replay | None" = None, serve_again: bool = True):
        if after is None:
            self._key, self._env = _acquire_env(spec.game, spec.sticky, spec.noop_max, spec.one_life, serve_again)
            _, info = self._env.reset(seed=spec.seed)
        else:
            self._key, self._env = after._key, after._env
            after._env = None
            _, info = self._env.reset()
        self._has_lives = bool(get_game(spec.game).lives)
        self._lives = int(info.get("lives", 0))
        self.actions: list[int] = []
        self.rewards: list[float] = []
        self.terminated: list[bool] = []
        self.truncated: list[bool] = []
        self.lives: list[int] = []
        self.lives_lost = 0
        self.ended_early: int | None = None  # the step after which the game ended while actions went on

    def feed(self, actions: list[int]) -> None:
        """Play ``actions`` after those fed before (ignored once the game has ended with actions left over)."""
        for action in actions:
            if self.ended_early is not None:
                return
            if self.rewards and (self.terminated[-1] or self.truncated[-1]):
                self.ended_early = len(self.rewards) - 1
                return
            self.actions.append(action)
            self.lives.append(self._lives)
            _, reward, terminated, truncated, info = self._env.step(action)
            self.rewards.append(float(reward))
            self.terminated.append(bool(terminated))
            self.truncated.append(bool(truncated))
            new_lives = int(info.get("lives", self._lives))
            if self._has_lives:
                self.lives_lost += max(0, self._lives - new_lives)
            elif reward < 0:  # a point conceded counts as a life lost where the game has none (Pong)
                self.lives_lost += 1
            self._lives = new_lives

    def release(self) -> None:
        """Give the environment back to the pool (every replay resets it before use)."""
        if self._env is not None:
            _replay_envs[self._key].append(self._env)
            self._env = None

    @property
    def final_lives(self) -> int:
        return self._lives

    @property
    def length(self) -> int:
        return len(self.rewards)

    @property
    def score(self) -> float:
        return math.fsum(self.rewards)


def replay_actions(spec: EpisodeSpec, actions: list[int], replay: Replay | None = None,
                   serve_again: bool = True) -> Replay:
    """Replay ``actions`` from ``spec``'s reset in this process (no policy code): continuing ``replay`` when its
    actions so far are a prefix of ``actions`` (fed while the episode played), else from the start."""
    if replay is not None and replay.actions != actions[:len(replay.actions)]:
        replay.release()  # what was reported while playing is not what the episode recorded: start again
        replay = None
    if replay is None:
        replay = Replay(spec, serve_again=serve_again)
    replay.feed(actions[len(replay.actions):])
    replay.release()
    return replay


def _recorded_actions(spec: EpisodeSpec, steps: pa.Table) -> tuple[list[int] | None, str | None]:
    """The actions a stored episode recorded (up to its failing step), or (None, why they cannot be replayed)."""
    raw = steps.column("action").to_pylist()
    first_null = raw.index(None) if None in raw else len(raw)
    if steps.column("step").to_pylist() != list(range(steps.num_rows)):
        return None, "the step rows are not numbered 0, 1, 2, ..."
    if len(raw) > first_null + 1:
        return None, f"actions recorded after the failing step {first_null}"
    actions = raw[:first_null]
    if any(not 0 <= a < get_game(spec.game).n_actions for a in actions):
        return None, "an action outside the game's action set was recorded"
    return actions, None


def _float(value: Any, default: float | None = None) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return default
    value = float(value)
    return value if math.isfinite(value) else default


def _int(value: Any, default: int = 0) -> int:
    return value if isinstance(value, int) and not isinstance(value, bool) and -2**31 < value < 2**31 else default


def _episode_row(spec: EpisodeSpec, reported: dict[str, Any]) -> dict[str, Any]:
    """The row the parent stores: the spec's fields, the worker's measurements type-checked and cleaned."""
    end_reason = reported.get("end_reason")
    started_at = reported.get("started_at")
    row = dict(
        episode_id=spec.episode_id, run_id=spec.run_id, iteration=spec.iteration, kind=spec.kind,
        episode_index=spec.index, game=get_game(spec.game).name, seed=spec.seed,
        policy_version_id=spec.policy_version_id, max_steps=spec.max_steps, traced=spec.trace,
        sticky=spec.sticky, noop_max=spec.noop_max, continues=spec.continues,
        start_step=max(0, _int(reported.get("start_step"))),
        started_at=started_at if isinstance(started_at, datetime) else None,
        duration_s=_float(reported.get("duration_s"), 0.0), env_s=_float(reported.get("env_s")),
        policy_s=_float(reported.get("policy_s")),
        length=_int(reported.get("length")), lives_lost=_int(reported.get("lives_lost")),
        end_reason=end_reason if end_reason in END_REASONS else TAMPERED,
        error=clean_untrusted_text(reported.get("error"), MESSAGE_LIMIT),
        verified=True, verify_error=None,
    )
    row["return"] = _float(reported.get("return"), math.nan)
    return row


def _tables(outcome: EpisodeOutcome) -> tuple[pa.Table | None, pa.Table | None, str | None]:
    """The steps and nodes tables in their schemas, or (None, ..., why) for a steps table that is not one."""
    steps, nodes = getattr(outcome, "steps", None), getattr(outcome, "nodes", None)
    try:
        if not isinstance(steps, pa.Table):
            raise TypeError(f"a {type(steps).__name__}")
        steps = clean_step_objects(steps.select(STEP_SCHEMA.names).cast(STEP_SCHEMA))
    except Exception as exc:  # noqa: BLE001 - anything a worker sent
        return None, None, f"the step table is malformed ({clean_untrusted_text(exc, 200)})"
    try:
        if nodes is not None:
            nodes = clean_nodes(nodes.select(NODE_SCHEMA.names).cast(NODE_SCHEMA))
    except Exception:  # noqa: BLE001 - node capture is evidence, not a score: drop a malformed table
        nodes = None
    return steps, nodes, None


def _compare(row: dict[str, Any], steps: pa.Table, replay: Replay, actions_end: int) -> str | None:
    """The first disagreement between the recorded episode and the replay, or None."""
    if replay.ended_early is not None:
        return (f"the game ended at step {replay.ended_early} but {actions_end} actions were recorded")
    n = replay.length
    columns = {c: steps.column(c).to_pylist() for c in ("reward", "score", "terminated", "truncated", "lives")}
    total = 0.0
    for t in range(n):
        total += replay.rewards[t]
        if columns["reward"][t] != replay.rewards[t]:
            return f"step {t}: recorded reward {columns['reward'][t]}, replay gives {replay.rewards[t]:g}"
        if columns["score"][t] is None or not math.isclose(columns["score"][t], total, abs_tol=1e-9):
            return f"step {t}: recorded score {columns['score'][t]}, replay gives {total:g}"
        if (columns["terminated"][t], columns["truncated"][t]) != (replay.terminated[t], replay.truncated[t]):
            return (f"step {t}: recorded terminated/truncated {columns['terminated'][t]}/{columns['truncated'][t]}, "
                    f"replay gives {replay.terminated[t]}/{replay.truncated[t]}")
        if columns["lives"][t] != replay.lives[t]:
            return f"step {t}: recorded lives {columns['lives'][t]}, replay gives {replay.lives[t]}"
    if steps.num_rows > n:  # the failing step: no action, nothing happened
        t = n
        if (columns["reward"][t], columns["terminated"][t], columns["truncated"][t]) != (0.0, False, False) or (
                columns["score"][t] is None or not math.isclose(columns["score"][t], total, abs_tol=1e-9)):
            return f"step {t} (the failing step, no action) records reward or score"
    if not math.isclose(row["return"], replay.score, abs_tol=1e-9):
        return f"recorded return {row['return']:g}, replay gives {replay.score:g}"
    if row["length"] != n:
        return f"recorded length {row['length']}, replay gives {n}"
    if row["lives_lost"] != replay.lives_lost:
        return f"recorded lives lost {row['lives_lost']}, replay gives {replay.lives_lost}"
    ended = bool(n and (replay.terminated[-1] or replay.truncated[-1]))
    reason = row["end_reason"]
    if ended and reason != ("terminated" if replay.terminated[-1] else "truncated"):
        return f"the game ended at step {n - 1} but the episode reports {reason}"
    if not ended and reason == "terminated":
        return "the episode reports terminated but the game did not end"
    if not ended and reason == "truncated" and n != row["max_steps"]:
        return f"the episode reports truncated after {n} of {row['max_steps']} steps"
    return None


def checked_outcome(spec: EpisodeSpec, outcome: EpisodeOutcome, hosted: bool = True) -> EpisodeOutcome:
    """The outcome of ``spec`` as the parent stores it: row rebuilt, text cleaned (see the module docstring);
    ``hosted``: a game host played it (``verified`` true), else the policy ran in this process (NULL). Never
    raises for anything a worker sent: a malformed step table is kept out and the episode ends ``crashed``."""
    reported = getattr(outcome, "episode", None)
    row = _episode_row(spec, reported if isinstance(reported, dict) else {})
    steps, nodes, why = _tables(outcome)
    if why is not None:
        row.update(end_reason="crashed", error=why, verified=None, length=0)
        return EpisodeOutcome(row, StepLog().table(), None)
    row.update(verified=True if hosted else None)
    printed = getattr(outcome, "printed", None)
    recording = getattr(outcome, "recording", None)
    return EpisodeOutcome(row, steps, nodes,
                          clean_untrusted_text(printed, PRINTED_TEXT_BYTES) if isinstance(printed, str) else None,
                          recording if isinstance(recording, str) else None)


def replay_outcome(spec: EpisodeSpec, row: dict[str, Any], steps: pa.Table) -> str | None:
    """Replay a stored episode's actions (see the module docstring): None if the replay agrees with ``row`` and
    ``steps`` in every step, else the first disagreement."""
    actions, why = _recorded_actions(spec, steps)
    if why is not None:
        return why
    why = _compare(dict(row), steps, replay_actions(spec, actions), len(actions))
    from games.wrappers import may_predate_serve_again  # here: as _acquire_env, the emulator stack on first use

    if why is not None and may_predate_serve_again(get_game(spec.game), spec.sticky):
        if _compare(dict(row), steps, replay_actions(spec, actions, serve_again=False), len(actions)) is None:
            return None
    return why


def _tampered(row: dict[str, Any], steps: pa.Table | None, nodes: pa.Table | None, replay: Replay,
              why: str) -> EpisodeOutcome:
    """The episode as the replay says it went, marked."""
    claimed = row["return"]
    n = replay.length
    if steps is not None and steps.num_rows >= n:
        kept = steps.slice(0, n)
        score, scores = 0.0, []
        for r in replay.rewards:
            score += r
            scores.append(score)
        for name, values in (("reward", replay.rewards), ("score", scores), ("terminated", replay.terminated),
                             ("truncated", replay.truncated), ("lives", replay.lives)):
            i = STEP_SCHEMA.get_field_index(name)
            kept = kept.set_column(i, STEP_SCHEMA.field(i), pa.array(values, type=STEP_SCHEMA.field(i).type))
    else:
        kept = StepLog().table()
    if nodes is not None:
        nodes = nodes.filter(pc.less(nodes.column("step"), n)) if n else None
    claimed_text = "not a number" if claimed is None or math.isnan(claimed) else f"{claimed:g}"
    row.update(
        verified=False, verify_error=clean_untrusted_text(why, MESSAGE_LIMIT), end_reason=TAMPERED,
        length=n, lives_lost=replay.lives_lost,
        error=clean_untrusted_text(f"score tampering detected: {why}; the recorded return {claimed_text} is "
                                   f"replaced by the replay's {replay.score:g}", MESSAGE_LIMIT),
    )
    row["return"] = replay.score
    return EpisodeOutcome(row, kept, nodes)


def tampering(outcomes: list[EpisodeOutcome]) -> str | None:
    """The first tampering error among ``outcomes`` (verified ones), or None."""
    for o in outcomes:
        if o.episode.get("end_reason") == TAMPERED:
            return o.episode.get("error") or "score tampering detected"
    return None


def replay_run(store: Any, run_id: str) -> list[tuple[str, str | None]]:
    """``codearcade doctor --replay RUN``: (episode id, the first disagreement or None) for every episode of the
    run that ended by the game or the step cap, replayed from its recorded actions (see the module docstring);
    the episodes of a continued game in order, each from where the replay of the one before it ended."""
    from store.readers import get_run, replay_material

    with store.read() as con:
        run = get_run(con, run_id)
        material = replay_material(con, run_id)
    # a store is anyone's file: settings that do not read are one line naming the run and the setting
    config = recorded_settings(EvalConfig, run["config"], run_id, ("one_life",)) if run else {}
    one_life = one_life_setting(config.get("one_life") or False)
    found = []
    continued = {row.get("continues") for row, _ in material} - {None}
    open_games: dict[str, Replay] = {}  # episode id -> its replay, whose game a later episode continues
    for row, steps in material:
        continues = row.get("continues")
        spec = EpisodeSpec(episode_id=row["episode_id"], run_id=run_id, game=row["game"], policy_text="",
                           policy_version_id="", seed=int(row["seed"] or 0), max_steps=int(row["max_steps"] or 0),
                           sticky=float(row["sticky"] or 0.0), noop_max=int(row["noop_max"] or 0),
                           one_life=one_life, continues=continues)
        if one_life != ONE_LIFE_CONTINUE:
            found.append((row["episode_id"], replay_outcome(spec, row, steps)))
            continue
        previous = open_games.pop(continues, None) if continues is not None else None
        actions, why = _recorded_actions(spec, steps)
        if why is None and continues is not None and previous is None:
            why = f"it continues episode {continues}, which was not replayed before it"
        if why is None:
            replay = Replay(spec, after=previous)
            replay.feed(actions)
            why = _compare(dict(row), steps, replay, len(actions))
            if row["episode_id"] in continued:
                open_games[row["episode_id"]] = replay
            else:
                replay.release()
        elif previous is not None:
            previous.release()
        found.append((row["episode_id"], why))
    for replay in open_games.values():
        replay.release()
    return found
