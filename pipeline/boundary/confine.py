"""Kernel confinement of the process that runs untrusted policy code (Linux; ctypes only, no dependency).

One job: take a freshly forked worker (``pipeline/boundary/zygote.py``), after its environment is built and before any
policy code is loaded, and make the operating system the boundary:

- ``PR_SET_NO_NEW_PRIVS``: nothing it executes could gain privileges (and it may not execute anything);
- a network namespace of its own with no interface up (:func:`enter_namespaces`, done once by the
  zygote; every worker inherits it): no network at all, not even 127.0.0.1 or abstract Unix sockets;
- a scratch directory per worker, a tmpfs of its own bounded in bytes and in inodes (:func:`worker_scratch`),
  mounted in the zygote's own mount namespace (:func:`scratch_tmpfs`): invisible to the rest of the machine, and
  gone as a whole when the zygote detaches it (:func:`unmount`), nothing walked;
- Landlock (ABI probed with ``landlock_create_ruleset(NULL, 0, VERSION)``): reads only what a policy process
  imports from (``pipeline/boundary/view.py``: the standard library, the allowed packages, what its zygote loaded,
  never the emulator, the project's tests, examples or stores); writes only
  in the episode's scratch directory (and a requested Rerun recording directory); from ABI 4 no TCP bind or
  connect, from ABI 6 no signals to processes outside the worker and no abstract Unix sockets;
- a seccomp filter (classic BPF written here): ``execve``/``execveat``, ``fork``/``vfork``, ``clone`` without
  ``CLONE_THREAD`` (``clone3`` answers ENOSYS so glibc falls back to ``clone``), socket creation, ``ptrace``,
  ``process_vm_*``, ``mknod``, ``mount``/``unshare``/``setns`` and friends, ``io_uring``, ``bpf``, uid
  changes, and ``kill``/``tgkill`` to any process but itself are refused with EPERM;
- rlimits: address space (a cap above what the worker had), no core files, a file-size cap, few open files,
  and CPU seconds as a backstop for a worker that ignores its timers;
- every capability dropped (bounding, ambient, effective, permitted, inheritable): a worker running as root
  cannot raise its rlimits back, set the clock, or use any other privilege of root.

:func:`probe` says which of these the machine lacks. Nothing degrades silently: the executor refuses to run
policy code when a feature is missing unless ``CODEARCADE_ALLOW_WEAK_SANDBOX=1`` is set, and then it warns on
every run (see :func:`weak_sandbox_allowed`).
"""

from __future__ import annotations

import ctypes
import os
import platform
import resource
import struct
from dataclasses import dataclass, field
from typing import Any

from pipeline.boundary.view import EMULATOR_PACKAGES, carve, read_paths  # noqa: F401 (the view's API, here too)
from pipeline.settings import EpisodeLimits

WEAK_ENV = "CODEARCADE_ALLOW_WEAK_SANDBOX"
"""Set to 1 to run policy code even when a kernel feature of the sandbox is missing (warned on every run)."""


class SandboxUnavailable(ValueError):
    """A kernel feature the sandbox needs is missing (a one-line message saying which and what to do)."""


def weak_sandbox_allowed() -> bool:
    return os.environ.get(WEAK_ENV, "") == "1"


_libc = ctypes.CDLL(None, use_errno=True)
_libc.syscall.restype = ctypes.c_long
_libc.prctl.restype = ctypes.c_int

PR_SET_PDEATHSIG, PR_SET_NO_NEW_PRIVS, PR_CAPBSET_DROP, PR_CAP_AMBIENT, PR_CAP_AMBIENT_CLEAR_ALL = 1, 38, 24, 47, 4
SYS_CAPSET, LINUX_CAPABILITY_VERSION_3 = 126, 0x20080522
CLONE_NEWNET, CLONE_THREAD = 0x40000000, 0x00010000

# ------------------------------------------------------------------------------------------------ landlock

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
    abi = _libc.syscall(ctypes.c_long(SYS_LANDLOCK_CREATE_RULESET), None, ctypes.c_size_t(0),
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


def _landlock(read: list[str], write: list[str], list_only: list[str], abi: int) -> None:
    handled = _handled_fs(abi)
    attr = struct.pack("=QQQ", handled, NET_BIND_TCP | NET_CONNECT_TCP if abi >= 4 else 0,
                       SCOPE_ABSTRACT_UNIX_SOCKET | SCOPE_SIGNAL if abi >= 6 else 0)
    size = 8 if abi < 4 else (16 if abi < 6 else 24)
    buf = ctypes.create_string_buffer(attr[:size], size)
    ruleset = _libc.syscall(ctypes.c_long(SYS_LANDLOCK_CREATE_RULESET), buf, ctypes.c_size_t(size),
                            ctypes.c_uint32(0))
    if ruleset < 0:
        raise OSError(ctypes.get_errno(), f"landlock_create_ruleset: {os.strerror(ctypes.get_errno())}")
    try:
        for paths, rights in ((list_only, FS_READ_DIR), (read, READ), (write, WRITE)):
            for path in paths:
                try:
                    fd = os.open(path, os.O_PATH | os.O_CLOEXEC)
                except OSError:
                    continue  # not on this machine: nothing to allow
                try:
                    allowed = rights & handled
                    if not os.path.isdir(path):
                        allowed &= _FILE_RIGHTS
                    rule = ctypes.create_string_buffer(struct.pack("=Qi", allowed, fd), 12)
                    if _libc.syscall(ctypes.c_long(SYS_LANDLOCK_ADD_RULE), ctypes.c_int(ruleset),
                                     ctypes.c_int(LANDLOCK_RULE_PATH_BENEATH), rule, ctypes.c_uint32(0)) < 0:
                        err = ctypes.get_errno()
                        raise OSError(err, f"landlock_add_rule({path}): {os.strerror(err)}")
                finally:
                    os.close(fd)
        if _libc.syscall(ctypes.c_long(SYS_LANDLOCK_RESTRICT_SELF), ctypes.c_int(ruleset), ctypes.c_uint32(0)) < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"landlock_restrict_self: {os.strerror(err)}")
    finally:
        os.close(ruleset)


# ------------------------------------------------------------------------------------------------- seccomp

AUDIT_ARCH_X86_64 = 0xC000003E
SECCOMP_SET_MODE_FILTER, SECCOMP_FILTER_FLAG_TSYNC = 1, 1
SYS_SECCOMP = 317
RET_KILL_PROCESS, RET_ALLOW, RET_ERRNO = 0x80000000, 0x7FFF0000, 0x00050000
EPERM, ENOSYS = 1, 38
_LD_ABS_W, _JEQ, _JSET, _RET = 0x20, 0x15, 0x45, 0x06

# x86_64 syscall numbers refused outright (EPERM)
DENIED_SYSCALLS = {
    "execve": 59, "execveat": 322, "fork": 57, "vfork": 58, "ptrace": 101, "process_vm_readv": 310,
    "process_vm_writev": 311, "process_madvise": 440, "process_mrelease": 448, "mknod": 133, "mknodat": 259,
    "mount": 165, "umount2": 166, "unshare": 272, "setns": 308, "pivot_root": 155, "chroot": 161, "socket": 41,
    "connect": 42, "bind": 49, "listen": 50, "accept": 43, "accept4": 288, "tkill": 200,
    "rt_sigqueueinfo": 129, "rt_tgsigqueueinfo": 297, "pidfd_open": 434, "pidfd_send_signal": 424,
    "pidfd_getfd": 438, "kcmp": 312, "bpf": 321, "perf_event_open": 298, "userfaultfd": 323, "keyctl": 250,
    "add_key": 248, "request_key": 249, "io_uring_setup": 425, "io_uring_enter": 426,
    "io_uring_register": 427, "open_by_handle_at": 304, "name_to_handle_at": 303, "open_tree": 428,
    "move_mount": 429, "fsopen": 430, "fsconfig": 431, "fsmount": 432, "fspick": 433, "mount_setattr": 442,
    "kexec_load": 246, "kexec_file_load": 320, "init_module": 175, "finit_module": 313, "delete_module": 176,
    "iopl": 172, "ioperm": 173, "swapon": 167, "swapoff": 168, "reboot": 169, "personality": 135,
    "setuid": 105, "setgid": 106, "setreuid": 113, "setregid": 114, "setresuid": 117, "setresgid": 119,
    "setgroups": 116, "setfsuid": 122, "setfsgid": 123, "acct": 163, "quotactl": 179, "quotactl_fd": 443,
    "syslog": 103, "settimeofday": 164, "clock_settime": 227, "adjtimex": 159, "clock_adjtime": 305,
    "sethostname": 170, "setdomainname": 171, "vhangup": 153,
    # calls that act on another process and have no harmless use here (migrate or inspect its memory,
    # change its I/O priority or process group)
    "migrate_pages": 256, "move_pages": 279, "ioprio_set": 251, "ioprio_get": 252, "setpgid": 109,
    # host IPC and memory the address-space limit does not count (System V, POSIX message queues, memfds)
    "shmget": 29, "shmat": 30, "shmctl": 31, "shmdt": 67, "semget": 64, "semop": 65, "semctl": 66,
    "semtimedop": 220, "msgget": 68, "msgsnd": 69, "msgrcv": 70, "msgctl": 71, "mq_open": 240,
    "mq_unlink": 241, "mq_timedsend": 242, "mq_timedreceive": 243, "mq_notify": 244, "mq_getsetattr": 245,
    "memfd_create": 319, "memfd_secret": 447,
    # watching files other processes touch
    "inotify_init": 253, "inotify_init1": 294, "fanotify_init": 300,
}
SYS_CLONE, SYS_CLONE3, SYS_KILL, SYS_TGKILL, SYS_PRCTL = 56, 435, 62, 234, 157
SELF_ONLY_SYSCALLS = {
    # name: (number, index of the argument that names the target process); allowed only when that argument is
    # 0 (the caller) or the caller's own pid: the family of calls that act on a process by its pid
    "sched_setaffinity": (203, 0), "sched_getaffinity": (204, 0), "sched_setscheduler": (144, 0),
    "sched_setparam": (142, 0), "sched_getparam": (143, 0), "sched_getscheduler": (145, 0),
    "sched_setattr": (314, 0), "sched_getattr": (315, 0), "sched_rr_get_interval": (148, 0),
    "prlimit64": (302, 0), "getpgid": (121, 0), "getsid": (124, 0), "get_robust_list": (274, 0),
}
PRIORITY_SYSCALLS = {"getpriority": 140, "setpriority": 141}
"""(which, who): allowed for PRIO_PROCESS (0) of the caller only (who 0 or its own pid)."""
PR_SET_PDEATHSIG_OPTION = 1


class _Bpf:
    """A classic BPF program with symbolic jump targets (offsets are counted when it is assembled)."""

    def __init__(self) -> None:
        self.code: list[tuple[int, Any, Any, int]] = []
        self.labels: dict[str, int] = {}

    def ld(self, offset: int) -> None:
        self.code.append((_LD_ABS_W, 0, 0, offset))

    def jeq(self, k: int, jt: Any = 0, jf: Any = 0) -> None:
        self.code.append((_JEQ, jt, jf, k))

    def ret(self, k: int) -> None:
        self.code.append((_RET, 0, 0, k))

    def label(self, name: str) -> None:
        self.labels[name] = len(self.code)

    def assemble(self) -> bytes:
        out = []
        for i, (code, jt, jf, k) in enumerate(self.code):
            jt, jf = (self.labels[j] - i - 1 if isinstance(j, str) else j for j in (jt, jf))
            if not (0 <= jt < 256 and 0 <= jf < 256):
                raise ValueError("a BPF jump out of range")
            out.append(_insn(code, jt, jf, k))
        return b"".join(out)


def _insn(code: int, jt: int, jf: int, k: int) -> bytes:
    return struct.pack("=HBBI", code, jt, jf, k & 0xFFFFFFFF)


def seccomp_program(own_pid: int) -> bytes:
    """The BPF filter (x86_64): see the module docstring; ``own_pid`` is the one process the calls that name a
    process may target."""
    def arg(i: int) -> int:  # offsetof(struct seccomp_data, args[i]), low 32 bits (little-endian): a pid_t
        return 16 + 8 * i

    deny, allow = RET_ERRNO | EPERM, RET_ALLOW
    p = _Bpf()
    p.ld(4)  # arch
    p.jeq(AUDIT_ARCH_X86_64, 1, 0)
    p.ret(RET_KILL_PROCESS)
    p.ld(0)  # syscall number
    p.code.append((0x35, 0, 1, 0x40000000))  # jge: the x32 ABI
    p.ret(deny)
    for nr in sorted(DENIED_SYSCALLS.values()):
        p.jeq(nr, 0, 1)
        p.ret(deny)
    p.jeq(SYS_CLONE3, 0, 1)
    p.ret(RET_ERRNO | ENOSYS)  # glibc then falls back to clone, refused below
    p.jeq(SYS_CLONE, 0, 1)
    p.ret(deny)  # no processes and no threads: the policy process is one thread, whatever it imports
    # the calls that name a process: the caller only
    for n, (nr, index) in enumerate(sorted(SELF_ONLY_SYSCALLS.values())):
        p.jeq(nr, 0, f"next{n}")
        p.ld(arg(index))
        p.jeq(0, "allow", 0)
        p.jeq(own_pid, "allow", "deny")
        p.label(f"next{n}")
        p.ld(0)
    for nr, pid_arg, zero_ok in ((SYS_KILL, 0, False), (SYS_TGKILL, 0, False)):  # kill(0) is the process group
        p.jeq(nr, 0, f"after{nr}")
        p.ld(arg(pid_arg))
        p.jeq(own_pid, "allow", "deny")
        p.label(f"after{nr}")
        p.ld(0)
    for nr in sorted(PRIORITY_SYSCALLS.values()):
        p.jeq(nr, 0, f"after{nr}")
        p.ld(arg(0))
        p.jeq(0, 0, "deny")  # PRIO_PROCESS; never a process group or a user's processes
        p.ld(arg(1))
        p.jeq(0, "allow", 0)
        p.jeq(own_pid, "allow", "deny")
        p.label(f"after{nr}")
        p.ld(0)
    p.jeq(SYS_PRCTL, 0, "allow")
    p.ld(arg(0))
    p.jeq(PR_SET_PDEATHSIG_OPTION, "deny", "allow")  # the parent-death signal stays as the zygote set it
    p.label("deny")
    p.ret(deny)
    p.label("allow")
    p.ret(allow)
    return p.assemble()


def _seccomp(program: bytes) -> None:
    n = len(program) // 8
    filt = ctypes.create_string_buffer(program, len(program))

    class SockFprog(ctypes.Structure):
        _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]

    prog = SockFprog(n, ctypes.addressof(filt))
    if _libc.syscall(ctypes.c_long(SYS_SECCOMP), ctypes.c_uint(SECCOMP_SET_MODE_FILTER),
                     ctypes.c_uint(SECCOMP_FILTER_FLAG_TSYNC), ctypes.byref(prog)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"seccomp(SET_MODE_FILTER): {os.strerror(err)}")


# ------------------------------------------------------------------------------------------ the whole thing


CLONE_NEWUSER, CLONE_NEWNS = 0x10000000, 0x00020000
MS_NOSUID, MS_NODEV, MS_NOEXEC, MS_REC, MS_PRIVATE = 2, 4, 8, 16384, 1 << 18
SCRATCH_MB = 16
"""Bytes of one worker's scratch tmpfs (:func:`worker_scratch`), in MiB: each policy process has its own."""
SCRATCH_INODES = 2_048
"""Inodes of one worker's scratch tmpfs (``nr_inodes``): files, directories and links together, its root included.
Without it a tmpfs gets the kernel's default (half the machine's pages: ~3.1M on a 24 GiB machine), and 300,000 empty
files in a 64 MiB scratch held ~300 MB of kernel memory (inodes, dentries) that no RSS or address-space limit counts;
at this cap it is ~2 MB. It bounds a directory's depth too (each level is an inode: the kernel has no depth
limit of its own for a tmpfs; ``PATH_MAX`` bounds one path, not a chain of ``chdir``s)."""
BASE_MB, BASE_INODES = 4, 8_192
"""The zygote's own tmpfs (:func:`scratch_tmpfs`), which holds only the workers' mount points (one inode each,
removed with the worker) and the minimal root's mount point: workers never write in it."""


def scratch_tmpfs(path: str, size_mb: int = BASE_MB, inodes: int = BASE_INODES) -> None:
    """Mount a tmpfs of ``size_mb`` and ``inodes`` over ``path`` in a mount namespace of this process's own (after
    :func:`enter_namespaces`, which provides the user namespace when not root): it holds each worker's scratch
    mount point (:func:`worker_scratch`), and it is gone, with every worker's tmpfs, when this process ends.
    ``path`` is this process's working directory again."""
    if _libc.unshare(ctypes.c_int(CLONE_NEWNS)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"unshare(CLONE_NEWNS): {os.strerror(err)}")
    if _libc.mount(b"none", b"/", None, ctypes.c_ulong(MS_REC | MS_PRIVATE), None) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount(/, MS_PRIVATE): {os.strerror(err)}")
    options = f"size={size_mb}m,nr_inodes={inodes},mode=0700".encode()
    if _libc.mount(b"tmpfs", os.fsencode(path), b"tmpfs", ctypes.c_ulong(MS_NOSUID | MS_NODEV | MS_NOEXEC),
                   options) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount tmpfs on {path}: {os.strerror(err)}")
    os.chdir(path)


def worker_scratch(path: str, size_mb: int = SCRATCH_MB, inodes: int = SCRATCH_INODES) -> None:
    """Mount a tmpfs of its own over ``path``, a worker's scratch directory (an empty directory on the zygote's
    tmpfs), in the worker before it is confined: what its policy can write there is bounded in bytes (``size_mb``)
    and in inodes (``inodes``, hence in depth), and none of it needs walking to be removed: the zygote detaches the
    mount when the worker has ended (:func:`unmount`) and the kernel frees it whole."""
    options = f"size={size_mb}m,nr_inodes={inodes},mode=0700".encode()
    if _libc.mount(b"tmpfs", os.fsencode(path), b"tmpfs", ctypes.c_ulong(MS_NOSUID | MS_NODEV | MS_NOEXEC),
                   options) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount a scratch tmpfs on {path}: {os.strerror(err)}")


MS_RDONLY, MS_REMOUNT, MS_BIND = 1, 32, 4096
SYS_PIVOT_ROOT = 155


def _mount(source: str | None, target: str, fstype: str | None, flags: int, data: str | None = None) -> None:
    if _libc.mount(None if source is None else os.fsencode(source), os.fsencode(target),
                   None if fstype is None else fstype.encode(), ctypes.c_ulong(flags),
                   None if data is None else data.encode()) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount {source or fstype} on {target}: {os.strerror(err)}")


def minimal_root(read: list[str], writable: list[str], devices: list[str]) -> None:
    """Make this process's root a small tmpfs that holds only ``read`` (bound read-only), ``writable`` (bound
    read-write: the scratch directories), ``devices`` (``/dev/null``, ``/dev/urandom``) and a ``/proc`` of this pid
    namespace, each at its own path, then pivot into it (after :func:`scratch_tmpfs`: this process's own mount
    namespace). Landlock decides what may be read or written; this decides what exists at all: ``stat()``,
    which Landlock does not cover, finds nothing else (not a user's files, not another store, not the emulator).
    Every child inherits the view."""
    root = os.path.join(writable[0], ".root")
    os.makedirs(root, exist_ok=True)
    _mount("tmpfs", root, "tmpfs", MS_NOSUID | MS_NODEV, "size=4m,mode=0755")

    def place(path: str, is_dir: bool) -> str:
        target = root + path
        os.makedirs(target if is_dir else os.path.dirname(target), exist_ok=True)
        if not is_dir and not os.path.exists(target):
            open(target, "wb").close()
        return target

    links: dict[str, str] = {}
    for path in read + writable + devices:
        probe = path
        while probe not in ("/", ""):  # a symlink on the way (Debian's /lib -> usr/lib) is made a symlink inside
            if os.path.islink(probe) and probe not in links:
                links[probe] = os.readlink(probe)
            probe = os.path.dirname(probe)
    seen = set()
    for path in read + writable + devices:
        real = os.path.realpath(path)
        if real in seen or not os.path.exists(real):
            continue
        seen.add(real)
        target = place(real, os.path.isdir(real))
        _mount(real, target, None, MS_BIND)  # not recursive: the scratch tmpfs holds this very root
        flags = MS_BIND | MS_REMOUNT | MS_NOSUID
        if path not in devices:
            flags |= MS_NODEV
        if path in read:
            flags |= MS_RDONLY
        _mount(None, target, None, flags)
    for link, value in links.items():
        target = root + link
        if not os.path.lexists(target):
            os.makedirs(os.path.dirname(target), exist_ok=True)
            os.symlink(value, target)
    os.makedirs(root + "/proc", exist_ok=True)
    _mount("proc", root + "/proc", "proc", MS_NOSUID | MS_NODEV | MS_NOEXEC)
    old = root + "/.old"
    os.makedirs(old, exist_ok=True)
    if _libc.syscall(ctypes.c_long(SYS_PIVOT_ROOT), os.fsencode(root), os.fsencode(old)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"pivot_root: {os.strerror(err)}")
    os.chdir("/")
    if _libc.umount2(b"/.old", ctypes.c_int(2)) != 0:  # MNT_DETACH
        err = ctypes.get_errno()
        raise OSError(err, f"umount /.old: {os.strerror(err)}")
    os.rmdir("/.old")
    _mount(None, "/", None, MS_REMOUNT | MS_BIND | MS_RDONLY | MS_NOSUID | MS_NODEV)


MNT_DETACH, UMOUNT_NOFOLLOW = 2, 8


def unmount(path: str) -> bool:
    """Detach the tmpfs mounted on ``path`` (:func:`scratch_tmpfs`, :func:`worker_scratch`) and every mount below it,
    however full or deep: the kernel frees it when nothing holds it any more. Whether something was detached;
    never raises."""
    try:
        return _libc.umount2(os.fsencode(path), ctypes.c_int(MNT_DETACH | UMOUNT_NOFOLLOW)) == 0
    except Exception:  # noqa: BLE001 - a path that cannot be encoded: nothing mounted there by us
        return False


def remove_tree(path: str) -> bool:
    """Remove ``path`` and everything below it, however deep, without recursion and without ever raising (what a
    policy left behind must not be able to end the process that cleans up: ``shutil.rmtree`` recurses on Python
    3.11, and a directory ~1,500 levels deep raised ``RecursionError``, which ``ignore_errors`` does not catch).
    Directories are walked by descriptor (``openat``, never a path longer than one name, symlinks never followed),
    one directory open at a time; the names of the directories still to visit are held in lists. Whether ``path``
    is gone. For a scratch without a tmpfs of its own (a weak sandbox); a worker's tmpfs is detached instead."""
    flags = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        try:
            os.unlink(path)  # a file or a link
            return True
        except FileNotFoundError:
            return True
        except (IsADirectoryError, PermissionError):  # Linux answers EISDIR for a directory
            pass
        fd = os.open(path, flags)
        try:
            def scan(fd: int) -> list[str]:
                """Unlink what is not a directory in ``fd``; its subdirectories' names."""
                subdirectories = []
                with os.scandir(fd) as entries:
                    for entry in entries:
                        if entry.is_dir(follow_symlinks=False):
                            subdirectories.append(entry.name)
                        else:
                            try:
                                os.unlink(entry.name, dir_fd=fd)
                            except FileNotFoundError:
                                pass
                return subdirectories

            stack = [scan(fd)]  # per level below ``path``: the subdirectories of that level still to remove
            names: list[str] = []  # the name of each level below ``path`` we are in
            while stack:
                if stack[-1]:
                    name = stack[-1].pop()
                    child = os.open(name, flags, dir_fd=fd)
                    os.close(fd)
                    fd = child
                    names.append(name)
                    stack.append(scan(fd))
                    continue
                stack.pop()
                if not names:
                    break
                parent = os.open("..", flags, dir_fd=fd)
                os.close(fd)
                fd = parent
                os.rmdir(names.pop(), dir_fd=fd)
        finally:
            os.close(fd)
        os.rmdir(path)
        return True
    except Exception:  # noqa: BLE001 - whatever is left stays; the caller goes on
        return False


CLONE_NEWPID, CLONE_NEWIPC = 0x20000000, 0x08000000


def enter_namespaces(offline: bool) -> list[str]:
    """Move this process's future children into new pid and IPC namespaces (and, when ``offline``, this process
    into a new, empty network namespace); the namespaces it could not have, by name. A new user namespace is
    taken when not root (where the distribution allows unprivileged ones).

    After this the process must fork at once (:func:`become_namespace_init`): its first child is pid 1 of the new
    pid namespace, and the process itself can no longer start threads."""
    missing = []
    flags = CLONE_NEWPID | CLONE_NEWIPC | (CLONE_NEWNET if offline else 0)
    if _libc.unshare(ctypes.c_int(flags)) == 0:
        return missing
    err = ctypes.get_errno()
    uid, gid = os.geteuid(), os.getegid()
    if _libc.unshare(ctypes.c_int(CLONE_NEWUSER | flags)) == 0:
        try:
            for name, line in (("setgroups", "deny"), ("uid_map", f"{uid} {uid} 1"), ("gid_map", f"{gid} {gid} 1")):
                with open(f"/proc/self/{name}", "w") as f:
                    f.write(line)
        except OSError:
            pass  # (mapping root needs CAP_SETFCAP) unmapped ids still reach their files
        return missing
    for name, flag in (("network namespace", CLONE_NEWNET if offline else 0), ("IPC namespace", CLONE_NEWIPC),
                       ("pid namespace", CLONE_NEWPID)):
        if flag and _libc.unshare(ctypes.c_int(flag)) != 0:
            missing.append(f"{name} (unshare: {os.strerror(ctypes.get_errno())}; {os.strerror(err)} together)")
    return missing


def become_namespace_init() -> None:
    """In the first child after :func:`enter_namespaces`: die with the process that made the namespace (which
    waits for us). As pid 1 of the namespace, when this process ends the kernel kills every process in it: no
    worker outlives its zygote, whatever it did to its own parent-death signal."""
    _libc.prctl(ctypes.c_int(PR_SET_PDEATHSIG), ctypes.c_ulong(9), ctypes.c_ulong(0), ctypes.c_ulong(0),
                ctypes.c_ulong(0))


def die_with_parent(parent_pid: int) -> None:
    """PR_SET_PDEATHSIG SIGKILL; end at once if the parent (``parent_pid``) is already gone."""
    _libc.prctl(ctypes.c_int(PR_SET_PDEATHSIG), ctypes.c_ulong(9), ctypes.c_ulong(0), ctypes.c_ulong(0),
                ctypes.c_ulong(0))
    if os.getppid() != parent_pid:
        os._exit(1)


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
        resource.setrlimit(resource.RLIMIT_NOFILE, (limits.open_files, limits.open_files))
        if limits.cpu_s:
            used = int(sum(os.times()[:2]))
            resource.setrlimit(resource.RLIMIT_CPU, (used + limits.cpu_s, used + limits.cpu_s + 5))
        if limits.memory_mb:
            with open("/proc/self/statm") as f:
                current = int(f.read().split()[0]) * resource.getpagesize()
            cap = current + limits.memory_mb * 2**20
            resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    def no_new_privs() -> None:
        if _libc.prctl(ctypes.c_int(PR_SET_NO_NEW_PRIVS), ctypes.c_ulong(1), ctypes.c_ulong(0), ctypes.c_ulong(0),
                       ctypes.c_ulong(0)) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS) failed")

    def capabilities() -> None:
        # root in the worker would otherwise keep CAP_SYS_RESOURCE (raise its rlimits back), CAP_SYS_TIME, ...
        prctl = _libc.prctl
        prctl(ctypes.c_int(PR_CAP_AMBIENT), ctypes.c_ulong(PR_CAP_AMBIENT_CLEAR_ALL), ctypes.c_ulong(0),
              ctypes.c_ulong(0), ctypes.c_ulong(0))
        for cap in range(64):
            if prctl(ctypes.c_int(PR_CAPBSET_DROP), ctypes.c_ulong(cap), ctypes.c_ulong(0), ctypes.c_ulong(0),
                     ctypes.c_ulong(0)) != 0 and ctypes.get_errno() == 22:  # EINVAL: past the last capability
                break
        header = struct.pack("=Ii", LINUX_CAPABILITY_VERSION_3, 0)
        data = bytes(24)  # effective, permitted, inheritable: all empty (two 32-bit words each)
        if _libc.syscall(ctypes.c_long(SYS_CAPSET), ctypes.create_string_buffer(header, 8),
                         ctypes.create_string_buffer(data, 24)) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"capset: {os.strerror(err)}")

    def landlock() -> None:
        abi = landlock_abi()
        if abi < 1:
            raise OSError("Landlock is not enabled in this kernel (needs Linux >= 5.13 with lsm=landlock)")
        read, list_only = read_paths()
        _landlock(list(read), list(limits.write_paths), list(list_only), abi)

    def seccomp() -> None:
        if platform.machine() != "x86_64":
            raise OSError(f"the seccomp filter is written for x86_64, not {platform.machine()}")
        _seccomp(seccomp_program(os.getpid()))

    step("rlimits", rlimits)
    step("capabilities", capabilities)
    step("no_new_privs", no_new_privs)
    step("landlock", landlock)
    step("seccomp", seccomp)
    return missing
