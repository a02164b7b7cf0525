"""The seccomp filter of a policy process: the system calls it may not make, in classic BPF written here.

One job: build the filter (:func:`seccomp_program`, x86_64) and install it (:func:`install`). Refused with EPERM:
``execve``/``execveat``, ``fork``/``vfork``, ``clone`` (``clone3`` answers ENOSYS so glibc falls back to
``clone``): no processes and no threads; socket creation, ``ptrace``, ``process_vm_*``, ``mknod``,
``mount``/``unshare``/``setns`` and friends, ``io_uring``, ``bpf``, uid changes, host IPC and memfds, and the
kernel buffers no limit counts (``socketpair``, ``setsockopt``, ``fcntl(F_SETPIPE_SZ)``); the calls
that name a process (``kill``/``tgkill``, scheduling, priorities, ``prlimit64``) unless they name the caller
itself; changing the parent-death signal. ``pipeline/boundary/confine.py`` applies it with the other layers.
"""

from __future__ import annotations

import ctypes
import functools
import os
import struct
from typing import Any

from pipeline.boundary.libc import libc

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
    # kernel memory no limit of the process counts: a socket pair's buffers (raised by setsockopt, and passed to
    # itself in flight past the open-file limit: one policy process held 4.6 GB that way); the process is given
    # the one socket it needs
    "socketpair": 53, "setsockopt": 54,
}
SYS_CLONE, SYS_CLONE3, SYS_KILL, SYS_TGKILL, SYS_PRCTL, SYS_FCNTL = 56, 435, 62, 234, 157, 72
F_SETPIPE_SZ = 1031
"""``fcntl``'s command that grows a pipe's buffer (to 1 MiB and more as root): kernel memory, refused."""
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
            out.append(_insn(code, jt, jf, 0 if k is OWN_PID else k))
        return b"".join(out)


def _insn(code: int, jt: int, jf: int, k: int) -> bytes:
    return struct.pack("=HBBI", code, jt, jf, k & 0xFFFFFFFF)


OWN_PID = "own pid"
"""Where the filter compares an argument with the policy process's own pid, which :func:`seccomp_program` fills in."""


def seccomp_program(own_pid: int) -> bytes:
    """The BPF filter (x86_64): see the module docstring; ``own_pid`` is the one process the calls that name a
    process may target. Assembled once per process (:func:`_template`, the policy zygote's, inherited by its
    workers: ~1 ms of Python), the pid written into it."""
    template, pid_offsets = _template()
    program = bytearray(template)
    for offset in pid_offsets:
        struct.pack_into("=I", program, offset, own_pid & 0xFFFFFFFF)
    return bytes(program)


@functools.cache
def _template() -> tuple[bytes, tuple[int, ...]]:
    """The filter with 0 for the own pid, and the byte offsets of those constants (``k``, 4 bytes into an insn)."""
    p = _filter(OWN_PID)
    return p.assemble(), tuple(8 * i + 4 for i, (_code, _jt, _jf, k) in enumerate(p.code) if k is OWN_PID)


def _filter(own_pid: int | str) -> "_Bpf":
    """The filter's program, unassembled; ``own_pid`` a pid or :data:`OWN_PID`."""
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
    p.jeq(SYS_FCNTL, 0, "after_fcntl")
    p.ld(arg(1))
    p.jeq(F_SETPIPE_SZ, "deny", "allow")
    p.label("after_fcntl")
    p.ld(0)
    p.jeq(SYS_PRCTL, 0, "allow")
    p.ld(arg(0))
    p.jeq(PR_SET_PDEATHSIG_OPTION, "deny", "allow")  # the parent-death signal stays as the zygote set it
    p.label("deny")
    p.ret(deny)
    p.label("allow")
    p.ret(allow)
    return p


def install(program: bytes) -> None:
    """Install ``program`` (:func:`seccomp_program`) on every thread of this process, for good."""
    n = len(program) // 8
    filt = ctypes.create_string_buffer(program, len(program))

    class SockFprog(ctypes.Structure):
        _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]

    prog = SockFprog(n, ctypes.addressof(filt))
    if libc.syscall(ctypes.c_long(SYS_SECCOMP), ctypes.c_uint(SECCOMP_SET_MODE_FILTER),
                    ctypes.c_uint(SECCOMP_FILTER_FLAG_TSYNC), ctypes.byref(prog)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"seccomp(SET_MODE_FILTER): {os.strerror(err)}")
