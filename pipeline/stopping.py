"""How a command stops: Ctrl-C (SIGINT) and SIGTERM end it the same way, as one KeyboardInterrupt.

A terminal's Ctrl-C reaches the whole process group: the command and everything it started hear it. SIGTERM
(``kill PID``, ``timeout``, a service manager) usually reaches the command alone, so it is raised as
:class:`Terminated`, a KeyboardInterrupt that tells the command to pass the stop on to the processes it started
that would not otherwise hear it (a batch's runs). Either is raised once: another while the command winds down is
ignored (it would break the winding down off with a traceback); ``kill -9`` still ends it at once.
"""

from __future__ import annotations

import atexit
import gc
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator, NoReturn


class Terminated(KeyboardInterrupt):
    """The KeyboardInterrupt of a SIGTERM: it may have reached this process alone."""


_uninterrupted = 0
"""How many :func:`uninterrupted` blocks the main thread is in."""
_held: int | None = None
"""The signal that arrived in one, raised as the outermost ends."""
_stopped: int | None = None
"""The signal that stopped the command (in this process), once one has."""


def stop_once(signum: int, frame: object) -> None:
    """The handler of both signals: ignore both from now on, and raise the interrupt (held, in an
    :func:`uninterrupted` block, until it ends)."""
    global _held, _stopped
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _stopped = signum
    if _uninterrupted:
        _held = signum
        return
    _raise(signum)


def _raise(signum: int) -> None:
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def stop_pending() -> bool:
    """Whether a Ctrl-C or SIGTERM has stopped the command: its interrupt may have been swallowed where Python
    ignores exceptions (an at-fork hook, a finalizer: "Exception ignored in ..."), and the signals are ignored from
    then on, so a wait for ever must look (``view --serve-web`` waited for good after a press landed in a fork).
    Only while they are ignored: a caller in this process (a test, a script) that put its handlers back after a
    stopped command is not stopped by that command's press."""
    return _stopped is not None and signal.getsignal(_stopped) is signal.SIG_IGN


def raise_if_stopped() -> None:
    """Raise the interrupt of a Ctrl-C or SIGTERM that stopped the command, also one Python swallowed (see
    :func:`stop_pending`): for a loop that waits a long time, to look at as it waits. In the main thread only, where
    the signal itself is raised (a server's games in a thread of their own end as the server does)."""
    if stop_pending() and threading.current_thread() is threading.main_thread():
        _raise(_stopped)


def quiet_swallowed_interrupts() -> None:
    """Say nothing of a Ctrl-C or SIGTERM that Python had to swallow: one that landed in an at-fork hook (logging's
    lock, as ``subprocess`` starts a child with a ``preexec_fn``), a finalizer or an exit handler printed "Exception
    ignored in ..." and a traceback. It is the press the command answers with its line ``interrupted``: the handler
    noted it (:func:`stop_pending`), and the command's long waits raise it (:func:`raise_if_stopped`). Any other
    ignored error is reported by the hook installed before this one."""
    report = sys.unraisablehook

    def _quiet(unraisable) -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            report(unraisable)

    sys.unraisablehook = _quiet


def wait_for_stop(done: Callable[[float], bool] | None = None) -> None:
    """Wait until a Ctrl-C or SIGTERM stops the command (raised as :func:`stop_once` raises it, the one a swallowed
    handler raised too), or until ``done(timeout)``, a wait of at most ``timeout`` seconds, says it is over."""
    while True:
        raise_if_stopped()
        if done is None:
            time.sleep(0.25)
        elif done(0.25):
            return


@contextmanager
def uninterrupted() -> Iterator[None]:
    """Run the block to its end: a Ctrl-C or SIGTERM that arrives meanwhile is raised as it ends (where
    :func:`stop_once` handles them). For the write that ends a run: a press that landed in it rolled it back, and a
    run whose games had all been played and stored was left 'running' for good. A block that raises keeps its own
    error (the signal still stops the command: both are ignored from then on)."""
    global _uninterrupted, _held
    if threading.current_thread() is not threading.main_thread():  # signals are raised in the main thread only
        yield
        return
    _uninterrupted += 1
    try:
        yield
    except BaseException:
        _uninterrupted -= 1
        if not _uninterrupted:
            _held = None
        raise
    _uninterrupted -= 1
    if not _uninterrupted and _held is not None:
        signum, _held = _held, None
        _raise(signum)


def exit_now(code: int) -> None:
    """End this process at once with ``code``, its own standard streams flushed first: nothing of Python's shutdown
    runs (no exit handler, no module teardown). For a process whose work and cleanup are done."""
    import os

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):  # a closed pipe, a closed or absent stream
            pass
    os._exit(code)


def end_process(code: int) -> NoReturn:
    """End a command's process, its work done, with ``code``: what the interpreter's own exit does that matters,
    then :func:`exit_now`. Its other threads are waited for as Python would (threads not marked daemon; a thread pool
    told to stop) and the exit handlers run (the zygotes stopped, Rerun's recordings flushed, temporary folders
    removed), while every thread still runs; then the process ends. Left out: the interpreter's teardown.

    Why: Python's teardown runs after it has frozen the daemon threads where they stood, then clears the modules and
    runs the finalizers of what that frees. A daemon thread stopped inside an import keeps Python's import lock for
    good, and a finalizer that imports waits for it forever: litellm's HTTP handler imports as it is dropped, and a
    batch run pressed while its model call was in flight said `interrupted` and never ended (2 presses of 13 beside
    a busy machine, until the batch's 60-s wind-down killed it). The teardown's garbage collections went, besides, over
    what a stopped command's work left (~490,000 objects of an optimize stopped in its episodes: 2-3 s after its
    last line); the operating system frees the memory at once. Under a profiler or a debugger (``python -m cProfile``,
    ``pdb``, coverage) the process exits as Python does, so that they report as it ends."""
    if sys.getprofile() is not None or sys.gettrace() is not None:
        raise SystemExit(code)
    gc.freeze()  # an exit handler's allocations start no collection over the whole heap
    try:
        threading._shutdown()  # what Python's exit does first (no public name): threads and thread pools end
    except KeyboardInterrupt:  # a press after the work was done: the exit handlers still run
        pass
    atexit._run_exitfuncs()  # each handler's error is reported as Python's exit reports it, and the next one runs
    exit_now(code)


def stop_on_signals(handler: Callable[[int, object], None] = stop_once) -> list[int]:
    """Install ``handler`` (in the main thread only) for SIGINT where it raises KeyboardInterrupt now (a process
    started with it ignored, under ``nohup`` or CI, keeps ignoring it) and for SIGTERM where it has its default;
    the signals it was installed for."""
    global _stopped
    if threading.current_thread() is not threading.main_thread():
        return []
    _stopped = None  # a command of its own (tests run many in one process)
    installed = []
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, handler)
        installed.append(signal.SIGINT)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, handler)
        installed.append(signal.SIGTERM)
    return installed
