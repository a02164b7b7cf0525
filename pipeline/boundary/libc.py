"""The C library of this process through ctypes: the one handle the confinement modules make their system calls
with (``syscall``, ``prctl``, ``unshare``, ``mount``, ``umount2``), errno kept so each failure is reported by name.

Linux only, no dependency: ``pipeline/boundary/confine.py`` and its siblings (``landlock``, ``seccomp``, ``mounts``,
``namespaces``) import it.
"""

from __future__ import annotations

import ctypes

libc = ctypes.CDLL(None, use_errno=True)
libc.syscall.restype = ctypes.c_long
libc.prctl.restype = ctypes.c_int
