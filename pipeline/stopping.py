"""How a command stops: Ctrl-C (SIGINT) and SIGTERM end it the same way, as one KeyboardInterrupt.

A terminal's Ctrl-C reaches the whole process group: the command and everything it started hear it. SIGTERM
(``kill PID``, ``timeout``, a service manager) usually reaches the command alone, so it is raised as
:class:`Terminated`, a KeyboardInterrupt that tells the command to pass the stop on to the processes it started
that would not otherwise hear it (a batch's runs). Either is raised once: another while the command winds down is
ignored (it would break the winding down off with a traceback); ``kill -9`` still ends it at once.
"""

from __future__ import annotations

import signal
import threading
from typing import Callable


class Terminated(KeyboardInterrupt):
    """The KeyboardInterrupt of a SIGTERM: it may have reached this process alone."""


def stop_once(signum: int, frame: object) -> None:
    """The handler of both signals: ignore both from now on, and raise the interrupt."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def stop_on_signals(handler: Callable[[int, object], None] = stop_once) -> list[int]:
    """Install ``handler`` (in the main thread only) for SIGINT where it raises KeyboardInterrupt now (a process
    started with it ignored, under ``nohup`` or CI, keeps ignoring it) and for SIGTERM where it has its default;
    the signals it was installed for."""
    if threading.current_thread() is not threading.main_thread():
        return []
    installed = []
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, handler)
        installed.append(signal.SIGINT)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, handler)
        installed.append(signal.SIGTERM)
    return installed
