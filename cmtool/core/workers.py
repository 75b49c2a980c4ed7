"""Worker processes that stop with their command: a pool whose workers leave Ctrl-C to the command (which stops
them) and end on SIGTERM as a command does, removing what they were writing, without a traceback each."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys

PR_SET_PDEATHSIG = 1  # prctl(2)
STOP_S = 2.0  # the longest a stopped worker unwinds before it ends at once


def pool(processes: int, start: str | None = None) -> multiprocessing.pool.Pool:
    """A process pool (``start``: "fork", "spawn" or the platform's default); leaving its ``with`` block, also by an
    error or a signal, terminates the workers."""
    context = multiprocessing.get_context(start)
    return context.Pool(processes, initializer=_worker_signals)


def _worker_signals() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGALRM, _stop)  # a stop put off (_stop_later)
    sys.unraisablehook = _stop_later
    try:  # Linux: the worker ends with the process that started it, however that ends (killed, or stopped while
        # multiprocessing's own termination waited on a worker)
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


_stopping = False


def _stop(signum, frame):
    """Unwind (temporary files removed; multiprocessing prints no traceback for SystemExit). A ``finally`` may put
    another error in the stop's place (zipfile's does, when the stop lands in a write), and the worker would then take
    its next task: a second SIGTERM, or the alarm set here, ends it at once."""
    global _stopping
    if _stopping:
        os._exit(128 + signal.SIGTERM)
    _stopping = True
    signal.setitimer(signal.ITIMER_REAL, STOP_S)
    raise SystemExit(128 + signal.SIGTERM)


def _stop_later(unraisable) -> None:
    """A stop that arrived inside a finalizer (``__del__``), where Python prints the exception and goes on: nothing is
    printed, and the stop comes again a millisecond later (SIGALRM), where the worker can unwind. Once stopping, the
    finalizers of what the stop left half made (a zip file whose file is closed) fail unprinted."""
    global _stopping
    if isinstance(unraisable.exc_value, SystemExit):
        _stopping = False
        signal.setitimer(signal.ITIMER_REAL, 0.001)
    elif not _stopping:
        sys.__unraisablehook__(unraisable)
