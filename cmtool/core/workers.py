"""Worker processes that stop with their command: a pool whose workers leave Ctrl-C to the command (which stops
them) and end on SIGTERM as a command does, removing what they were writing, without a traceback each."""

from __future__ import annotations

import ctypes
import multiprocessing
import signal
import sys

PR_SET_PDEATHSIG = 1  # prctl(2)


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


def _stop(signum, frame):
    raise SystemExit(128 + signal.SIGTERM)  # unwinds (temporary files removed); multiprocessing prints no traceback for it


def _stop_later(unraisable) -> None:
    """A stop that arrived inside a finalizer (``__del__``), where Python prints the exception and goes on: nothing is
    printed, and the stop comes again a millisecond later (SIGALRM), where the worker can unwind."""
    if isinstance(unraisable.exc_value, SystemExit):
        signal.setitimer(signal.ITIMER_REAL, 0.001)
    else:
        sys.__unraisablehook__(unraisable)

