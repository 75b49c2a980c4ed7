"""Worker processes that stop with their command: a pool whose workers leave Ctrl-C to the command (which stops
them) and end on SIGTERM as a command does, removing what they were writing, without a traceback each."""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import multiprocessing.pool
import multiprocessing.resource_tracker
import os
import signal
import sys
import threading
import time

from cmtool.core.errors import CmtoolError

PR_SET_PDEATHSIG = 1  # prctl(2)
STOP_S = 2.0  # the longest a stopped worker unwinds before it ends at once
KILL_S = 3 * STOP_S  # a terminated pool's workers still there this long after are killed
WATCH_S = 0.1  # how often a running pool looks for a worker that ended
MODEL_THREADS = 1  # torch's threads in a model's passes, on every machine (:func:`model_threads`)


def cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def model_threads():
    """torch on ``MODEL_THREADS`` threads inside the block, whatever the cores, ``OMP_NUM_THREADS`` or the count
    before: oneDNN's convolutions and MKL's products split their sums by the thread count, so a seed's map would
    follow the machine and the workers beside the model (one thread: also torchrun's, and no process oversubscribes
    a core; the count before is restored)."""
    import torch  # here: the workers import this module and need no torch

    before = torch.get_num_threads()
    torch.set_num_threads(MODEL_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def pool(processes: int, start: str | None = None, initializer=None,
         initargs: tuple = ()) -> multiprocessing.pool.Pool:
    """A process pool (``start``: "fork", "spawn" or the platform's default) whose workers first run
    ``initializer(*initargs)``; when its ``with`` block ends the workers finish and leave, or, after an error or a
    signal, are terminated; a worker that ends while the pool runs fails its tasks with the cause (:class:`_Pool`).
    The workers are born with Ctrl-C blocked, then ignore it (the command stops them): none prints a
    KeyboardInterrupt from its start."""
    context = multiprocessing.get_context(start)
    fork = context.get_start_method() == "fork"
    if not fork:  # started while the workers start, multiprocessing's resource tracker would unblock Ctrl-C after it
        multiprocessing.resource_tracker.ensure_running()
    got: list[int] = []
    # a stop while spawned workers start (and read what they are sent) waits until they have; a forked worker would
    # inherit the held handlers
    held = {} if fork else _hold_signals(got)
    try:
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})  # inherited by the workers and threads
        try:
            made = _Pool(processes, initializer, initargs, context)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
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
    starting has been seen waiting on that lock for ever, and the pool's termination with it; a worker killed as it
    sent a result holds the results' lock for ever, which the termination then replaces).

    A worker that ends while the pool runs (killed, or its initializer failed) would be replaced, and the task it held
    would never end: every task waiting then, and every one given after, fails with a :class:`CmtoolError` naming
    the cause (:meth:`_watch`)."""

    def __init__(self, processes: int, initializer, initargs: tuple, context):
        self._started: list = []  # every worker started (Process)
        self._errors = context.SimpleQueue()  # why a worker's initializer failed, one line each
        self._broken: CmtoolError | None = None
        super().__init__(processes, _worker_signals, (self._errors, initializer, initargs), context=context)
        threading.Thread(target=self._watch, daemon=True).start()

    def Process(self, ctx, *args, **kwargs):
        worker = ctx.Process(*args, **kwargs)
        self._started.append(worker)
        return worker

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
            self.join()
        else:
            self.terminate()

    def terminate(self):
        lock = self._outqueue._wlock  # held for ever by a worker killed as it sent a result (None: no lock here)
        if lock is not None and not lock.acquire(timeout=STOP_S):
            self._outqueue._wlock = self._ctx.Lock()  # the termination's last message to the results would wait on it
        elif lock is not None:
            lock.release()
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

    def _watch(self) -> None:
        """While the pool runs: once a worker has ended, fail the tasks waiting (and those given later)."""
        failed = set()
        while self._state == multiprocessing.pool.RUN:
            if self._broken is None:
                self._broken = next((self._cause(w) for w in list(self._started) if w.exitcode is not None), None)
            if self._broken is not None:
                for job, result in list(self._cache.items()):
                    if job not in failed:
                        failed.add(job)
                        _fail(result, self._broken)
            time.sleep(WATCH_S)

    def _cause(self, worker) -> CmtoolError:
        """Why ``worker`` ended, in one line."""
        if not self._errors.empty():
            return CmtoolError(f"a worker process could not start: {self._errors.get()}")
        if worker.exitcode < 0:
            name = signal.Signals(-worker.exitcode).name
            return CmtoolError(f"a worker process was killed ({name}{', out of memory?' if name == 'SIGKILL' else ''})")
        return CmtoolError(f"a worker process ended unexpectedly (exit status {worker.exitcode})")

    @staticmethod
    def _help_stuff_finish(inqueue, task_handler, size):
        """multiprocessing's, but waiting at most ``STOP_S`` for the task queue's lock: a worker killed while it held
        it (waiting for a task) holds it for ever, and the termination waited with it."""
        inqueue._rlock.acquire(timeout=STOP_S)
        while task_handler.is_alive() and inqueue._reader.poll():
            inqueue._reader.recv_bytes()
            time.sleep(0)


def _fail(result, error: Exception) -> None:
    """End a pool's waiting result (of ``apply_async``, ``map``, ``imap``) with ``error``, as a failed task does."""
    with contextlib.suppress(KeyError):  # the result handler ended it meanwhile
        if isinstance(result, multiprocessing.pool.IMapIterator):
            result._set(result._index, (False, error))
        else:
            result._number_left = 1  # a map's: ends at once
            result._set(0, (False, error))


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


def _worker_signals(errors, initializer=None, initargs: tuple = ()) -> None:
    """A worker's start: Ctrl-C ignored (then unblocked: :func:`pool` blocked it), SIGTERM a stop; then
    ``initializer(*initargs)``, whose error goes to ``errors`` as one line and ends the worker quietly."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGALRM, _stop)  # a stop put off (_stop_later)
    sys.unraisablehook = _stop_later
    try:  # Linux: the worker ends with the process that started it, however that ends (killed, or stopped while
        # multiprocessing's own termination waited on a worker)
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass
    if initializer is not None:
        try:
            initializer(*initargs)
        except Exception as e:  # noqa: BLE001 (whatever failed, the pool names it)
            errors.put(_one_line(e))
            raise SystemExit(1) from None


def _one_line(e: Exception) -> str:
    """``e`` as one line: a file error as PATH: reason."""
    if isinstance(e, OSError) and e.strerror:
        return f"{'' if e.filename is None else f'{e.filename}: '}{e.strerror.lower()}"
    return str(e).splitlines()[0] if str(e) else type(e).__name__


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
