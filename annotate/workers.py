"""Independent tracking work spread over processes: an ordered map whose results equal a plain loop's, and a pool
kept for small batches that a sequential pass hands out one after another (TaskPool).

Tracking's per-frame work is numpy on a few thousand points at a time, which holds the GIL: threads cost more
CPU than they save. Forked processes share
the parent's state as it is at the fork (frames read, models and their search grids built) without pickling
it; only the items' indices go out and the results (poses, figures) come back. Each item runs the same
code on the same inputs as in a loop, so the results are the same bit for bit whatever the count
(tests/test_workers.py, test_tracking_suspects.py, test_tracking_engine.py).
That needs Open3D on one thread in every process: on two, its normal equations sum in a varying order (one
frame registered 30 times from the same start gave 25 different last bits).

Forking needs Linux (elsewhere, or with one worker, the map is a plain loop), and Open3D on one thread in the
parent (the engine's default, ``TrackingConfig.threads``; ``TrackingConfig.worker_count``): the workers inherit
the setting, and neither OpenMP nor TBB promises that a thread pool survives a fork. So a map or a pool holds
Open3D on one thread while its workers live (open3d_threads, below), whoever calls it: a worker forked from a
process that had run Open3D on two threads (a test calling the refinement directly) hung in TBB's reduction of the
ICP's normal equations, waiting for a thread it does not have.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
import os
import sys
import threading
import warnings
from contextlib import ExitStack, contextmanager
from typing import Callable, Iterable, Iterator, Sequence, TypeVar

import open3d as o3d

Item = TypeVar("Item")
Result = TypeVar("Result")

#: The function and items of the map under way, set before the fork: the workers inherit them.
_job: tuple[Callable, Sequence] | None = None
#: Held while a map's workers run.
_forking = threading.Lock()
#: True inside a worker: a map there runs as a loop (a pool's workers cannot have children).
_in_worker = False


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where known)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def resolve(workers: int, cap: int = 4) -> int:
    """A worker count: ``workers`` itself when >= 1, otherwise (0) the available cores, at most ``cap``."""
    return int(workers) if workers >= 1 else max(1, min(cap, available_cores()))


def _mark_worker() -> None:
    global _in_worker
    _in_worker = True


def _call(index: int):
    function, items = _job
    return function(items[index])


class WorkerDied(RuntimeError):
    """A worker process ended without a result (killed, say by the out-of-memory killer, or crashed)."""


_DIED = ("a tracking worker process died (killed, as by the out-of-memory killer, or crashed); "
         "tracking on one process (annotate --track --workers 1, TrackingConfig.workers = 1) avoids it")


def _may_fork(count: int) -> bool:
    """Whether ``count`` workers may be forked now, taking the fork lock if so (release it when the workers are done):
    one map or pool at a time forks (the workers read _job); one started meanwhile on another thread runs as a loop."""
    return count > 1 and not _in_worker and sys.platform.startswith("linux") and _forking.acquire(blocking=False)


def _new_pool(count: int) -> ProcessPoolExecutor:
    """A pool of ``count`` workers, forked at its first submit."""
    return ProcessPoolExecutor(count, mp_context=multiprocessing.get_context("fork"), initializer=_mark_worker)


@contextmanager
def _quiet_fork() -> Iterator[None]:
    """Around the submits that fork: Python 3.12+ warns of forking a process with threads (the browser app's, tqdm's
    monitor), and the workers run only the job's function and exit, touching no lock those threads may hold."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*fork.*", category=DeprecationWarning)
        yield


def ordered_map(function: Callable[[Item], Result], items: Iterable[Item], workers: int = 1, done: Callable[[Item, Result], None] | None = None) -> list[Result]:
    """``[function(item) for item in items]``, on up to ``workers`` forked processes where there are several items.

    ``function`` may be a closure over any state: the workers inherit it. Its result must pickle. ``done(item,
    result)`` is called in this process, in item order, as results arrive (progress). An exception raised by
    ``function`` or ``done`` is raised here (the items not yet started are dropped); a worker that dies raises
    :class:`WorkerDied` (no hang); where no process can be forked (out of memory or process slots), the map runs
    as a loop here.
    """
    global _job
    items = list(items)
    count = min(int(workers), len(items))
    if not _may_fork(count):
        return _loop(function, items, done)
    _job = (function, items)
    pool = None
    # the children alive before the pool: the pool's workers are the ones that come after (multiprocessing's public
    # record of a process's children; no other map forks meanwhile, _forking is held)
    others = set(multiprocessing.active_children())
    try:
        with _one_thread():
            try:
                pool = _new_pool(count)
                with _quiet_fork():
                    results = pool.map(_call, range(len(items)))  # submits every item: the workers are forked here
            except OSError:  # a fork refused (memory, process slots): end those already forked, and do the work here
                _abandon(pool, others)
                return _loop(function, items, done)
            try:
                out = []
                for item, result in zip(items, results):
                    out.append(result)
                    if done is not None:
                        done(item, result)
            except BrokenProcessPool as error:
                _abandon(pool, others)
                raise WorkerDied(_DIED) from error
            except BaseException:
                _abandon(pool, others)
                raise
            pool.shutdown()
            return out
    finally:
        _job = None
        _forking.release()


def _one_thread():
    """Open3D held on one thread (open3d_threads, below) while forked workers live: see the module doc."""
    return open3d_threads(1)


def _call_with(args: tuple):
    function, _ = _job
    return function(*args)


class TaskPool:
    """Forked workers kept for many small batches whose arguments are known only as the work goes on (a sequential
    pass that registers each frame from its predecessor's outcome: the starts of one frame run at once).

    ``function(*args)`` runs on the workers, which inherit it and all state as it is when the pool is made (make it
    after the state the tasks read, as for :func:`ordered_map`); the arguments go out and the results come back
    pickled, so keep both small (a frame id and a 4x4 pose). :meth:`map` returns what a loop would, in order.
    Use it as a context manager. Where there is one worker, or no fork (not Linux, inside a worker, another pool or
    map forking on another thread, a fork refused), the batches run as loops here; a worker that dies raises
    :class:`WorkerDied`.
    """

    def __init__(self, function: Callable, workers: int) -> None:
        self.function = function
        self.workers = int(workers)
        self._pool: ProcessPoolExecutor | None = None
        self._others: set = set()
        self._held = False

    def __enter__(self) -> "TaskPool":
        global _job
        if _may_fork(self.workers):
            self._held = True
            _job = (self.function, None)
            self._others = set(multiprocessing.active_children())
            self._single = ExitStack()
            try:
                self._single.enter_context(_one_thread())
                self._pool = _new_pool(self.workers)
            except OSError:
                self._pool = None
            except BaseException:
                self._release()
                raise
        return self

    def map(self, batch: Sequence[tuple]) -> list:
        """``[function(*args) for args in batch]``, the items of the batch at once on the workers."""
        batch = list(batch)
        if self._pool is None or len(batch) <= 1:
            return [self.function(*args) for args in batch]
        try:
            with _quiet_fork():
                futures = [self._pool.submit(_call_with, args) for args in batch]  # the first submit forks the workers
        except OSError:  # a fork refused: no pool from here on
            _abandon(self._pool, self._others)
            self._pool = None
            return [self.function(*args) for args in batch]
        try:
            return [future.result() for future in futures]
        except BrokenProcessPool as error:
            _abandon(self._pool, self._others)
            self._pool = None
            raise WorkerDied(_DIED) from error

    def __exit__(self, kind, error, trace) -> None:
        try:
            if self._pool is not None:
                if error is None:
                    self._pool.shutdown()
                else:
                    _abandon(self._pool, self._others)
        finally:
            self._pool = None
            if self._held:
                self._release()

    def _release(self) -> None:
        """Open3D's thread setting back and the fork lock freed (held since __enter__)."""
        global _job
        _job = None
        self._held = False
        try:
            self._single.close()
        finally:
            _forking.release()


def _abandon(pool: ProcessPoolExecutor | None, others: set) -> None:
    """Drop a pool's pending items and end its workers now (an error, or a fork that failed partway, whose
    forked workers nothing would ever end: the interpreter would wait for them at exit). ``others``: the children
    of this process alive before the pool was made, left alone."""
    if pool is None:
        return
    pool.shutdown(wait=False, cancel_futures=True)
    # two passes: a fresh clone's CI (2 cores) once still listed a worker after one pass (1 test of 445); whether it
    # was started late or slow to end was not found. No other pool forks meanwhile (_forking), so only this pool's
    # workers are new
    for _ in range(2):
        processes = [process for process in multiprocessing.active_children() if process not in others]
        for process in processes:
            process.terminate()
        for process in processes:
            process.join(5)


def counting(progress: Callable[[int, int], None] | None, total: int) -> Callable[[object, object], None] | None:
    """A ``done`` callback for :func:`ordered_map` that reports (items done, ``total``) to ``progress`` (None: none)."""
    if progress is None:
        return None
    count = iter(range(1, total + 1))
    return lambda *_: progress(next(count), total)


def _loop(function: Callable[[Item], Result], items: list[Item], done: Callable[[Item, Result], None] | None) -> list[Result]:
    out = []
    for item in items:
        out.append(function(item))
        if done is not None:
            done(item, out[-1])
    return out


@contextmanager
def open3d_threads(count: int) -> Iterator[None]:
    """Run the body with Open3D limited to ``count`` threads (0: leave as is), restoring the setting after.

    One thread makes tracking reproducible: Open3D's parallel reductions (ICP normal equations)
    sum in a varying order, and the chains amplify those last-bit differences into different poses.

    The setting is one per process, and the browser tool may refine a frame while a track runs on another
    thread: the lowest count of the bodies running holds until the last of them ends, and only then comes the
    setting from before the first (restoring on each exit let the end of a refinement put a running track back
    on every thread, and its worker processes would fork from there: below).
    """
    global _threads_before
    if count <= 0:
        yield
        return
    count = int(count)
    with _threads_lock:
        if not _thread_limits:
            _threads_before = o3d.utility.get_max_threads()
        _thread_limits.append(count)
        o3d.utility.set_max_threads(min(_thread_limits))
    try:
        yield
    finally:
        with _threads_lock:
            _thread_limits.remove(count)
            o3d.utility.set_max_threads(min(_thread_limits) if _thread_limits else _threads_before)


#: The counts of the :func:`open3d_threads` bodies running now (any thread), and Open3D's setting before the first.
_thread_limits: list[int] = []
_threads_before = 0
_threads_lock = threading.Lock()
