"""The episode task, on both sides: one episode played by a game host with a confined policy process, and many at once.

A game host (the game zygote's ``host`` task, ``pipeline/boundary/zygote.py``) runs :func:`host_task`: it resets
the environment, has its policy process (the policy zygote's ``policy`` task, ``pipeline/boundary/policy.py``)
load the policy, and plays the episode (``pipeline/play/rollout.py``), asking the policy process for one action
per step; it writes its progress and its outcome as frames (``pipeline/boundary/wire.py``). The host runs no
policy code, so the rewards, score, lives and steps it reports are right by construction: nothing is replayed to
trust them. In the parent, :func:`run_episodes` plays many through :func:`~pipeline.boundary.workers.run_tasks`,
and :func:`episode_from_worker` checks every field of what a host sent (and the node rows its policy process
made, which the host relays unread) against what the parent asked for and the Arrow schemas ``rollout``
produces, raising :class:`~pipeline.boundary.wire.BadMessage` otherwise (the episode is then recorded as
``crashed`` with that reason). Node rows are the policy process's: read within bounds and checked field by field
(``pipeline/boundary/nodes.py``); rows that break a rule make the episode a ``policy_error`` ("malformed trace at
step N: ..."), its steps kept and its nodes dropped; a traced episode that arrives without node rows says why
(``trace missing: ...``, the host's reason: ``pipeline/play/channels.py``), never passes for traced with none.
Fields the parent knows (ids, seed, settings) are taken from
the :class:`EpisodeSpec`, never from the worker.
"""

from __future__ import annotations

import math
import signal
import socket
import sys
from contextlib import closing
from dataclasses import asdict, fields
from datetime import datetime
from typing import Any, Callable, Iterable, Iterator

from games import get_game
from pipeline.boundary import wire
from pipeline.boundary.nodes import MalformedTrace, check_nodes, read_nodes
from pipeline.boundary.policy import PRINTED_TEXT_BYTES
from pipeline.boundary.untrusted import utf8_prefix
from pipeline.boundary.wire import MAX_TEXT, BadMessage
from pipeline.boundary.workers import ProgressCallback, Task, run_tasks
from pipeline.boundary.zygotes import Zygote
from pipeline.play.channels import RemotePolicy
from pipeline.play.rollout import (GAME_END_REASONS, EpisodeOutcome, _episode_row, crashed_outcome, play_episode,
                                   play_game, prepare_episode, run_episode, run_game)
from pipeline.play.spec import EpisodeSpec
from viewers.safe_text import terminal_text

RECORDING_TEXT_BYTES = 1_000
"""At most this much of why an episode's live recording failed is said (a path and Rerun's reason)."""

WORKER_END_REASONS = frozenset({"terminated", "truncated", "policy_error", "timeout", "crashed"})
"""End reasons a host may report (``crashed``: its policy process died or broke the protocol, the steps before
kept; ``tampered`` belongs to the replay check of old runs)."""


# ---------------------------------------------------------------------------------------------- the host


def host_task(item: dict[str, Any], fd: int, policy_fd: int) -> Callable[[int | None], bool]:
    """In a game host (the game zygote's ``host`` task): prepare the episode ``item`` (an :class:`EpisodeSpec` as
    JSON) with its policy process on ``policy_fd`` (environment reset, policy loaded: a staged host does this
    before its go-ahead, while the previous episode plays), and return what plays it on a CPU and writes its
    progress and outcome on ``fd``: the result, the step rows, and the node rows as the policy process sent them."""
    spec = spec_from_json(item)
    policy = RemotePolicy(socket.socket(fileno=policy_fd), spec, get_game(spec.game).n_actions)
    prepared = prepare_episode(spec, policy)

    def play(cpu: int | None) -> bool:
        try:
            outcome = play_episode(prepared, lambda n: wire.write_all(fd, wire.json_frame({"kind": "progress",
                                                                                          "n": n})), cpu=cpu)
        finally:
            policy.close()  # the host may play the next episode, with a new policy process
        nodes = outcome.nodes
        frames = [wire.json_frame({"kind": "result", "episode": episode_to_json(outcome.episode, outcome.printed,
                                                                                outcome.recording),
                                   "nodes": nodes is not None}), wire.arrow_frame(outcome.steps)]
        if nodes is not None:
            frames.append(wire.raw_arrow_frame(nodes) if isinstance(nodes, bytes) else wire.arrow_frame(nodes))
        wire.write_all(fd, b"".join(frames))
        return _can_play_again()

    return play


def _can_play_again() -> bool:
    """Whether this host may play another episode: not once a Rerun recording's sink is stuck in it (a disk that
    filled under ``--rerun DIR``: ``viewers.rerun_recording.within``), which would hold up every recording after it.
    The zygote then lets it go and the next episode gets a fresh host."""
    recording = sys.modules.get("viewers.rerun_recording")  # loaded only where an episode was recorded
    return not (recording is not None and recording.wedged)


def game_host_task(item: dict[str, Any], fd: int, policy_fd: int) -> Callable[[int | None], bool]:
    """In a game host (the game zygote's ``game`` task): the episodes of one continued game (``item["episodes"]``,
    :class:`EpisodeSpec` s as JSON, in order), played one after the other with one environment and one policy
    process that keeps its state (``pipeline/play/rollout.py`` :func:`play_game`). Prepared as :func:`host_task`
    (the first episode's reset, the policy loaded); it writes the game's steps so far as progress and, at the
    end, one result with every episode's row, then each episode's step rows (and node rows)."""
    specs = [spec_from_json(data) for data in item["episodes"]]
    policy = RemotePolicy(socket.socket(fileno=policy_fd), specs[0], get_game(specs[0].game).n_actions)
    first = prepare_episode(specs[0], policy)

    def play(cpu: int | None) -> bool:
        try:
            outcomes = play_game(specs, first, lambda n: wire.write_all(fd, wire.json_frame({"kind": "progress",
                                                                                            "n": n})), cpu=cpu)
        finally:
            policy.close()
        frames = [wire.json_frame({"kind": "result", "episodes": [episode_to_json(o.episode, o.printed, o.recording)
                                                                  for o in outcomes],
                                   "nodes": [o.nodes is not None for o in outcomes]})]
        for outcome in outcomes:
            frames.append(wire.arrow_frame(outcome.steps))
            nodes = outcome.nodes
            if nodes is not None:
                frames.append(wire.raw_arrow_frame(nodes) if isinstance(nodes, bytes) else wire.arrow_frame(nodes))
        wire.write_all(fd, b"".join(frames))
        return _can_play_again()

    return play


# ------------------------------------------------------------------------------------------------- the wire


def spec_to_json(spec: Any) -> dict[str, Any]:
    data = asdict(spec)
    for key, value in data.items():
        if not (value is None or isinstance(value, (str, int, float, bool))):
            raise TypeError(f"EpisodeSpec.{key} is not a primitive")
    return data


def spec_from_json(data: dict[str, Any]) -> Any:
    names = {f.name for f in fields(EpisodeSpec)}
    return EpisodeSpec(**{k: v for k, v in data.items() if k in names})


MEASURED = ("game", "started_at", "duration_s", "env_s", "policy_s", "length", "lives_lost", "end_reason", "error",
            "return")


def episode_to_json(episode: dict[str, Any], printed: str | None = None,
                    recording: str | None = None) -> dict[str, Any]:
    """The episode row as the host sends it, with what the policy printed (``EpisodeSpec.keep_printed``) and why
    its live recording is not whole (``EpisodeOutcome.recording``)."""
    row = {k: episode[k] for k in MEASURED + ("episode_id",)}
    if printed is not None:
        row["printed"] = printed
    if recording is not None:
        row["recording"] = recording[:RECORDING_TEXT_BYTES]
    if isinstance(row["started_at"], datetime):
        row["started_at"] = row["started_at"].isoformat()
    if isinstance(row["error"], str):
        row["error"] = row["error"][:MAX_TEXT]
    return row


def _number(row: dict, key: str, nullable: bool = False) -> float | None:
    value = row.get(key)
    if value is None and nullable:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BadMessage(f"episode field {key} is not a finite number: {str(value)[:50]}")
    return float(value)


def _int(row: dict, key: str, low: int, high: int) -> int:
    value = row.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise BadMessage(f"episode field {key} is not an int in {low}..{high}: {str(value)[:50]}")
    return value


def episode_from_worker(spec: Any, row: Any, steps: Any, nodes: Any) -> Any:
    """The :class:`EpisodeOutcome` of ``spec`` from what its worker sent, every value checked; BadMessage if
    anything is off. Fields the parent knows (ids, seed, settings) come from ``spec``, never from the worker."""
    if not isinstance(row, dict):
        raise BadMessage("the episode row is not an object")
    if row.get("episode_id") != spec.episode_id:
        raise BadMessage(f"the worker answered for episode {str(row.get('episode_id'))[:60]!r}, "
                         f"not {spec.episode_id!r}")
    game = get_game(spec.game).name
    if row.get("game") != game:
        raise BadMessage(f"the episode's game is {str(row.get('game'))[:30]!r}, not {game!r}")
    end_reason = row.get("end_reason")
    if end_reason not in WORKER_END_REASONS:
        raise BadMessage(f"unknown end reason {str(end_reason)[:30]!r}")
    error = row.get("error")
    if error is not None and not isinstance(error, str):
        raise BadMessage("the episode's error is not text")
    printed = row.get("printed") if spec.keep_printed else None
    if printed is not None and not isinstance(printed, str):
        raise BadMessage("what the policy printed is not text")
    recording = row.get("recording") if spec.rerun else None
    if recording is not None and not isinstance(recording, str):
        raise BadMessage("why the recording failed is not text")
    if recording is not None:
        recording = utf8_prefix(recording, RECORDING_TEXT_BYTES)
    try:
        started_at = datetime.fromisoformat(row["started_at"]) if row.get("started_at") is not None else None
    except (TypeError, ValueError):
        raise BadMessage("started_at is not an ISO timestamp") from None
    length = _int(row, "length", 0, spec.max_steps)
    measured = dict(
        game=game, started_at=started_at, duration_s=_number(row, "duration_s"),
        env_s=_number(row, "env_s", nullable=True), policy_s=_number(row, "policy_s", nullable=True),
        length=length, lives_lost=_int(row, "lives_lost", 0, 2**31 - 1), end_reason=end_reason,
        error=error[:MAX_TEXT] if error else error,
    )
    failed_step = end_reason in ("policy_error", "timeout", "crashed")  # the step the policy failed on is stored too
    if steps.num_rows not in ((length, length + 1) if failed_step else (length,)) or steps.num_rows > spec.max_steps:
        raise BadMessage(f"{steps.num_rows} step rows for an episode of length {length}")
    if steps.num_rows and steps.column("step").to_pylist() != list(range(steps.num_rows)):
        raise BadMessage("the step rows are not numbered 0, 1, 2, ...")
    if printed is not None:
        printed = utf8_prefix(printed, PRINTED_TEXT_BYTES)
    episode = _episode_row(spec, score=_number(row, "return"), **measured)
    if nodes is not None:
        try:
            nodes = (read_nodes(nodes, spec, steps.num_rows, episode["duration_s"]) if isinstance(nodes, bytes)
                     else check_nodes(nodes, spec, steps.num_rows, episode["duration_s"]) or nodes)
        except MalformedTrace as exc:
            return EpisodeOutcome(trace_refused(episode, str(exc)), steps, None, printed, recording)
    elif spec.trace:  # the host records why a traced episode's rows did not come (channels.no_trace): this is a host
        # that did not, and the episode must not pass for traced with no rows and no error
        trace_refused(episode, "trace missing: the game host sent no node rows for a traced episode")
    return EpisodeOutcome(episode, steps, nodes, printed, recording)


def trace_refused(episode: dict[str, Any], error: str) -> dict[str, Any]:
    """``episode`` (a row) ended by its policy's malformed trace: a policy error (a forfeit), unless the policy
    had already failed (that error stays: it came first)."""
    if episode["end_reason"] in GAME_END_REASONS:
        episode.update(end_reason="policy_error", error=error)
    return episode


# ----------------------------------------------------------------------------------------------- the parent



def _episode_failed(spec: EpisodeSpec, error: str, timed_out: bool) -> EpisodeOutcome:
    outcome = crashed_outcome(spec, error)
    if timed_out:
        outcome.episode["end_reason"] = "timeout"
    return outcome


def _decode_episode(spec: EpisodeSpec, msg: dict[str, Any], tables: list[bytes]) -> EpisodeOutcome:
    from tracing.steps import STEP_SCHEMA

    steps = wire.parse_arrow(tables[0], STEP_SCHEMA, max_rows=spec.max_steps)
    # the node rows as the policy process sent them (the host relays them unread): read bounded, then checked
    return episode_from_worker(spec, msg.get("episode"), steps, tables[1] if len(tables) > 1 else None)


def _policy_limits(spec: EpisodeSpec) -> dict[str, Any]:
    """The policy process's limits (``pipeline.boundary.confine.Limits``); the host writes every file itself."""
    return dict(memory_mb=spec.memory_limit_mb)


def _policy_died(outcome: EpisodeOutcome, exit_code: Callable[[], int | None]) -> EpisodeOutcome:
    """A ``crashed`` episode says how its policy process ended (a CPU limit is a time-out)."""
    if outcome.end_reason != "crashed":
        return outcome
    code = exit_code()
    if code == -signal.SIGXCPU:
        outcome.episode.update(end_reason="timeout", error="the policy process exceeded its CPU-time limit")
    elif code is not None and code < 0:
        outcome.episode["error"] = f"{outcome.episode['error']} (killed by signal {-code})"
    return outcome


EPISODE = Task("host", run_episode, spec_to_json, _decode_episode,
               tables=lambda msg: 2 if msg.get("nodes") is True else 1, limits=_policy_limits, paired=True,
               after_pair=_policy_died)


# ------------------------------------------------------------------------- continued games (one_life="continue")


def games_of(specs: list[EpisodeSpec]) -> list[list[int]]:
    """The indices of ``specs`` grouped into games, in order: an episode that ``continues`` another joins that
    one's game, right after it; every other episode is a game of its own. ValueError for a spec that continues
    one that is not the last of a game listed before it."""
    games: list[list[int]] = []
    last_of: dict[str, list[int]] = {}  # episode id -> its game, while it is the game's last episode
    for i, spec in enumerate(specs):
        if spec.continues is None:
            game = [i]
            games.append(game)
        else:
            game = last_of.pop(spec.continues, None)
            if game is None:
                raise ValueError(f"episode {spec.episode_id} continues {spec.continues}, which is not the last "
                                 f"episode of a game listed before it")
            game.append(i)
        last_of[spec.episode_id] = game
    return games


def _game_to_json(game: list[EpisodeSpec]) -> dict[str, Any]:
    return {"episodes": [spec_to_json(spec) for spec in game]}


def _game_tables(msg: dict[str, Any]) -> int:
    flags = msg.get("nodes")
    if not isinstance(flags, list) or len(flags) > 2**16:
        raise BadMessage("a game's result without its list of node flags")
    return sum(2 if flag is True else 1 for flag in flags)


def _decode_game(game: list[EpisodeSpec], msg: dict[str, Any], tables: list[bytes]) -> list[EpisodeOutcome]:
    """Each episode of a continued game from what its host sent, checked as :func:`episode_from_worker` does,
    and as a game: once an episode ended by the policy's failure, the rest were not played (length 0); each
    ``start_step`` is the sum of the lengths before it (the parent's, never the host's)."""
    rows, flags = msg.get("episodes"), msg.get("nodes")
    if not isinstance(rows, list) or not isinstance(flags, list) or len(rows) != len(game) or len(flags) != len(game):
        raise BadMessage(f"a game of {len(game)} episodes answered with another number of episodes")
    outcomes, at, played, stopped = [], 0, 0, False
    for spec, row, flag in zip(game, rows, flags):
        taken = tables[at:at + (2 if flag is True else 1)]
        at += len(taken)
        outcome = _decode_episode(spec, {"episode": row}, taken)
        if stopped and outcome.episode["length"]:
            raise BadMessage(f"episode {spec.index} was played after its game ended by the policy's failure")
        outcome.episode["start_step"] = played
        played += outcome.episode["length"]
        # the game goes on after an episode the host saw end normally, even if its trace is then refused here
        stopped = stopped or (row.get("end_reason") if isinstance(row, dict) else None) not in GAME_END_REASONS
        outcomes.append(outcome)
    return outcomes


def _game_failed(game: list[EpisodeSpec], error: str, timed_out: bool) -> list[EpisodeOutcome]:
    return [_episode_failed(spec, error, timed_out) for spec in game]


def _game_policy_died(outcomes: list[EpisodeOutcome], exit_code: Callable[[], int | None]) -> list[EpisodeOutcome]:
    return [_policy_died(outcome, exit_code) for outcome in outcomes]


GAME = Task("game", run_game, _game_to_json, _decode_game, tables=_game_tables,
            limits=lambda game: _policy_limits(game[0]), paired=True, after_pair=_game_policy_died)
"""A continued game: one host and one policy process play its episodes in order (:func:`game_host_task`)."""


def run_episodes(
    specs: Iterable[EpisodeSpec],
    workers: int = 1,
    progress: ProgressCallback | None = None,
    started: Callable[[], None] | None = None,
    deadline: float | None = None,
) -> Iterator[tuple[int, EpisodeOutcome]]:
    """Play ``specs``, each by a game host with a confined policy process (see
    :func:`~pipeline.boundary.workers.run_tasks`); an episode whose host or policy process dies, misbehaves or hangs
    ends ``crashed`` or ``timeout``. Past ``deadline`` (``time.monotonic()``) the episodes playing are ended and
    :class:`~pipeline.boundary.workers.DeadlinePassed` raised."""
    specs = list(specs)
    # each environment is built once in the game zygote (~0.1-0.2 s each): forked hosts inherit it ready, and a
    # host kept from an earlier call (zygotes.keep_hosts) is handed only episodes on the environments it has
    envs = tuple(sorted({(s.game, s.sticky, s.noop_max, s.one_life, s.observation) for s in specs}, key=str))

    def prepare(zyg: Zygote) -> None:
        try:
            zyg.send({"op": "prepare", "envs": [list(e) for e in envs]})
        except OSError:
            pass  # the zygote died: every episode is recorded as crashed

    if all(spec.continues is None for spec in specs):
        played = run_tasks(EPISODE, specs, workers, _episode_failed,
                           time_limit_s=lambda spec: spec.episode_time_limit_s, progress=progress, started=started,
                           prepare=prepare, hosts_key=envs, deadline=deadline)
    else:
        played = _run_games(specs, workers, progress, started, prepare, envs, deadline)
    return _saying_recordings(played) if any(spec.rerun for spec in specs) else played


def _saying_recordings(played: Iterator[tuple[int, EpisodeOutcome]]) -> Iterator[tuple[int, EpisodeOutcome]]:
    """``played``, saying on stderr which episode's live Rerun recording is not whole and why (a full disk under
    ``--rerun DIR``): the host that recorded it writes its stderr nowhere, and the recording was lost unsaid. Its
    file is removed, never left cut short under the episode's name; the store has the episode, which ``view`` can
    record again."""
    with closing(played):  # a caller that stops early (a Ctrl-C, a deadline) ends the episodes playing
        for i, outcome in played:
            if outcome.recording:
                episode_id, run_id = outcome.episode["episode_id"], outcome.episode["run_id"]
                print(terminal_text(f"codearcade: the Rerun recording of episode {episode_id} was not made: "
                                    f"{outcome.recording}; the episode is stored (`codearcade view {run_id} "
                                    f"--episode {episode_id} --save FILE.rrd` records it again)"),
                      file=sys.stderr, flush=True)
            yield i, outcome


def _run_games(specs: list[EpisodeSpec], workers: int, progress: ProgressCallback | None,
               started: Callable[[], None] | None, prepare: Callable[[Zygote], None], envs: tuple,
               deadline: float | None = None) -> Iterator[tuple[int, EpisodeOutcome]]:
    """:func:`run_episodes` where some episodes continue others: each game (:func:`games_of`) is one task of
    one host and one policy process (:data:`GAME`), an episode of its own a game of one; its time limit is the
    sum of its episodes'. Progress is reported under the index of the game's first episode."""
    games = games_of(specs)
    items = [[specs[i] for i in game] for game in games]
    report = None if progress is None else (lambda g, n: progress(games[g][0], n))
    for g, outcomes in run_tasks(GAME, items, workers, _game_failed,
                                 time_limit_s=lambda game: sum(spec.episode_time_limit_s for spec in game),
                                 progress=report, started=started, prepare=prepare, hosts_key=envs,
                                 deadline=deadline):
        for i, outcome in zip(games[g], outcomes):
            yield i, outcome
