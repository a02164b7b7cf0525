"""The settings of ``codearcade serve`` (:class:`ServeConfig`), each declared once (``pipeline/settings.py``): the
command line's flags come from these declarations."""

from __future__ import annotations

from dataclasses import dataclass

from games import GAMES
from pipeline.settings import limit, setting


@dataclass
class ServeConfig:
    """Options of a served run (the flags of ``codearcade serve``)."""

    policy: str | None = setting(None, "the starting policy file (default: the game's scaffold)", positional=True,
                                 metavar="POLICY.py")
    game: str | None = setting(None, f"game to play: {', '.join(GAMES)}, or any game OCAtari reads (default: the "
                               "file's GAME)")
    budget: int = setting(64, "training episodes the agent may play in the whole run, failures included (default: "
                          "%(default)s)", minimum=1)
    """The run's episode budget: every episode a submission asks for costs one, whatever ends it; a request
    refused before anything plays (malformed, a policy that does not parse) costs nothing."""
    instances: int = setting(16, "visible training instances, ids 0..N-1 (default: %(default)s)", minimum=1,
                             maximum=4096)
    """Training instances the agent names by id; each is a game seed drawn from the OS's entropy when the run is
    made, below the audit's range, recorded only in the run's config and its episodes, never in a response."""
    per_submission: int = setting(8, "most episodes one submission may ask for (default: %(default)s)", minimum=1)
    validation_episodes: int = setting(5, "games of the sealed validation pool each accepted submission plays at "
                                       "the end (default: %(default)s)", minimum=1)
    heldout_episodes: int = setting(5, "games of the sealed held-out pool the best by validation (and the starter) "
                                    "play at the end (default: %(default)s)", minimum=1)
    max_steps: int = limit("max_steps", help="step cap of every episode (default: %(default)s)")
    workers: int = setting(1, "episodes played at once (default: %(default)s)", minimum=1)
    call_time_limit_s: float = limit("call_time_limit_s")
    episode_time_limit_s: float = limit("episode_time_limit_s", cli=False)
