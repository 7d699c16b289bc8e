"""The ordered map over worker processes (annotate/workers.py): a plain loop's results, in order."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from annotate import workers
from annotate.tracking.config import TrackingConfig

needs_fork = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="worker processes are forked, on Linux only")


@needs_fork
def test_the_map_runs_on_other_processes_and_keeps_the_order():
    state = np.arange(1000.0)  # a closure over the parent's state: the workers inherit it, nothing is pickled out
    seen = []
    out = workers.ordered_map(lambda k: (k, float(state[k::7].sum()), os.getpid()), list(range(40)), 2, done=lambda item, r: seen.append(item))
    assert [r[0] for r in out] == list(range(40)) and seen == list(range(40))
    assert [r[1] for r in out] == [float(state[k::7].sum()) for k in range(40)]
    assert os.getpid() not in {r[2] for r in out}
    assert workers._job is None  # nothing left behind for the next map


def test_one_worker_or_one_item_is_a_plain_loop_in_this_process():
    for count, items in ((1, [1, 2, 3]), (4, [5])):
        out = workers.ordered_map(lambda k: (k * k, os.getpid()), items, count)
        assert out == [(k * k, os.getpid()) for k in items]


@needs_fork
def test_an_error_in_a_worker_reaches_the_caller():
    def fails_on_three(k: int) -> int:
        if k == 3:
            raise ValueError("frame 3 is bad")
        return k

    with pytest.raises(ValueError, match="frame 3 is bad"):
        workers.ordered_map(fails_on_three, range(6), 2)
    assert workers._job is None
    assert workers.ordered_map(lambda k: k + 1, range(3), 2) == [1, 2, 3]  # and the next map runs

    def missing_on_two(k: int) -> int:
        if k == 2:
            raise FileNotFoundError("frame 2 is gone")
        return k

    seen = []
    with pytest.raises(FileNotFoundError, match="frame 2 is gone"):
        workers.ordered_map(missing_on_two, range(6), 2, done=lambda item, result: seen.append(item))
    assert seen == [0, 1]  # an OSError of the function's own is not taken for a refused fork: nothing ran twice


@needs_fork
def test_a_map_inside_a_worker_runs_as_a_loop():
    outer = workers.ordered_map(lambda k: (os.getpid(), workers.ordered_map(lambda j: os.getpid(), range(3), 2)), range(2), 2)
    for pid, inner in outer:
        assert pid != os.getpid() and inner == [pid] * 3  # in the worker itself


def test_the_worker_count():
    assert workers.resolve(3) == 3
    assert 1 <= workers.resolve(0) <= 4
    assert TrackingConfig(workers=3).worker_count() == 3
    assert TrackingConfig(workers=3, threads=0).worker_count() == 1  # Open3D's thread pool does not survive a fork
    with pytest.raises(ValueError, match="workers must be 0"):
        TrackingConfig(workers=-1)


@needs_fork
def test_a_worker_that_dies_raises_instead_of_hanging():
    def dies_on_three(k: int) -> int:
        if k == 3:
            os._exit(1)  # as the out-of-memory killer would end it
        return k

    with pytest.raises(workers.WorkerDied, match="--workers 1"):
        workers.ordered_map(dies_on_three, range(8), 2)
    assert workers._job is None


@needs_fork
@pytest.mark.parametrize("refused", [1, 2])  # the first fork, or the second after one worker started
def test_no_fork_possible_runs_the_map_here_and_leaves_no_worker(monkeypatch, refused):
    import multiprocessing

    fork = multiprocessing.get_context("fork")

    class Refusing:
        made = 0

        def Process(self, *args, **kwargs):  # noqa: N802 (multiprocessing's name)
            Refusing.made += 1
            if Refusing.made >= refused:
                raise OSError(12, "Cannot allocate memory")
            return fork.Process(*args, **kwargs)

        def __getattr__(self, name):
            return getattr(fork, name)

    monkeypatch.setattr(workers.multiprocessing, "get_context", lambda method: Refusing())
    others = set(multiprocessing.active_children())  # a map of another test's tracking thread may still run
    out = workers.ordered_map(lambda k: (k, os.getpid()), range(4), 2)
    assert out == [(k, os.getpid()) for k in range(4)]
    assert set(multiprocessing.active_children()) <= others  # a worker left waiting would hold the interpreter at exit


def _children_ended(others: set, seconds: float = 10.0) -> bool:
    """Whether this process's children are only ``others`` within ``seconds``: a terminated worker may take a moment
    to be reaped on a loaded machine (CI, 2 cores), while a worker left waiting would stay for good."""
    import multiprocessing
    import time

    end = time.monotonic() + seconds
    while not set(multiprocessing.active_children()) <= others:
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


@needs_fork
def test_an_error_in_the_progress_callback_stops_the_map_at_once(tmp_path):
    import multiprocessing
    import time

    log = tmp_path / "ran.txt"

    def item(k: int) -> None:
        with open(log, "a") as out:  # one line per item that ran, from whichever worker
            out.write(f"{k}\n")
        time.sleep(0.05)

    def stop(item, result):
        raise KeyboardInterrupt  # the user pressed Ctrl-C while the bar updated

    others = set(multiprocessing.active_children())  # a map of another test's tracking thread may still run
    with pytest.raises(KeyboardInterrupt):
        workers.ordered_map(item, range(200), 2, done=stop)
    assert len(log.read_text().split()) < 100  # the items not yet started were dropped, not all run first
    assert _children_ended(others)


@needs_fork
def test_a_map_started_on_another_thread_meanwhile_runs_there_as_a_loop():
    import threading

    started, release = threading.Event(), threading.Event()
    inner: list = []

    def slow(k: int) -> int:
        return k

    def first_done(item, result):
        if item == 0:
            started.set()
            release.wait(10)  # hold the first map open while another thread maps

    first: list = []
    thread = threading.Thread(target=lambda: first.extend(workers.ordered_map(slow, range(4), 2, done=first_done)))
    thread.start()
    assert started.wait(30)
    inner.extend(workers.ordered_map(lambda k: (k, os.getpid()), range(3), 2))
    release.set()
    thread.join(30)
    assert not thread.is_alive() and first == [0, 1, 2, 3]
    assert inner == [(k, os.getpid()) for k in range(3)]  # here, not in the first map's workers
    assert workers.ordered_map(lambda k: os.getpid(), range(2), 2)[0] != os.getpid()  # and the lock is free again


@needs_fork
def test_a_task_pool_runs_each_batch_on_its_workers_as_a_loop_would():
    state = np.arange(500.0)
    steps = []
    with workers.TaskPool(lambda k, scale: (k, float(state[k::5].sum()) * scale, os.getpid()), 2) as pool:
        # each batch's arguments come from the one before, as a frame's starts from its predecessor's outcome
        scale = 1.0
        for k in range(6):
            out = pool.map([(k, scale), (k + 100, scale)])
            assert [r[:2] for r in out] == [(j, float(state[j::5].sum()) * scale) for j in (k, k + 100)]
            steps.append({r[2] for r in out})
            scale = out[0][1] % 7 + 1
        assert pool.map([]) == [] and pool.map([(1, 2.0)])[0][2] == os.getpid()  # a lone task runs here
        assert workers.ordered_map(lambda k: os.getpid(), range(3), 2) == [os.getpid()] * 3  # meanwhile a map is a loop
    assert os.getpid() not in set.union(*steps) and len(set.union(*steps)) <= 2  # the same two workers throughout
    assert workers._job is None and workers._forking.acquire(blocking=False)
    workers._forking.release()


def test_a_task_pool_of_one_worker_is_a_loop_here():
    with workers.TaskPool(lambda k: (k, os.getpid()), 1) as pool:
        assert pool.map([(1,), (2,)]) == [(1, os.getpid()), (2, os.getpid())]


@needs_fork
def test_a_task_pool_whose_worker_dies_raises_and_frees_the_lock():
    def dies_on_three(k: int) -> int:
        if k == 3:
            os._exit(1)
        return k

    with pytest.raises(workers.WorkerDied, match="--workers 1"):
        with workers.TaskPool(dies_on_three, 2) as pool:
            assert pool.map([(1,), (2,)]) == [1, 2]
            pool.map([(3,), (4,)])
    assert workers._job is None
    assert workers.ordered_map(lambda k: k + 1, range(3), 2) == [1, 2, 3]


@needs_fork
def test_workers_run_open3d_on_one_thread_whatever_the_callers_setting():
    # neither OpenMP nor TBB survives a fork: a worker forked from a process on two Open3D threads hung in TBB's
    # reduction of the ICP's normal equations (the test suite, twice on 2026-11-28)
    import open3d as o3d

    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(2)
    try:
        seen = workers.ordered_map(lambda _: (os.getpid(), o3d.utility.get_max_threads()), range(4), 2)
        assert {threads for _, threads in seen} == {1} and any(pid != os.getpid() for pid, _ in seen)
        assert o3d.utility.get_max_threads() == 2  # the caller's setting back afterwards
        with workers.TaskPool(lambda _: o3d.utility.get_max_threads(), 2) as pool:
            assert pool.map([(0,), (1,)]) == [1, 1]
        assert o3d.utility.get_max_threads() == 2
    finally:
        o3d.utility.set_max_threads(before)
