"""The settings of ``codearcade serve`` (:class:`ServeConfig`), each declared once (``pipeline/settings.py``): the
command line's flags come from these declarations; :func:`served_settings` reads them back from a served run's
store, checked."""

from __future__ import annotations

import reprlib
from dataclasses import asdict, dataclass
from typing import Any

from games import GAMES
from games.base import AUDIT_SEED_BASE, STANDARD_NOOP_MAX, STANDARD_STICKY
from pipeline.play.config import MAX_EPISODES
from pipeline.settings import limit, recorded_problem, setting
from store.recorded import unreadable_settings


@dataclass
class ServeConfig:
    """Options of a served run (the flags of ``codearcade serve``)."""

    policy: str | None = setting(None, "the starting policy file (default: the game's scaffold)", positional=True,
                                 metavar="POLICY.py")
    game: str | None = setting(None, f"game to play: {', '.join(GAMES)}, or any game OCAtari reads (default: the "
                               "file's GAME)")
    budget: int = setting(64, "training episodes the agent may play in the whole run, failures included (default: "
                          "%(default)s)", minimum=1, maximum=MAX_EPISODES)
    """The run's episode budget: every episode a submission asks for costs one, whatever ends it; a request
    refused before anything plays (malformed, a policy that does not parse) costs nothing."""
    instances: int = setting(16, "visible training instances, ids 0..N-1 (default: %(default)s)", minimum=1,
                             maximum=4096)
    """Training instances the agent names by id; each is a game seed drawn from the OS's entropy when the run is
    made, below the audit's range, recorded only in the run's config and its episodes, never in a response."""
    per_submission: int = setting(8, "most episodes one submission may ask for (default: %(default)s)", minimum=1,
                                 maximum=MAX_EPISODES)
    validation_episodes: int = setting(5, "games of the sealed validation pool each accepted submission plays at "
                                       "the end (default: %(default)s)", minimum=1,
                                       maximum=MAX_EPISODES)
    heldout_episodes: int = setting(5, "games of the sealed held-out pool the best by validation (and the starter) "
                                    "play at the end (default: %(default)s)", minimum=1,
                                    maximum=MAX_EPISODES)
    max_steps: int = limit("max_steps", help="step cap of every episode (default: %(default)s)")
    workers: int = setting(1, "episodes played at once (default: %(default)s)", minimum=1)
    call_time_limit_s: float = limit("call_time_limit_s")
    episode_time_limit_s: float = limit("episode_time_limit_s", cli=False)


PROTOCOL_KEYS = ("train_seeds", "sticky", "noop_max")
"""What a served run records under ``serve`` beside its settings: the training instances' seeds, drawn when it is
made, and the protocol every game of it is played under (``pipeline/serve/protocol.py: create_run``)."""


def served_settings(record: dict[str, Any], run_id: str) -> dict[str, Any]:
    """A served run's ``serve`` settings as its store records them (``record``: its ``runs.config``, as
    ``pipeline.settings.read_recorded`` reads it), each checked as its flag is, a setting the run predates taking
    its default, with the seeds and protocol it was made with (:data:`PROTOCOL_KEYS`: the standard protocol, which
    its rules promise); an ``unreadable_settings`` error naming the first that is not what it should be. A store is
    anyone's file: a budget of null, a missing key or a text where a number goes had ended ``serve --resume`` and
    ``--finalize`` in a traceback (some after the run was marked running). The other recorded settings a served
    run plays with (``observation``, ``rng_key``) are checked as an optimization's are."""
    from pipeline.optimizer.config import OptimizeConfig
    from pipeline.optimizer.task import recorded_task_problem

    served = record.get("serve")
    if not isinstance(served, dict):
        raise unreadable_settings(run_id, f"serve must be a JSON object, not {reprlib.repr(served)}")
    problem = recorded_problem(ServeConfig, served)
    if problem is not None:
        raise unreadable_settings(run_id, f"serve.{problem}")
    config = ServeConfig(**{k: served[k] for k in ServeConfig.__dataclass_fields__ if k in served})
    missing = [key for key in PROTOCOL_KEYS if key not in served]
    if missing:
        raise unreadable_settings(run_id, f"serve.{missing[0]} is missing")
    seeds = served["train_seeds"]
    if not isinstance(seeds, list) or len(seeds) < config.instances or \
            any(not isinstance(s, int) or isinstance(s, bool) or not 0 <= s < AUDIT_SEED_BASE for s in seeds):
        raise unreadable_settings(run_id, f"serve.train_seeds must list {config.instances} seeds (whole numbers "
                                          f"from 0 to {AUDIT_SEED_BASE - 1}), not {reprlib.repr(seeds)}")
    for key, standard in (("sticky", STANDARD_STICKY), ("noop_max", STANDARD_NOOP_MAX)):  # the rules it serves
        # say every game is played under the standard protocol (a no-op count of 2**70 passed any range)
        if served[key] != standard or isinstance(served[key], bool):
            raise unreadable_settings(run_id, f"serve.{key} must be {standard}, the standard protocol's, not "
                                              f"{reprlib.repr(served[key])}")
    problem = recorded_problem(OptimizeConfig, {k: record[k] for k in ("observation", "rng_key") if k in record}) \
        or recorded_task_problem(record, ("instruction",))  # the instruction goes to the agent as it is
    if problem is not None:
        raise unreadable_settings(run_id, problem)
    return {**served, **asdict(config)}
