"""Worker processes that stop with their command: a pool whose workers leave Ctrl-C to the command (which stops
them) and end on SIGTERM as a command does, removing what they were writing, without a traceback each."""

from __future__ import annotations

import ctypes
import multiprocessing
import multiprocessing.pool
import os
import signal
import sys
import threading

PR_SET_PDEATHSIG = 1  # prctl(2)
STOP_S = 2.0  # the longest a stopped worker unwinds before it ends at once
KILL_S = 3 * STOP_S  # a terminated pool's workers still there this long after are killed


def cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def pool(processes: int, start: str | None = None, initializer=None,
         initargs: tuple = ()) -> multiprocessing.pool.Pool:
    """A process pool (``start``: "fork", "spawn" or the platform's default) whose workers first run
    ``initializer(*initargs)``; when its ``with`` block ends the workers finish and leave, or, after an error or a
    signal, are terminated (:class:`_Pool`)."""
    context = multiprocessing.get_context(start)
    if context.get_start_method() == "fork":  # at once, nothing sent; a forked worker would inherit held handlers
        return _Pool(processes, _worker_signals, (initializer, initargs), context=context)
    got: list[int] = []
    held = _hold_signals(got)  # a stop while the workers start (and read what they are sent) waits until they have
    try:
        made = _Pool(processes, _worker_signals, (initializer, initargs), context=context)
    finally:
        for signum, handler in held.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
    if got:
        made.terminate()
        signal.raise_signal(got[0])
    return made


class _Pool(multiprocessing.pool.Pool):
    """A pool whose workers, when its ``with`` block ends normally, finish and leave (no signal: terminating them
    while one was still starting left it waiting for ever on the task queue's lock, which terminate holds); after an
    error or a stop they are terminated, and any still there ``KILL_S`` later killed (a worker the termination found
    starting has been seen waiting on that lock for ever, and the pool's termination with it)."""

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
            self.join()
        else:
            self.terminate()

    def terminate(self):
        done = threading.Event()
        threading.Thread(target=self._kill_stragglers, args=(done,), daemon=True).start()
        try:
            super().terminate()
        finally:
            done.set()

    def _kill_stragglers(self, done: threading.Event) -> None:
        while not done.wait(KILL_S):
            for worker in list(self._pool):
                if worker.exitcode is None and worker.pid is not None:
                    try:
                        os.kill(worker.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass


def _hold_signals(got: list[int]) -> dict:
    """Replace the handlers of SIGINT and SIGTERM by one that notes each in ``got``; returns the handlers replaced
    (none outside the main thread, where no handler runs)."""
    try:
        return {s: signal.signal(s, lambda signum, frame: got.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:
        return {}


def each(function, items: list, workers: int, least: int = 2) -> list:
    """``[function(item) for item in items]`` in ``workers`` fresh processes ("spawn": they share no lock with this
    process's threads; ``function`` must be importable without torch to start fast), in order; in this process when
    ``workers`` is 1 or there are fewer than ``least`` items."""
    if workers <= 1 or len(items) < max(2, least):
        return [function(item) for item in items]
    with pool(min(workers, len(items)), "spawn") as p:
        return p.map(function, items, chunksize=max(1, len(items) // (4 * workers)))


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
