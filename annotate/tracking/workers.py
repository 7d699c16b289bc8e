"""Independent tracking work spread over processes: an ordered map whose results equal a plain loop's.

Tracking's per-frame work is numpy on a few thousand points at a time, which holds the GIL: two threads
measured 15-25 % more CPU for a 12 % shorter laptop run and slower small objects. Forked processes share
the parent's state as it is at the fork (frames read, models and their KD-trees built) without pickling
it; only the items' indices go out and the results (poses, figures) come back. Each item runs the same
code on the same inputs as in a loop, so the results are the same bit for bit whatever the count
(tests/test_tracking_workers.py, and bench_tracking's pose dumps compared frame by frame).

Forking needs Linux (elsewhere, or with one worker, the map is a plain loop), and Open3D on one thread in the
parent (the engine's default, ``TrackingConfig.threads``): an OpenMP thread pool does not survive a fork.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from typing import Callable, Iterable, Sequence, TypeVar

Item = TypeVar("Item")
Result = TypeVar("Result")

#: The function and items of the map under way, set before the fork: the workers inherit them.
_job: tuple[Callable, Sequence] | None = None
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


def ordered_map(function: Callable[[Item], Result], items: Iterable[Item], workers: int = 1, done: Callable[[Item, Result], None] | None = None) -> list[Result]:
    """``[function(item) for item in items]``, on up to ``workers`` forked processes where there are several items.

    ``function`` may be a closure over any state: the workers inherit it. Its result must pickle. ``done(item,
    result)`` is called in this process, in item order, as results arrive (progress). An exception raised by
    ``function`` is raised here.
    """
    global _job
    items = list(items)
    count = min(int(workers), len(items))
    if count <= 1 or _in_worker or not sys.platform.startswith("linux") or _job is not None:
        out = []
        for item in items:
            out.append(function(item))
            if done is not None:
                done(item, out[-1])
        return out
    _job = (function, items)
    try:
        with multiprocessing.get_context("fork").Pool(count, initializer=_mark_worker) as pool:
            out = []
            for item, result in zip(items, pool.imap(_call, range(len(items)))):
                out.append(result)
                if done is not None:
                    done(item, result)
            return out
    finally:
        _job = None
