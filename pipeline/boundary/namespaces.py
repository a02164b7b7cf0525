"""The namespaces and the lifetime of the policy zygote and its workers.

One job: move the zygote's children into pid and IPC namespaces of their own, and the zygote into an empty
network namespace (:func:`enter_namespaces`, done once by the zygote; every worker inherits them: no other process
to see, no host IPC, no network at all, not even 127.0.0.1 or abstract Unix sockets); make the namespace's first
process its init, so that nothing in it outlives the zygote (:func:`become_namespace_init`); and tie a process's
life to its parent's (:func:`die_with_parent`).
"""

from __future__ import annotations

import ctypes
import os

from pipeline.boundary.libc import libc

PR_SET_PDEATHSIG = 1
CLONE_NEWNET, CLONE_NEWUSER = 0x40000000, 0x10000000
CLONE_NEWPID, CLONE_NEWIPC = 0x20000000, 0x08000000


def enter_namespaces(offline: bool) -> list[str]:
    """Move this process's future children into new pid and IPC namespaces (and, when ``offline``, this process
    into a new, empty network namespace); the namespaces it could not have, by name. A new user namespace is
    taken when not root (where the distribution allows unprivileged ones).

    After this the process must fork at once (:func:`become_namespace_init`): its first child is pid 1 of the new
    pid namespace, and the process itself can no longer start threads."""
    missing = []
    flags = CLONE_NEWPID | CLONE_NEWIPC | (CLONE_NEWNET if offline else 0)
    if libc.unshare(ctypes.c_int(flags)) == 0:
        return missing
    err = ctypes.get_errno()
    uid, gid = os.geteuid(), os.getegid()
    if libc.unshare(ctypes.c_int(CLONE_NEWUSER | flags)) == 0:
        try:
            for name, line in (("setgroups", "deny"), ("uid_map", f"{uid} {uid} 1"), ("gid_map", f"{gid} {gid} 1")):
                with open(f"/proc/self/{name}", "w") as f:
                    f.write(line)
        except OSError:
            pass  # (mapping root needs CAP_SETFCAP) unmapped ids still reach their files
        return missing
    for name, flag in (("network namespace", CLONE_NEWNET if offline else 0), ("IPC namespace", CLONE_NEWIPC),
                       ("pid namespace", CLONE_NEWPID)):
        if flag and libc.unshare(ctypes.c_int(flag)) != 0:
            missing.append(f"{name} (unshare: {os.strerror(ctypes.get_errno())}; {os.strerror(err)} together)")
    return missing


def become_namespace_init() -> None:
    """In the first child after :func:`enter_namespaces`: die with the process that made the namespace (which
    waits for us). As pid 1 of the namespace, when this process ends the kernel kills every process in it: no
    worker outlives its zygote, whatever it did to its own parent-death signal."""
    libc.prctl(ctypes.c_int(PR_SET_PDEATHSIG), ctypes.c_ulong(9), ctypes.c_ulong(0), ctypes.c_ulong(0),
               ctypes.c_ulong(0))


def die_with_parent(parent_pid: int) -> None:
    """PR_SET_PDEATHSIG SIGKILL; end at once if the parent (``parent_pid``) is already gone."""
    libc.prctl(ctypes.c_int(PR_SET_PDEATHSIG), ctypes.c_ulong(9), ctypes.c_ulong(0), ctypes.c_ulong(0),
               ctypes.c_ulong(0))
    if os.getppid() != parent_pid:
        os._exit(1)
