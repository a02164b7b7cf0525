"""Identity and provenance of runs: ULID run ids, episode ids, and the package versions a run used."""

from __future__ import annotations

import functools
import hashlib
import os
import time
from importlib import metadata

_CROCKFORD = "0123456789ABCDEFGHJKMNPQRSTVWXYZ"

PROVENANCE_PACKAGES = (
    "codearcade", "gymnasium", "ale-py", "ocatari", "numpy", "duckdb", "pyarrow", "rerun-sdk", "litellm", "radon",
)


def new_run_id(now: float | None = None) -> str:
    """A ULID: 48 bits of milliseconds then 80 random bits, 26 Crockford base-32 characters (sortable by time)."""
    ms = int((time.time() if now is None else now) * 1000)
    value = (ms << 80) | int.from_bytes(os.urandom(10), "big")
    return "".join(_CROCKFORD[(value >> shift) & 31] for shift in range(125, -1, -5))


def episode_id(run_id: str, iteration: int, kind: str, index: int, candidate: int = 0) -> str:
    """Deterministic episode id: ``{run_id}.{iteration}.{kind}.{index}``, or ``{run_id}.{iteration}.c{candidate}.
    {kind}.{index}`` for an iteration's later candidates (re-running an episode replaces it)."""
    if candidate:
        return f"{run_id}.{iteration}.c{candidate}.{kind}.{index}"
    return f"{run_id}.{iteration}.{kind}.{index}"


def audit_episode_id(run_id: str, iteration: int, protocol: str, index: int, audit: str) -> str:
    """An audit's episode: ``{run_id}.{iteration}.audit-{protocol}.{index}.{audit}``, ``audit`` the token of the
    audit that plays it (:func:`new_audit_token`). Each audit's games have ids of their own, so a re-audit stopped
    part way never overwrites a game the earlier audit's rows still name."""
    return f"{episode_id(run_id, iteration, f'audit-{protocol}', index)}.{audit}"


def new_audit_token() -> str:
    """A token for an audit's episode ids: the time part of a ULID (milliseconds), ordered as the audits were."""
    return new_run_id()[:10]


def policy_rng_seed(key: str, game_seed: int) -> int:
    """The seed of a policy process's ``random`` and NumPy generators for the game of ``game_seed``, in the run
    whose random stream is ``key`` (its ``rng_key``: the run's id, or the replayed run's).

    A keyed hash (BLAKE2b of the game's seed, keyed with the run's key), so the same run and game seed give the
    same stream (a resumed or replayed run, and the evaluation cache, see the same policy behaviour) while the
    policy, which never sees the key, cannot read the game's seed back from what its generators draw, nor carry a
    table keyed by them from one run to another."""
    digest = hashlib.blake2b(str(int(game_seed)).encode(), digest_size=8, key=key.encode()[:64],
                             person=b"codearcade.rng").digest()
    return int.from_bytes(digest, "big") >> 1


def package_versions() -> dict[str, str]:
    """Installed versions of the packages that decide a run's behaviour."""
    return dict(_package_versions())


@functools.lru_cache(maxsize=1)  # ~20 ms of metadata parsing, once per process instead of once per run
def _package_versions() -> dict[str, str]:
    versions = {}
    for name in PROVENANCE_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions
