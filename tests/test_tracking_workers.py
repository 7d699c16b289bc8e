"""The ordered map over worker processes (annotate/tracking/workers.py): a plain loop's results, in order."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from annotate.tracking import workers
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


@needs_fork
def test_a_map_inside_a_worker_runs_as_a_loop():
    inner = workers.ordered_map(lambda k: workers.ordered_map(lambda j: (j, os.getpid()), range(3), 2), range(2), 2)
    for rows in inner:
        assert len({pid for _, pid in rows}) == 1  # one process: the worker itself


def test_the_worker_count():
    assert workers.resolve(3) == 3
    assert 1 <= workers.resolve(0) <= 4
    assert TrackingConfig(workers=3).worker_count() == 3
    assert TrackingConfig(workers=3, threads=0).worker_count() == 1  # Open3D's thread pool does not survive a fork
