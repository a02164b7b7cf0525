"""The policy process's file view: the paths it may read, derived from what it runs.

One job: say which files a policy process may read. ``pipeline/boundary/confine.py`` turns the answer into
Landlock's read rules (``landlock.py``: what may be opened) and ``mounts.minimal_root``'s read-only mounts (what
exists at all).

A policy process reads a file only to import a module: the policy's own text comes over its socket, and every
module its zygote preloaded (``pipeline/boundary/preload.py``) is in memory already. What it may still import is a
module of the import allow-list the zygote did not load (``statistics``, ``fractions``, numpy's lazily loaded
``numpy.fft`` or ``numpy.polynomial``) or one that a preloaded package imports lazily. So it may read:

- **Python's standard library** (its ``lib-dynload`` too), but :data:`STDLIB_LEFT_OUT`: the base interpreter's
  own ``site-packages``, CPython's test suite, the GUI;
- **the allow-list's packages** outside the standard library (``tracing.sandbox.ALLOWED_MODULES``: numpy) and
  their vendored native libraries (``numpy.libs``);
- **what the policy zygote loaded** before it forks, each top-level package's directory: the project's own
  ``pipeline``, ``tracing`` and ``games`` (validation looks the game up), pyarrow (the node rows), radon (code
  metrics) and what they import;
- **the files it has mapped** (the interpreter and its shared libraries: a library that a lazily loaded extension
  needs is found among the loaded ones by its name), ``/etc/ld.so.cache``, ``/etc/localtime``, ``/dev/null``,
  ``/dev/urandom``.

Never the emulator stack (:data:`EMULATOR_PACKAGES`, cut out wherever it lies: :func:`carve`), and nothing else:
not the project's tests, examples, fixtures or stores, not the project folder's listing, not the rest of the
virtualenv or of /usr. ``bench/file_view.py`` counts the files a policy process can read; docs/sandbox.md quotes
the figures.
"""

from __future__ import annotations

import functools
import glob
import os
import sys
import sysconfig

EMULATOR_PACKAGES = ("ale_py", "ocatari", "gymnasium")
"""What a policy process may never read (nor so import): the emulator, its ROMs, the object extractors and the
environment API. The game runs in the host process (``pipeline/play``); the policy sees observations only."""

STDLIB_LEFT_OUT = ("site-packages", "dist-packages", "test", "idlelib", "tkinter", "turtledemo", "ensurepip")
"""Folders of the standard library's directory a policy process never needs: the base interpreter's third-party
packages (not on a virtualenv's path), CPython's own test suite (3,760 files of the 7,700), the GUI and the
bundled pip wheels (it has no display and runs no installer)."""

SYSTEM_FILES = ("/etc/ld.so.cache", "/etc/localtime", "/dev/null", "/dev/urandom")
"""The dynamic loader's cache (a library loaded by name), the local time zone, and the two devices."""


@functools.cache
def read_paths() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(paths readable below, directories that may only be listed) for a policy process (see the module
    docstring). The folders :func:`carve` opened up (the standard library's, its site-packages cut out) may be
    listed: Python's import system lists a ``sys.path`` folder before it finds a module there.

    Computed once per process, from the modules and mappings it holds when first called: the policy zygote calls it
    after its preload, for its filesystem view, and every worker it forks inherits the answer (walking the
    directories again cost each worker several ms). Called elsewhere it answers for that process's modules."""
    stdlib = stdlib_paths()
    read = stdlib + package_paths(allowed_packages()) + package_paths(loaded_packages()) + mapped_files()
    read += [path for path in SYSTEM_FILES if os.path.exists(path)]
    forbidden = emulator_paths() + left_out(stdlib)
    opened: list[str] = []
    readable = outermost(carve(read, forbidden, opened))
    return tuple(readable), tuple(sorted(set(opened)))


def stdlib_paths() -> list[str]:
    """The standard library's directory and its ``lib-dynload`` (inside it, or beside it on ``sys.path``)."""
    stdlib = os.path.realpath(sysconfig.get_paths()["stdlib"])
    dynload = [os.path.realpath(p) for p in sys.path if os.path.basename(p.rstrip(os.sep)) == "lib-dynload"]
    return [stdlib] + [p for p in dynload if os.path.isdir(p)]


def left_out(stdlib: list[str]) -> list[str]:
    """The folders of :data:`STDLIB_LEFT_OUT` in the standard library's directory."""
    return [os.path.join(root, name) for root in stdlib for name in STDLIB_LEFT_OUT
            if os.path.isdir(os.path.join(root, name))]


def allowed_packages() -> list[str]:
    """The import allow-list's top-level names (policy code imports them; some only after the fork)."""
    from tracing.sandbox import ALLOWED_MODULES

    return sorted(name for name in ALLOWED_MODULES if name != "__future__")


def loaded_packages() -> list[str]:
    """The top-level modules this process has loaded (in the policy zygote: what its tasks import)."""
    return sorted(name for name in list(sys.modules) if "." not in name and name != "__main__")


def package_paths(names: list[str]) -> list[str]:
    """Where the top-level modules ``names`` are installed (a package's directories, a module's file, and a
    ``NAME.libs`` folder of vendored native libraries beside them), found without importing them; built-in and
    frozen modules have no files."""
    import importlib.util

    found: list[str] = []
    for name in names:
        module = sys.modules.get(name)
        spec = getattr(module, "__spec__", None) if module is not None else None
        if spec is None:
            try:
                spec = importlib.util.find_spec(name)
            except (ImportError, ValueError):
                spec = None
        if spec is None:
            continue
        locations = list(spec.submodule_search_locations or [])
        if not locations and spec.has_location and spec.origin:
            locations = [spec.origin]
        for location in locations:
            location = os.path.realpath(location)
            if not os.path.exists(location):
                continue
            found.append(location)
            libs = os.path.join(os.path.dirname(location), f"{name}.libs")
            if os.path.isdir(libs):
                found.append(libs)
    return found


def mapped_files() -> list[str]:
    """The files this process has mapped (the interpreter, its shared libraries, extension modules)."""
    found = set()
    try:
        with open("/proc/self/maps") as maps:
            for line in maps:
                fields = line.split(maxsplit=5)
                if len(fields) == 6 and fields[5].startswith("/"):
                    path = fields[5].rstrip("\n")
                    if not path.endswith(" (deleted)") and os.path.isfile(path):
                        found.add(os.path.realpath(path))
    except OSError:
        pass
    return sorted(found)


def emulator_paths() -> list[str]:
    """Where :data:`EMULATOR_PACKAGES` are installed (their package directories, native libraries and metadata),
    found without importing them."""
    import importlib.util

    found: list[str] = []
    for name in EMULATOR_PACKAGES:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        locations = list(spec.submodule_search_locations or []) if spec is not None else []
        if spec is not None and spec.origin and not locations:
            locations = [spec.origin]
        for location in locations:
            location = os.path.realpath(location)
            found.append(location)
            parent = os.path.dirname(location)
            found += glob.glob(os.path.join(parent, f"{name}.libs"))
            found += glob.glob(os.path.join(parent, f"{name}-*.dist-info"))
    return sorted(set(found))


def carve(allowed: list[str], forbidden: list[str], opened: list[str] | None = None) -> list[str]:
    """``allowed`` with every path in ``forbidden`` taken out: an allowed directory that contains a forbidden path
    is replaced by its entries (and so on down the way to it), all but the forbidden one; each directory so
    replaced is appended to ``opened``. Landlock only ever adds rights, so what it must not grant has to be left
    out of the rules."""
    forbidden = [os.path.realpath(f) for f in forbidden]
    out: list[str] = []

    def add(path: str) -> None:
        real = os.path.realpath(path)
        if any(real == f or real.startswith(f + os.sep) for f in forbidden):
            return
        inside = [f for f in forbidden if f.startswith(real.rstrip(os.sep) + os.sep)]
        if not inside or not os.path.isdir(real):
            out.append(path)
            return
        try:
            entries = sorted(os.listdir(real))
        except OSError:
            return
        if opened is not None:
            opened.append(real)
        for entry in entries:
            add(os.path.join(real, entry))

    for path in allowed:
        add(path)
    return sorted(set(out))


def outermost(paths: list[str]) -> list[str]:
    """``paths`` without those that lie below another of them (a rule or a mount fewer: each costs every worker)."""
    by_real = {os.path.realpath(p): p for p in paths}
    kept: set[str] = set()
    for resolved in sorted(by_real, key=len):
        above = os.path.dirname(resolved)
        while above not in kept and above != os.path.dirname(above):
            above = os.path.dirname(above)
        if above not in kept:
            kept.add(resolved)
    return sorted(by_real[r] for r in kept)
