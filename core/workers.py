"""Worker processes for independent units of work (the extraction's (rotation, LED) units).

:func:`usable_cores` is the default worker count: the cores this process may run on
(``os.sched_getaffinity``, which honours taskset and container CPU sets), not the
machine's. :func:`process_pool` starts workers with the ``spawn`` method (a fresh
interpreter: no lock or thread of the parent is inherited, unlike ``fork``) whose
native thread pools (BLAS, OpenMP, OpenCV) are limited to one thread each, so that
n workers use n cores instead of n times the thread count (oversubscription).
:func:`ordered_results` runs jobs in such a pool, at most a few ahead of the one the
caller is waiting for, and yields their results in job order, so a result that is
consumed as it comes bounds the parent's memory and the order never depends on the
worker count.
"""
from __future__ import annotations

import functools
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, ParamSpec, TypeVar

__all__ = ["usable_cores", "resolve_workers", "WorkerPool", "process_pool", "ordered_results", "single_threaded",
           "one_blas_thread", "in_one_blas_thread", "release_memory"]

_P = ParamSpec("_P")
_R = TypeVar("_R")


def usable_cores() -> int:
    """The number of cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):          # not on Linux
        return max(1, os.cpu_count() or 1)


def resolve_workers(workers: int | None) -> int:
    """``workers`` checked (an int >= 1), or :func:`usable_cores` for None."""
    from glossrig.core.errors import InputError

    if workers is None:
        return usable_cores()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"the number of worker processes must be an integer >= 1, got {workers!r}")
    return workers


def one_blas_thread():
    """A context in which this process's native BLAS / OpenMP pools run one thread
    (threadpoolctl; restored after): the project's one switch for small linear algebra.

    The fits, the calibration draws' refits and diagnose's causes solve tall n x k least
    squares (k <= ~15) and dot products of such vectors, where BLAS threads gain nothing and
    OpenBLAS's spinning threads cost much when the cores are shared. Measured on this 2-core
    machine under load: a 70k-sample, four-channel fit took 23 s with the default OpenBLAS
    threads, 3 s with one; diagnose's ``r @ r`` of 53 000 rows 8.2 ms of CPU against 0.02 ms; the
    fit's calibration component (24 draws x 4 channels, 20 000 rows) 6.0-6.2 CPU-s against 1.9-2.2
    (validation/uncertainty_coverage.md, section 4). One thread also leaves the other core free."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1)


def in_one_blas_thread(f: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator: each call of ``f`` runs under :func:`one_blas_thread` (its signature kept)."""
    @functools.wraps(f)
    def run(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with one_blas_thread():
            return f(*args, **kwargs)

    return run


def single_threaded() -> None:
    """Limit this process's native thread pools to one thread (a worker's initializer):
    BLAS/OpenMP through threadpoolctl, OpenCV through ``cv2.setNumThreads``."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:                        # optional at run time: the env vars above still apply
        pass
    import cv2

    cv2.setNumThreads(1)


@functools.lru_cache(maxsize=1)
def _malloc_trim() -> Callable[[int], Any] | None:
    """glibc's ``malloc_trim``, looked up once per process (None elsewhere)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    return getattr(libc, "malloc_trim", None)


def release_memory() -> None:
    """Give the heap's free memory back to the system (glibc ``malloc_trim``; nothing
    elsewhere): a worker that has just freed a large job's arrays would otherwise keep
    them resident, fragmented, while it runs the next."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


class WorkerPool(ProcessPoolExecutor):
    """A process pool that knows its number of ``workers`` (:func:`ordered_results` sizes
    its window by it)."""

    def __init__(self, workers: int, **kwargs):
        super().__init__(max_workers=workers, **kwargs)
        self.workers = workers

    def terminate(self) -> None:
        """Stop at once: terminate the worker processes (a running job is not waited for, as
        ``shutdown`` would) and shut the pool down. For an error or an interruption in the
        caller, whose workers' results are no longer wanted."""
        for proc in list((getattr(self, "_processes", None) or {}).values()):
            proc.terminate()
        self.shutdown(wait=True, cancel_futures=True)


def process_pool(workers: int) -> WorkerPool:
    """A pool of ``workers`` single-threaded (:func:`single_threaded`) spawned processes."""
    import multiprocessing

    return WorkerPool(workers, mp_context=multiprocessing.get_context("spawn"), initializer=single_threaded)


class InWorker:
    """``fn(*args, **kwargs)`` in one worker of :func:`process_pool`, started at construction,
    beside whatever the calling process does next (diagnose's frame-space causes, and its
    instrument causes on the Ward lobe, each beside the BRDF-space work of the caller: on a
    2-core machine the two then share the cores instead of taking turns). :meth:`result`
    waits for it and shuts the worker down; an interruption while waiting, or leaving the
    ``with`` block on an error, stops the worker instead of waiting for it."""

    def __init__(self, fn: Callable[..., Any], *args: Any, **kwargs: Any):
        self._pool = process_pool(1)
        self._future = self._pool.submit(fn, *args, **kwargs)

    def result(self) -> Any:
        try:
            out = self._future.result()
        except BaseException:
            self._pool.terminate()
            raise
        self._pool.shutdown()
        return out

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:          # an exception leaving the block goes on
        if exc[0] is not None:
            self._pool.terminate()
        else:
            self._pool.shutdown(wait=True, cancel_futures=True)


def ordered_results(pool: WorkerPool | None, fn: Callable[..., Any], jobs: Iterable[tuple],
                    ahead: int = 1, window: int | None = None) -> Iterator[Any]:
    """``fn(*job)`` for every job, yielded in job order. With a ``pool`` at most its
    worker count + ``ahead`` jobs (or ``window``, when given: 1 runs one job at a time,
    for jobs too large in memory to run side by side) are submitted beyond the results
    already yielded (bounding the results held at once); with None each job runs here
    when its result is asked for. An exception of a job is raised here, at its turn; the
    jobs not yet started are then cancelled."""
    if pool is None:
        for job in jobs:
            yield fn(*job)
        return
    limit = max(1, window) if window is not None else pool.workers + max(0, ahead)
    pending: deque[Future] = deque()
    it = iter(jobs)
    try:
        for job in it:
            pending.append(pool.submit(fn, *job))
            if len(pending) >= limit:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for f in pending:
            f.cancel()
