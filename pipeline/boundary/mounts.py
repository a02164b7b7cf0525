"""The filesystem a policy process sees and writes: its scratch tmpfs, the minimal root, and their removal.

One job: the mounts of the policy zygote and its workers. The zygote takes a mount namespace of its own with a
small tmpfs (:func:`scratch_tmpfs`) and pivots into a root that holds only what a policy process may read
(:func:`minimal_root`: the paths of ``pipeline/boundary/view.py``, bound read-only; ``stat()``, which Landlock does
not cover, finds nothing else); each worker mounts a tmpfs of its own as its scratch directory, bounded in bytes
and inodes (:func:`worker_scratch`), which the zygote detaches whole when the worker ends (:func:`unmount`), nothing
walked; a scratch without a tmpfs (a weak sandbox) is removed by an iterative walk (:func:`remove_tree`) that cannot
raise. A zygote removes its scratch directory when it ends; those of zygotes killed with their parent, a whole
process group at once, are swept by the next process that starts one (:func:`sweep_stale_scratch`).
"""

from __future__ import annotations

import ctypes
import os
import stat
import tempfile
import time

from pipeline.boundary.libc import libc

CLONE_NEWNS = 0x00020000
MS_NOSUID, MS_NODEV, MS_NOEXEC, MS_REC, MS_PRIVATE = 2, 4, 8, 16384, 1 << 18
SCRATCH_MB = 16
"""Bytes of one worker's scratch tmpfs (:func:`worker_scratch`), in MiB: each policy process has its own."""
SCRATCH_INODES = 2_048
"""Inodes of one worker's scratch tmpfs (``nr_inodes``): files, directories and links together, its root included.
Without it a tmpfs gets the kernel's default (half the machine's pages: ~3.1M on a 24 GiB machine), and 300,000 empty
files in a 64 MiB scratch held ~300 MB of kernel memory (inodes, dentries) that no RSS or address-space limit counts;
at this cap it is ~2 MB. It bounds a directory's depth too (each level is an inode: the kernel has no depth
limit of its own for a tmpfs; ``PATH_MAX`` bounds one path, not a chain of ``chdir``s)."""
SCRATCH_PREFIX = "codearcade-sandbox-"
"""The name of each zygote's scratch directory in the temporary directory begins with this."""
STALE_AFTER_S = 3_600.0
"""A scratch directory no process works in is swept once nothing has touched it for this long (a zygote's is
touched by every worker it forks)."""
BASE_MB, BASE_INODES = 4, 8_192
"""The zygote's own tmpfs (:func:`scratch_tmpfs`), which holds only the workers' mount points (one inode each,
removed with the worker) and the minimal root's mount point: workers never write in it."""


def scratch_tmpfs(path: str, size_mb: int = BASE_MB, inodes: int = BASE_INODES) -> None:
    """Mount a tmpfs of ``size_mb`` and ``inodes`` over ``path`` in a mount namespace of this process's own (after
    :func:`enter_namespaces`, which provides the user namespace when not root): it holds each worker's scratch
    mount point (:func:`worker_scratch`), and it is gone, with every worker's tmpfs, when this process ends.
    ``path`` is this process's working directory again."""
    if libc.unshare(ctypes.c_int(CLONE_NEWNS)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"unshare(CLONE_NEWNS): {os.strerror(err)}")
    if libc.mount(b"none", b"/", None, ctypes.c_ulong(MS_REC | MS_PRIVATE), None) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount(/, MS_PRIVATE): {os.strerror(err)}")
    options = f"size={size_mb}m,nr_inodes={inodes},mode=0700".encode()
    if libc.mount(b"tmpfs", os.fsencode(path), b"tmpfs", ctypes.c_ulong(MS_NOSUID | MS_NODEV | MS_NOEXEC),
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
    if libc.mount(b"tmpfs", os.fsencode(path), b"tmpfs", ctypes.c_ulong(MS_NOSUID | MS_NODEV | MS_NOEXEC),
                  options) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount a scratch tmpfs on {path}: {os.strerror(err)}")


MS_RDONLY, MS_REMOUNT, MS_BIND = 1, 32, 4096
SYS_PIVOT_ROOT = 155


def _mount(source: str | None, target: str, fstype: str | None, flags: int, data: str | None = None) -> None:
    if libc.mount(None if source is None else os.fsencode(source), os.fsencode(target),
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
    if libc.syscall(ctypes.c_long(SYS_PIVOT_ROOT), os.fsencode(root), os.fsencode(old)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"pivot_root: {os.strerror(err)}")
    os.chdir("/")
    if libc.umount2(b"/.old", ctypes.c_int(2)) != 0:  # MNT_DETACH
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
        return libc.umount2(os.fsencode(path), ctypes.c_int(MNT_DETACH | UMOUNT_NOFOLLOW)) == 0
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


def sweep_stale_scratch(base: str | None = None, older_than_s: float = STALE_AFTER_S) -> list[str]:
    """Remove the zygote scratch directories in ``base`` (the temporary directory) that a zygote could not remove
    itself (killed with its parent, a whole process group at once): this user's, untouched for ``older_than_s``,
    and no process's working directory or below it (a zygote runs in its scratch, each worker in a folder of it).
    Never raises; the paths removed."""
    base = base or tempfile.gettempdir()
    now, uid = time.time(), os.getuid()
    try:
        candidates = []
        with os.scandir(base) as entries:
            for entry in entries:
                if not entry.name.startswith(SCRATCH_PREFIX):
                    continue
                info = entry.stat(follow_symlinks=False)
                if stat.S_ISDIR(info.st_mode) and info.st_uid == uid and now - info.st_mtime > older_than_s:
                    candidates.append(os.path.realpath(entry.path))
        if not candidates:
            return []
        in_use = _working_directories()
        removed = []
        for path in candidates:
            if not any(cwd == path or cwd.startswith(path + os.sep) for cwd in in_use) and remove_tree(path):
                removed.append(path)
        return removed
    except OSError:
        return []


def _working_directories() -> set[str]:
    """The working directory of every process this one can see and read (its own user's at least)."""
    found = set()
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                found.add(os.readlink(f"/proc/{name}/cwd").removesuffix(" (deleted)"))
            except OSError:  # gone meanwhile, or another user's
                pass
    return found
