"""Kernel confinement of the process that runs untrusted policy code (Linux; ctypes only, no dependency).

One job: take a freshly forked worker (``pipeline/boundary/zygote.py``), after its environment is built and before any
policy code is loaded, and make the operating system the boundary (:func:`confine`), layer after layer:

- rlimits: address space (a cap above what the worker had), no core files, a file-size cap, few open files
  (set after Landlock), and CPU seconds as a backstop for a worker that ignores its timers;
- every capability dropped (bounding, ambient, effective, permitted, inheritable): a worker running as root
  cannot raise its rlimits back, set the clock, or use any other privilege of root;
- ``PR_SET_NO_NEW_PRIVS``: nothing it executes could gain privileges (and it may not execute anything);
- Landlock (``pipeline/boundary/landlock.py``): reads only what a policy process imports from
  (``pipeline/boundary/view.py``: the standard library, the allowed packages, what its zygote loaded, never the
  emulator, the project's tests, examples or stores); writes only in the episode's scratch directory (and a
  requested Rerun recording directory); no TCP, no signals out, no abstract Unix sockets where the ABI has them.
  The view's paths are opened once by the policy zygote (:func:`prepare_workers`); a worker makes its rules from
  the descriptors it inherited and closes them, whatever happens, before the open-files limit and the policy;
- a seccomp filter (``pipeline/boundary/seccomp.py``): no exec, no processes or threads, no sockets, nothing that
  acts on another process, no host IPC.

What the zygote sets up before its workers exist lives beside it: the namespaces (``pipeline/boundary/namespaces.py``:
pid, IPC and an empty network namespace, and the lifetime of what runs in them) and the filesystem
(``pipeline/boundary/mounts.py``: the minimal root, each worker's scratch tmpfs bounded in bytes and inodes, and
their removal). The C library handle they share is ``pipeline/boundary/libc.py``.

The zygote's probe (``zygote._probe``: this confinement applied in a throwaway child) says which of these the machine
lacks. Nothing degrades silently: the executor refuses to run policy code when a feature is missing unless
``CODEARCADE_ALLOW_WEAK_SANDBOX=1`` is set, and then it warns on every run (see :func:`weak_sandbox_allowed`).
"""

from __future__ import annotations

import ctypes
import os
import platform
import resource
import struct
from dataclasses import dataclass, field

from pipeline.boundary import landlock, seccomp
from pipeline.boundary.libc import libc
from pipeline.boundary.view import read_paths
from pipeline.settings import EpisodeLimits

WEAK_ENV = "CODEARCADE_ALLOW_WEAK_SANDBOX"
"""Set to 1 to run policy code even when a kernel feature of the sandbox is missing (warned on every run)."""


class SandboxUnavailable(ValueError):
    """A kernel feature the sandbox needs is missing (a one-line message saying which and what to do)."""


def weak_sandbox_allowed() -> bool:
    return os.environ.get(WEAK_ENV, "") == "1"


PR_SET_NO_NEW_PRIVS, PR_CAPBSET_DROP, PR_CAP_AMBIENT, PR_CAP_AMBIENT_CLEAR_ALL = 38, 24, 47, 4
SYS_CAPSET, LINUX_CAPABILITY_VERSION_3 = 126, 0x20080522


@dataclass
class Limits:
    """What one worker may use."""

    memory_mb: int | None = EpisodeLimits.memory_limit_mb
    """Address space above what the worker had when confined (None: unlimited)."""
    cpu_s: int | None = None
    """CPU seconds before SIGXCPU/SIGKILL (a backstop; the parent's wall-clock kill comes first)."""
    file_size_mb: int = 64
    open_files: int = 256
    write_paths: list[str] = field(default_factory=list)
    """Directories the worker may write below (its scratch directory, a Rerun recording directory)."""


def confine(limits: Limits, strict: bool = True) -> list[str]:
    """Confine this process for good (see the module docstring). Returns the features that could not be
    applied; with ``strict`` the first failure raises OSError naming it instead."""
    missing: list[str] = []

    def step(name: str, fn) -> None:
        try:
            fn()
        except Exception as exc:  # noqa: BLE001 - reported by name
            if strict:
                raise OSError(f"{name}: {exc}") from None
            missing.append(f"{name} ({exc})")

    def rlimits() -> None:
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        size = limits.file_size_mb * 2**20
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
        if limits.cpu_s:
            used = int(sum(os.times()[:2]))
            resource.setrlimit(resource.RLIMIT_CPU, (used + limits.cpu_s, used + limits.cpu_s + 5))
        if limits.memory_mb:
            with open("/proc/self/statm") as f:
                current = int(f.read().split()[0]) * resource.getpagesize()
            cap = current + limits.memory_mb * 2**20
            resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    def no_new_privs() -> None:
        if libc.prctl(ctypes.c_int(PR_SET_NO_NEW_PRIVS), ctypes.c_ulong(1), ctypes.c_ulong(0), ctypes.c_ulong(0),
                      ctypes.c_ulong(0)) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS) failed")

    def capabilities() -> None:
        # root in the worker would otherwise keep CAP_SYS_RESOURCE (raise its rlimits back), CAP_SYS_TIME, ...
        prctl = libc.prctl
        prctl(ctypes.c_int(PR_CAP_AMBIENT), ctypes.c_ulong(PR_CAP_AMBIENT_CLEAR_ALL), ctypes.c_ulong(0),
              ctypes.c_ulong(0), ctypes.c_ulong(0))
        for cap in range(64):
            if prctl(ctypes.c_int(PR_CAPBSET_DROP), ctypes.c_ulong(cap), ctypes.c_ulong(0), ctypes.c_ulong(0),
                     ctypes.c_ulong(0)) != 0 and ctypes.get_errno() == 22:  # EINVAL: past the last capability
                break
        header = struct.pack("=Ii", LINUX_CAPABILITY_VERSION_3, 0)
        data = bytes(24)  # effective, permitted, inheritable: all empty (two 32-bit words each)
        if libc.syscall(ctypes.c_long(SYS_CAPSET), ctypes.create_string_buffer(header, 8),
                        ctypes.create_string_buffer(data, 24)) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"capset: {os.strerror(err)}")

    def landlock_rules() -> None:
        abi = landlock.landlock_abi()
        if abi < 1:
            raise OSError("Landlock is not enabled in this kernel (needs Linux >= 5.13 with lsm=landlock)")
        opened = [] if _view_rules else _open_view_rules(abi)  # not forked from a zygote that opened them
        opened += landlock.open_rules(limits.write_paths, landlock.WRITE, abi)
        try:
            landlock.restrict(_view_rules + opened, abi)
        finally:
            _close_rules(opened)

    def open_files() -> None:  # after the Landlock rules: their ~220 descriptors are closed by then
        resource.setrlimit(resource.RLIMIT_NOFILE, (limits.open_files, limits.open_files))

    def seccomp_filter() -> None:
        if platform.machine() != "x86_64":
            raise OSError(f"the seccomp filter is written for x86_64, not {platform.machine()}")
        seccomp.install(seccomp.seccomp_program(os.getpid()))

    try:
        step("rlimits", rlimits)
        step("capabilities", capabilities)
        step("no_new_privs", no_new_privs)
        step("landlock", landlock_rules)
    finally:  # whatever happened, the view's descriptors are not the policy's
        forget_view_rules()
    step("open files", open_files)
    step("seccomp", seccomp_filter)
    return missing


_view_rules: list[landlock.Rule] = []
"""The Landlock rules of the file view, opened by the policy zygote (:func:`prepare_workers`) and inherited by every
worker it forks, which closes them once confined (:func:`forget_view_rules`)."""


def _open_view_rules(abi: int) -> list[landlock.Rule]:
    read, list_only = read_paths()
    return landlock.open_rules(list_only, landlock.FS_READ_DIR, abi) + landlock.open_rules(read, landlock.READ, abi)


def _close_rules(rules: list[landlock.Rule]) -> None:
    for _path, fd, _allowed in rules:
        os.close(fd)


def prepare_workers() -> None:
    """What every worker's confinement needs and no worker changes, done once by the policy zygote (once its
    filesystem view is in place) for the workers it forks to inherit: the file view's Landlock rules opened
    (:func:`view_rule_descriptors`, which a worker keeps open until it is confined), the seccomp filter assembled.

    A worker then adds ~220 rules from descriptors it inherited instead of opening, checking and closing each path
    again, and writes its pid into the filter instead of assembling it: its confinement took 3.5 ms, now 2.5 (on
    the first episode's critical path: the host waits for its policy process)."""
    global _view_rules
    abi = landlock.landlock_abi()
    if abi >= 1 and not _view_rules:
        _view_rules = _open_view_rules(abi)
    if platform.machine() == "x86_64":
        seccomp.seccomp_program(0)  # assembles the template the workers inherit


def view_rule_descriptors() -> list[int]:
    """The descriptors of the view's rules this process holds (:func:`prepare_workers`), which a worker keeps open
    until it is confined."""
    return [fd for _path, fd, _allowed in _view_rules]


def forget_view_rules() -> None:
    """Close this process's descriptors of the view's rules (a worker, once confined or failing to be)."""
    global _view_rules
    rules, _view_rules = _view_rules, []
    _close_rules(rules)
