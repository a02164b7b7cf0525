"""Kernel confinement of the process that runs untrusted policy code (Linux; ctypes only, no dependency).

One job: take a freshly forked worker (``pipeline/boundary/zygote.py``), after its environment is built and before any
policy code is loaded, and make the operating system the boundary:

- ``PR_SET_NO_NEW_PRIVS``: nothing it executes could gain privileges (and it may not execute anything);
- a network namespace of its own with no interface up (:func:`enter_network_namespace`, done once by the
  zygote; every worker inherits it): no network at all, not even 127.0.0.1 or abstract Unix sockets;
- scratch directories on a small tmpfs in the zygote's own mount namespace (:func:`scratch_tmpfs`): what
  workers can write is bounded in all, and invisible to (and gone for) the rest of the machine;
- Landlock (ABI probed with ``landlock_create_ruleset(NULL, 0, VERSION)``): reads only below the Python
  installation, site-packages (ROMs included), system libraries and the project's own packages; writes only
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
import sys
from dataclasses import dataclass, field
from pathlib import Path

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
    "process_vm_writev": 311, "process_madvise": 440, "mknod": 133, "mknodat": 259, "mount": 165,
    "umount2": 166, "unshare": 272, "setns": 308, "pivot_root": 155, "chroot": 161, "socket": 41,
    "connect": 42, "bind": 49, "listen": 50, "accept": 43, "accept4": 288, "tkill": 200,
    "rt_sigqueueinfo": 129, "rt_tgsigqueueinfo": 297, "pidfd_open": 434, "pidfd_send_signal": 424,
    "pidfd_getfd": 438, "kcmp": 312, "bpf": 321, "perf_event_open": 298, "userfaultfd": 323, "keyctl": 250,
    "add_key": 248, "request_key": 249, "io_uring_setup": 425, "io_uring_enter": 426,
    "io_uring_register": 427, "open_by_handle_at": 304, "name_to_handle_at": 303, "open_tree": 428,
    "move_mount": 429, "fsopen": 430, "fsconfig": 431, "fsmount": 432, "fspick": 433, "mount_setattr": 442,
    "kexec_load": 246, "kexec_file_load": 320, "init_module": 175, "finit_module": 313, "delete_module": 176,
    "iopl": 172, "ioperm": 173, "swapon": 167, "swapoff": 168, "reboot": 169, "personality": 135,
    "setuid": 105, "setgid": 106, "setreuid": 113, "setregid": 114, "setresuid": 117, "setresgid": 119,
    "setgroups": 116, "setfsuid": 122, "setfsgid": 123, "acct": 163, "quotactl": 179, "syslog": 103,
    "settimeofday": 164, "clock_settime": 227, "adjtimex": 159, "clock_adjtime": 305, "sethostname": 170,
    "setdomainname": 171, "vhangup": 153,
}
SYS_CLONE, SYS_CLONE3, SYS_KILL, SYS_TGKILL = 56, 435, 62, 234


def _insn(code: int, jt: int, jf: int, k: int) -> bytes:
    return struct.pack("=HBBI", code, jt, jf, k & 0xFFFFFFFF)


def seccomp_program(own_pid: int) -> bytes:
    """The BPF filter (x86_64): see the module docstring; ``own_pid`` is the one process kill may signal."""
    arg0_lo = 16  # offsetof(struct seccomp_data, args[0]), low 32 bits (little-endian)
    p = [
        _insn(_LD_ABS_W, 0, 0, 4),  # arch
        _insn(_JEQ, 1, 0, AUDIT_ARCH_X86_64),
        _insn(_RET, 0, 0, RET_KILL_PROCESS),
        _insn(_LD_ABS_W, 0, 0, 0),  # syscall number
        _insn(0x35, 0, 1, 0x40000000),  # jge: the x32 ABI
        _insn(_RET, 0, 0, RET_ERRNO | EPERM),
    ]
    for nr in sorted(DENIED_SYSCALLS.values()):
        p += [_insn(_JEQ, 0, 1, nr), _insn(_RET, 0, 0, RET_ERRNO | EPERM)]
    p += [_insn(_JEQ, 0, 1, SYS_CLONE3), _insn(_RET, 0, 0, RET_ERRNO | ENOSYS)]
    # clone: threads only
    p += [_insn(_JEQ, 0, 4, SYS_CLONE), _insn(_LD_ABS_W, 0, 0, arg0_lo), _insn(_JSET, 0, 1, CLONE_THREAD),
          _insn(_RET, 0, 0, RET_ALLOW), _insn(_RET, 0, 0, RET_ERRNO | EPERM)]
    # kill / tgkill: this process only (no process groups, no pid 0 / -1)
    for nr in (SYS_KILL, SYS_TGKILL):
        p += [_insn(_LD_ABS_W, 0, 0, 0), _insn(_JEQ, 0, 4, nr), _insn(_LD_ABS_W, 0, 0, arg0_lo),
              _insn(_JEQ, 0, 1, own_pid), _insn(_RET, 0, 0, RET_ALLOW), _insn(_RET, 0, 0, RET_ERRNO | EPERM)]
    p.append(_insn(_RET, 0, 0, RET_ALLOW))
    return b"".join(p)


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
SCRATCH_MB = 64
"""Size of the tmpfs that holds every worker's scratch directory (all workers of a zygote together)."""


def scratch_tmpfs(path: str, size_mb: int = SCRATCH_MB) -> None:
    """Mount a tmpfs of ``size_mb`` over ``path`` in a mount namespace of this process's own (after
    :func:`enter_network_namespace`, which provides the user namespace when not root): what workers write is
    bounded in all, and gone when this process ends. ``path`` is this process's working directory again."""
    if _libc.unshare(ctypes.c_int(CLONE_NEWNS)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"unshare(CLONE_NEWNS): {os.strerror(err)}")
    if _libc.mount(b"none", b"/", None, ctypes.c_ulong(MS_REC | MS_PRIVATE), None) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount(/, MS_PRIVATE): {os.strerror(err)}")
    options = f"size={size_mb}m,mode=0700".encode()
    if _libc.mount(b"tmpfs", os.fsencode(path), b"tmpfs", ctypes.c_ulong(MS_NOSUID | MS_NODEV | MS_NOEXEC),
                   options) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount tmpfs on {path}: {os.strerror(err)}")
    os.chdir(path)


def unmount(path: str) -> None:
    """Detach the tmpfs of :func:`scratch_tmpfs` (so that the directory beneath can be removed)."""
    _libc.umount2(os.fsencode(path), ctypes.c_int(2))  # MNT_DETACH


def enter_network_namespace() -> None:
    """Move this process into a new, empty network namespace: directly as root, else inside a new user
    namespace (unprivileged users, where the distribution allows it)."""
    if _libc.unshare(ctypes.c_int(CLONE_NEWNET)) == 0:
        return
    err = ctypes.get_errno()
    uid, gid = os.geteuid(), os.getegid()
    if _libc.unshare(ctypes.c_int(CLONE_NEWUSER | CLONE_NEWNET)) != 0:
        err2 = ctypes.get_errno()
        raise OSError(err, f"unshare(CLONE_NEWNET): {os.strerror(err)}; with a user namespace: {os.strerror(err2)}")
    try:
        for name, line in (("setgroups", "deny"), ("uid_map", f"{uid} {uid} 1"), ("gid_map", f"{gid} {gid} 1")):
            with open(f"/proc/self/{name}", "w") as f:  # the same ids inside, so that files keep their owners
                f.write(line)
    except OSError:
        pass  # (mapping root needs CAP_SETFCAP) unmapped ids still reach their files; the netns is what counts


def die_with_parent(parent_pid: int) -> None:
    """PR_SET_PDEATHSIG SIGKILL; end at once if the parent (``parent_pid``) is already gone."""
    _libc.prctl(ctypes.c_int(PR_SET_PDEATHSIG), ctypes.c_ulong(9), ctypes.c_ulong(0), ctypes.c_ulong(0),
                ctypes.c_ulong(0))
    if os.getppid() != parent_pid:
        os._exit(1)


@dataclass
class Limits:
    """What one worker may use."""

    memory_mb: int | None = 4096
    """Address space above what the worker had when confined (None: unlimited)."""
    cpu_s: int | None = None
    """CPU seconds before SIGXCPU/SIGKILL (a backstop; the parent's wall-clock kill comes first)."""
    file_size_mb: int = 64
    open_files: int = 256
    write_paths: list[str] = field(default_factory=list)
    """Directories the worker may write below (its scratch directory, a Rerun recording directory)."""


def read_paths() -> tuple[list[str], list[str]]:
    """(paths readable below, directories that may only be listed): Python, site-packages, system
    libraries, the project's packages (not the project directory's other files, such as a store)."""
    import site

    read = {sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix,
            os.path.dirname(os.path.realpath(sys.executable)), "/usr/lib", "/usr/lib64", "/lib", "/lib64",
            "/usr/local/lib", "/etc/ld.so.cache", "/usr/share/zoneinfo", "/etc/localtime", "/dev/urandom",
            "/dev/null"}
    try:
        read.update(site.getsitepackages())
    except AttributeError:
        pass
    project = Path(__file__).resolve().parents[2]
    list_only = {str(project)}
    for sub in project.iterdir():
        if (sub / "__init__.py").exists():
            read.add(str(sub))
    return sorted(read), sorted(list_only)


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
        _landlock(read, list(limits.write_paths), list_only, abi)

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
