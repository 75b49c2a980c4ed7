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
# where processes fork, workers start with their parent's memory (what they work on need not be pickled to them)
FORK = "fork" if "fork" in multiprocessing.get_all_start_methods() else None


def cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def pool(processes: int, start: str | None = None, initializer=None,
         initargs: tuple = ()) -> multiprocessing.pool.Pool:
    """A process pool (``start``: "fork", "spawn" or the platform's default) whose workers first run
    ``initializer(*initargs)``; leaving its ``with`` block, also by an error or a signal, terminates the workers."""
    context = multiprocessing.get_context(start)
    return context.Pool(processes, initializer=_worker_signals, initargs=(initializer, initargs))


def each(function, items: list, workers: int) -> list:
    """``[function(item) for item in items]`` in ``workers`` processes (in order; one worker: in this process). Where
    processes fork, the workers start with ``function`` and ``items`` in memory (nothing pickled but the results);
    elsewhere both are pickled once for each worker."""
    if workers <= 1 or len(items) < 2:
        return [function(item) for item in items]
    with pool(min(workers, len(items)), FORK, _keep, (function, items)) as p:
        return p.map(_call, range(len(items)), chunksize=max(1, len(items) // (4 * workers)))


_KEPT: list = []  # in a worker of each(): its function and items


def _keep(function, items: list) -> None:
    _KEPT[:] = [function, items]


def _call(k: int):
    return _KEPT[0](_KEPT[1][k])


def _worker_signals(initializer=None, initargs: tuple = ()) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGALRM, _stop)  # a stop put off (_stop_later)
    sys.unraisablehook = _stop_later
    try:  # Linux: the worker ends with the process that started it, however that ends (killed, or stopped while
        # multiprocessing's own termination waited on a worker)
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass
    if initializer is not None:
        initializer(*initargs)


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
