"""Each batch's per-map work beside the denoising of the batches after it: the maps' checks and guarantee
(:func:`cmtool.sample.checks.check_maps`) and their files' bytes (:meth:`cmtool.sample.files.MapFiles.contents`), in
``workers`` processes, or with one worker in a second thread of the denoising process. Only the denoising process
writes (it stages the bytes the workers send back, in the jobs' order), so the files are the same byte for byte
whatever the number of workers, and a stopped run leaves no temporary file of a worker's behind. The workers are
started afresh ("spawn": a process forked from one with torch's, Rerun's or a test runner's threads can wait for
ever on a lock one of them held) and each reads the run's jobs from one file, in a temporary folder that the run
removes (or, when it was killed, the next run with workers)."""

from __future__ import annotations

import contextlib
import os
import pickle
import shutil
import tempfile
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from cmtool.core import workers as W
from cmtool.maps.lanegraph import LaneGraph
from cmtool.sample.checks import check_maps
from cmtool.sample.files import MapFiles

if TYPE_CHECKING:
    from cmtool.sample.job import Job, SampleSettings


def default_workers() -> int:
    """One per core where there are more than two; else 1, the thread: on two cores the model's thread
    (:func:`~cmtool.core.workers.model_threads`) and the checks' thread keep both busy, and processes measured no
    faster (docs/speed.md)."""
    return W.cores() if W.cores() > 2 else 1


def pipelined(jobs: list[Job], settings: SampleSettings, denoise, files: MapFiles | None, workers: int,
              finished, starts: list[int] | None = None) -> None:
    """Denoise the jobs batch after batch (``denoise(batch, start)``: the batch's lane graphs as the model drew them;
    ``starts``: the first jobs of the batches to make, every batch by default) while ``workers`` check the batches
    before; with ``files``, each checked batch's files are staged there, and ``finished(start, graphs, seconds)``
    gets its checked maps and each map's share of the time, batch after batch: a batch's time runs from the end of
    the batch before (the start, for the first) to the end of its own, so the maps' times add up to the run's. At
    most ``workers`` + 1 batches wait for their checks; a stop (an error, Ctrl-C) drops those still waiting."""
    waiting: deque = deque()
    since = time.perf_counter()
    with contextlib.ExitStack() as stack:
        if workers > 1:  # the jobs reach the workers through a file each reads: they start at once, side by side
            folder = _jobs_folder(stack)
            (folder / "jobs.pickle").write_bytes(pickle.dumps((jobs, settings, files), pickle.HIGHEST_PROTOCOL))
            executor = stack.enter_context(W.pool(workers, "spawn", _start, (str(folder / "jobs.pickle"),)))
            submit = lambda start, graphs: executor.apply_async(_in_worker, (start, graphs))  # noqa: E731
            result, ready = (lambda h: h.get()), (lambda h: h.ready())
        else:
            executor = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="cmtool-checks"))
            work = partial(_finish, jobs, settings, files)
            submit = lambda start, graphs: executor.submit(work, start, graphs)  # noqa: E731
            result, ready = (lambda h: h.result()), (lambda h: h.done())

        def collect() -> None:
            nonlocal since
            start, handle = waiting.popleft()
            graphs, contents = result(handle)
            if files is not None:
                files.add(*contents)
            now = time.perf_counter()
            finished(start, graphs, (now - since) / len(graphs))
            since = now

        for start in range(0, len(jobs), settings.batch) if starts is None else starts:
            waiting.append((start, submit(start, denoise(jobs[start:start + settings.batch], start))))
            while len(waiting) > workers or (len(waiting) > 1 and ready(waiting[0][1])):
                collect()
        while waiting:
            collect()


RUN_PREFIX = "cmtool-run-"  # the jobs' folders in the temporary folder: cmtool-run-PID-RANDOM


def _jobs_folder(stack: contextlib.ExitStack) -> Path:
    """A new temporary folder for the run's jobs file, named after this process and removed when ``stack`` ends;
    first the folders of runs whose process is gone (killed) are removed."""
    for old in Path(tempfile.gettempdir()).glob(f"{RUN_PREFIX}*-*"):
        pid = old.name[len(RUN_PREFIX):].split("-")[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=f"{RUN_PREFIX}{os.getpid()}-")))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        pass
    return True


_RUN: dict = {}  # in a worker process: the run's jobs, settings and files (:func:`_start`)


def _start(path: str) -> None:
    with open(path, "rb") as f:
        _RUN["jobs"], _RUN["settings"], _RUN["files"] = pickle.load(f)


def _in_worker(start: int, graphs: list[LaneGraph]):
    return _finish(_RUN["jobs"], _RUN["settings"], _RUN["files"], start, graphs)


def _finish(jobs: list[Job], settings: SampleSettings, files: MapFiles | None, start: int, graphs: list[LaneGraph]):
    """The checked maps of the batch of ``jobs`` from ``start`` and, with ``files``, their files' bytes."""
    batch = jobs[start:start + len(graphs)]
    check_maps(batch, graphs, settings)
    return graphs, files.contents(batch, graphs) if files is not None else None
