"""Which store a command uses, found without thinking: the one function every verb asks.

In order, the first that applies:

1. ``--store PATH`` (``explicit``);
2. ``$CODEARCADE_STORE``;
3. the nearest ``codearcade.duckdb`` in the working directory or one of its parents, as git finds ``.git``, so
   every verb run from a subdirectory of a project uses the project's store;
4. the per-user store, ``$XDG_DATA_HOME/codearcade/codearcade.duckdb`` (``~/.local/share/codearcade/`` when
   ``XDG_DATA_HOME`` is unset or not absolute, as the XDG base directory specification says); its directory is
   made the first time a run writes there.

:class:`StoreLocation` says which rule chose the store, so the command line can print it where ambiguity could
bite (a store found in a parent directory, or the per-user one, is not the file a person might expect).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

DEFAULT_STORE = "codearcade.duckdb"
"""The store's file name: what the search through parent directories looks for."""

ENV_STORE = "CODEARCADE_STORE"

RULES = ("option", "environment", "here", "parent", "user", "experiment")
"""How a store was chosen: ``--store``; ``$CODEARCADE_STORE``; ``codearcade.duckdb`` in the working directory; in
a parent directory; the per-user default; an experiment file's ``store`` (``codearcade batch``, which puts it
between ``--store`` and the environment)."""


@dataclass(frozen=True)
class StoreLocation:
    path: Path
    rule: str
    """One of :data:`RULES`."""

    @property
    def surprising(self) -> bool:
        """Whether the choice may not be the file a person expects: found in a parent directory, or the per-user
        default (the command line prints :meth:`describe` then)."""
        return self.rule in ("parent", "user")

    def describe(self) -> str:
        """One line: the store's path and the rule that chose it."""
        why = {
            "option": "given with --store",
            "environment": f"from ${ENV_STORE}",
            "here": "in the working directory",
            "parent": "the nearest in a parent directory",
            "user": f"the per-user store: no {DEFAULT_STORE} in this directory or a parent, no --store, "
                    f"no ${ENV_STORE}",
            "experiment": "named by the experiment file's store",
        }[self.rule]
        return f"store {self.path} ({why})"


def user_store_path(environ: Mapping[str, str] | None = None) -> Path:
    """The per-user store: ``$XDG_DATA_HOME/codearcade/codearcade.duckdb``, else under ``~/.local/share``."""
    environ = os.environ if environ is None else environ
    data_home = environ.get("XDG_DATA_HOME", "")
    if not data_home or not os.path.isabs(data_home):  # the spec: a relative value is invalid and ignored
        home = environ.get("HOME") or os.path.expanduser("~")
        data_home = os.path.join(home, ".local", "share")
    return Path(data_home) / "codearcade" / DEFAULT_STORE


def locate_store(explicit: str | os.PathLike | None = None, cwd: str | os.PathLike | None = None,
                 environ: Mapping[str, str] | None = None, ceiling: str | os.PathLike | None = None) -> StoreLocation:
    """The store a command uses (see the module docstring for the rules). ``cwd`` and ``environ`` default to the
    process's; the search through parents stops below ``ceiling`` when given (it is not searched itself, as
    git's ``GIT_CEILING_DIRECTORIES``), else at the filesystem's root."""
    environ = os.environ if environ is None else environ
    if explicit:
        return StoreLocation(Path(explicit), "option")
    if environ.get(ENV_STORE):
        return StoreLocation(Path(environ[ENV_STORE]), "environment")
    start = Path(os.path.abspath(cwd if cwd is not None else os.getcwd()))
    stop = Path(os.path.abspath(ceiling)) if ceiling is not None else None
    for directory in (start, *start.parents):
        if stop is not None and directory == stop:
            break
        candidate = directory / DEFAULT_STORE
        if candidate.is_file():
            return StoreLocation(candidate, "here" if directory == start else "parent")
    return StoreLocation(user_store_path(environ), "user")
