"""OCAtari imported without the libraries of its vision mode and of its own window, which codearcade never uses.

Importing ``ocatari`` (any of its modules) runs its package: ``ocatari.ram.utils`` takes ``match_objects`` from
``ocatari.vision.utils``, whose top imports ``skimage.morphology``, ``matplotlib.pyplot`` and ``scipy.optimize``
(three vision readers import ``matplotlib``, and ``ocatari.core`` pygame for a window of its own). The RAM readers,
the only part codearcade runs, use none of them but scipy's ``linear_sum_assignment``, and that only in the readers
that match objects from step to step (Enduro's, of the eight games); together they were ~0.8-1.1 s of a game
zygote's start, on the path of every command that plays (the zygote imports OCAtari before its first episode).

:func:`install` (called by ``games/__init__.py``, before anything imports OCAtari) puts a finder first on
``sys.meta_path`` that wraps the first import of the ``ocatari`` package: while it runs, those modules, when not
imported already, are :class:`Deferred` stand-ins, and afterwards they are taken out of ``sys.modules``, so that
any later import gets the real ones. What OCAtari's vision code bound from them (``plt``, ``disk``,
``linear_sum_assignment``, ...) stays a stand-in that imports the real module at its first use and forwards to it:
OCAtari behaves as before, the import is only paid by what uses it. An environment whose reader matches objects
calls :func:`ready` as it is built (``games.envs.ObjectObservation``): scipy's ``optimize`` is imported then, in
the game zygote before any host forks, and OCAtari's modules get the real functions in place of the stand-ins.
OpenCV, which the RAM readers use too, is imported in full.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import types
from typing import Any

DEFERRED = ("matplotlib", "matplotlib.pyplot", "skimage.morphology", "scipy.optimize", "pygame")
"""Modules OCAtari imports at its top for its vision readers (``ocatari.vision.utils``, ``.enduro``, ``.frostbite``,
``.pitfall``) and its own window (``ocatari.core``, ``ocatari.utils``: pygame, with setuptools' ``pkg_resources``),
which its RAM readers never use, but for :data:`USED_AT_RUN_TIME`."""

USED_AT_RUN_TIME = {"match_objects": "scipy.optimize"}
"""What a RAM reader may bind that reaches a deferred module when called: OCAtari's matching of objects from step
to step (``ocatari.vision.utils.match_objects``, bound by the readers of Amidar, Asteroids, Berzerk, Chopper Command,
Enduro, Frostbite, Krull and Road Runner) calls scipy's ``linear_sum_assignment``."""


_importing = False
"""Whether the wrapped import of ``ocatari`` is running (what it binds is deferred; anything asked later is real)."""


class Deferred(types.ModuleType):
    """A stand-in for the module of its name: what OCAtari's import takes from it (``from skimage.morphology import
    disk``) is a :class:`Forward`; whatever is asked of it after (``plt.figure``) is the real module's, imported
    then."""

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)
        submodule = sys.modules.get(f"{self.__name__}.{attr}")
        if isinstance(submodule, Deferred):  # ``import matplotlib.pyplot as plt`` takes pyplot from matplotlib
            return submodule
        forward = Forward(self.__name__, (attr,))
        return forward if _importing else forward.resolve()


class Forward:
    """``module.path...`` of a deferred module: called, or an attribute of it called, it imports the real module
    (and a submodule on the path, as ``matplotlib.pyplot``) and does the same there."""

    def __init__(self, module: str, path: tuple[str, ...]):
        self._module, self._path = module, path

    def resolve(self) -> Any:
        value = importlib.import_module(self._module)
        for i, attr in enumerate(self._path):
            try:
                value = getattr(value, attr)
            except AttributeError:  # a submodule not imported yet
                value = importlib.import_module(".".join((self._module, *self._path[:i + 1])))
        return value

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.resolve()(*args, **kwargs)

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)
        return Forward(self._module, (*self._path, attr)) if _importing else getattr(self.resolve(), attr)


class _Wrapped(importlib.abc.Loader):
    """The ``ocatari`` package's own loader, with the stand-ins in place while it runs."""

    def __init__(self, loader: Any):
        self.loader = loader

    def create_module(self, spec: Any) -> Any:
        return self.loader.create_module(spec)

    def __getattr__(self, name: str) -> Any:  # the rest of a loader's interface (its source, its resources)
        return getattr(self.loader, name)

    def exec_module(self, module: types.ModuleType) -> None:
        global _importing
        placed = [name for name in DEFERRED if name not in sys.modules]
        for name in placed:
            sys.modules[name] = Deferred(name)
        _importing = True
        try:
            self.loader.exec_module(module)
        finally:
            _importing = False
            for name in placed:
                if isinstance(sys.modules.get(name), Deferred):
                    del sys.modules[name]


class _FirstImport(importlib.abc.MetaPathFinder):
    """Finds the ``ocatari`` package once, as the finders after it would, and wraps its loader."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if fullname != "ocatari":
            return None
        sys.meta_path.remove(self)  # once: the real finders find it (and every later import)
        spec = importlib.util.find_spec(fullname)
        if spec is not None and spec.loader is not None:
            spec.loader = _Wrapped(spec.loader)
        return spec


def ready(reader: types.ModuleType) -> None:
    """Make ``reader`` (an ``ocatari.ram`` module) run as with OCAtari's own import: the deferred modules it reaches at
    run time (:data:`USED_AT_RUN_TIME`) are imported now, and OCAtari's modules get their real objects in place of
    the stand-ins bound from them. Called as an environment is built: in the game zygote, so that no host it forks
    pays the import (~0.3 s for scipy's ``optimize``) and a step calls the real function."""
    needed = {module for name, module in USED_AT_RUN_TIME.items() if name in vars(reader)}
    if not needed:
        return
    for module in needed:
        importlib.import_module(module)
    for module in [m for name, m in list(sys.modules.items()) if name.partition(".")[0] == "ocatari"]:
        for name, bound in list(vars(module).items()):
            if isinstance(bound, Forward) and bound._module in needed:
                setattr(module, name, bound.resolve())
            elif isinstance(bound, Deferred) and bound.__name__ in needed:
                setattr(module, name, sys.modules[bound.__name__])


def install() -> None:
    """Wrap the first import of ``ocatari`` in this process (nothing when it is imported already)."""
    if "ocatari" not in sys.modules and not any(isinstance(f, _FirstImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _FirstImport())
