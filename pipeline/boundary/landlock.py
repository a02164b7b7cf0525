"""Landlock rules of a policy process: what it may read, write and reach, enforced by the kernel.

One job: probe the kernel's Landlock ABI (:func:`landlock_abi`, ``landlock_create_ruleset(NULL, 0, VERSION)``) and
restrict this process for good to a ruleset (:func:`restrict`, of the paths :func:`open_rules` opened): reads only
below the paths of its file view (``pipeline/boundary/view.py``), writes only below its scratch directory (and a
requested Rerun recording directory); from ABI 4 no TCP bind or connect, from ABI 6 no signals to processes
outside it and no abstract Unix sockets. ``pipeline/boundary/confine.py`` applies it with the other layers.
"""

from __future__ import annotations

import ctypes
import os
import stat
import struct

from pipeline.boundary.libc import libc

SYS_LANDLOCK_CREATE_RULESET, SYS_LANDLOCK_ADD_RULE, SYS_LANDLOCK_RESTRICT_SELF = 444, 445, 446
LANDLOCK_CREATE_RULESET_VERSION = 1
LANDLOCK_RULE_PATH_BENEATH = 1
FS_EXECUTE, FS_WRITE_FILE, FS_READ_FILE, FS_READ_DIR = 1, 2, 4, 8
FS_REMOVE_DIR, FS_REMOVE_FILE, FS_MAKE_CHAR, FS_MAKE_DIR, FS_MAKE_REG = 16, 32, 64, 128, 256
FS_MAKE_SOCK, FS_MAKE_FIFO, FS_MAKE_BLOCK, FS_MAKE_SYM, FS_REFER, FS_TRUNCATE, FS_IOCTL_DEV = (
    512, 1024, 2048, 4096, 8192, 16384, 32768)
NET_BIND_TCP, NET_CONNECT_TCP = 1, 2
SCOPE_ABSTRACT_UNIX_SOCKET, SCOPE_SIGNAL = 1, 2
_FILE_RIGHTS = FS_EXECUTE | FS_WRITE_FILE | FS_READ_FILE | FS_TRUNCATE | FS_IOCTL_DEV
READ = FS_EXECUTE | FS_READ_FILE | FS_READ_DIR
WRITE = READ | FS_WRITE_FILE | FS_REMOVE_DIR | FS_REMOVE_FILE | FS_MAKE_DIR | FS_MAKE_REG | FS_MAKE_SYM | \
    FS_REFER | FS_TRUNCATE


def landlock_abi() -> int:
    """The kernel's Landlock ABI version (0: none)."""
    abi = libc.syscall(ctypes.c_long(SYS_LANDLOCK_CREATE_RULESET), None, ctypes.c_size_t(0),
                       ctypes.c_uint32(LANDLOCK_CREATE_RULESET_VERSION))
    return max(0, abi)


def _handled_fs(abi: int) -> int:
    rights = (1 << 13) - 1
    if abi >= 2:
        rights |= FS_REFER
    if abi >= 3:
        rights |= FS_TRUNCATE
    if abi >= 5:
        rights |= FS_IOCTL_DEV
    return rights


Rule = tuple[str, int, int]
"""A Landlock path rule as :func:`restrict` takes it: the path, an ``O_PATH`` descriptor of it, the rights allowed
below it."""


def open_rules(paths: list[str] | tuple[str, ...], rights: int, abi: int) -> list[Rule]:
    """The rules allowing ``rights`` below each of ``paths`` under Landlock ``abi`` (a file gets only the rights
    that apply to files), each path opened (``O_PATH``); a path not on this machine is skipped. The caller closes
    the descriptors."""
    handled = _handled_fs(abi)
    rules: list[Rule] = []
    for path in paths:
        try:
            fd = os.open(path, os.O_PATH | os.O_CLOEXEC)
        except OSError:
            continue  # not on this machine: nothing to allow
        allowed = rights & handled
        if not stat.S_ISDIR(os.fstat(fd).st_mode):
            allowed &= _FILE_RIGHTS
        rules.append((path, fd, allowed))
    return rules


def restrict(rules: list[Rule], abi: int) -> None:
    """Restrict this process for good to ``rules`` (:func:`open_rules`: what it may read, write or list), no TCP,
    no signals out and no abstract Unix sockets where ``abi`` has them. Raises OSError naming the call that
    failed; the rules' descriptors are left to the caller."""
    handled = _handled_fs(abi)
    attr = struct.pack("=QQQ", handled, NET_BIND_TCP | NET_CONNECT_TCP if abi >= 4 else 0,
                       SCOPE_ABSTRACT_UNIX_SOCKET | SCOPE_SIGNAL if abi >= 6 else 0)
    size = 8 if abi < 4 else (16 if abi < 6 else 24)
    buf = ctypes.create_string_buffer(attr[:size], size)
    ruleset = libc.syscall(ctypes.c_long(SYS_LANDLOCK_CREATE_RULESET), buf, ctypes.c_size_t(size),
                           ctypes.c_uint32(0))
    if ruleset < 0:
        raise OSError(ctypes.get_errno(), f"landlock_create_ruleset: {os.strerror(ctypes.get_errno())}")
    try:
        add_rule, beneath, no_flags = libc.syscall, ctypes.c_int(LANDLOCK_RULE_PATH_BENEATH), ctypes.c_uint32(0)
        number, into = ctypes.c_long(SYS_LANDLOCK_ADD_RULE), ctypes.c_int(ruleset)
        for path, fd, allowed in rules:
            rule = ctypes.create_string_buffer(struct.pack("=Qi", allowed, fd), 12)
            if add_rule(number, into, beneath, rule, no_flags) < 0:
                err = ctypes.get_errno()
                raise OSError(err, f"landlock_add_rule({path}): {os.strerror(err)}")
        if libc.syscall(ctypes.c_long(SYS_LANDLOCK_RESTRICT_SELF), ctypes.c_int(ruleset), ctypes.c_uint32(0)) < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"landlock_restrict_self: {os.strerror(err)}")
    finally:
        os.close(ruleset)
