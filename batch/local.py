"""The default engine: each unit step in a fresh process of this machine, at most N at once.

Fresh processes, not a pool of long-lived workers: a worker that dies (the out-of-memory killer, a crash in
native code) is known to have died running that unit and no other, which fails alone (a
``ProcessPoolExecutor`` breaks whole, failing every unit in flight); and every unit starts from the same state,
whatever ran before it. They fork from a server process (multiprocessing's ``forkserver``) that imported the
commands' modules once, so a unit starts in about 30 ms instead of the 2-3 s of importing numpy, SciPy, Open3D
and trimesh again (measured on the 2-core machine); the server is started without threads, so forking it is safe
where forking this process, with tqdm's and Open3D's threads running, is not.

One thread per unit: the server starts with OpenMP and the BLAS libraries on one thread (``UNIT_ENVIRONMENT``),
and its children inherit that; a command turns its own helper threads off in its units (the reconstruction's
frame decoding ahead). Results then do not depend on the worker count (Open3D's and BLAS's parallel sums add in
an order that varies with their threads), and N units use N cores.

A Dask worker runs its units the same way (:func:`run_in_process`, batch.cluster): in a fresh process of its
machine, forked from its own server, so that a unit runs in the same environment on every engine, and a unit
that crashes takes down its process, not the worker.
"""

from __future__ import annotations

import heapq
import itertools
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

from .units import run_step

#: Environment of the units' processes: OpenMP (Open3D, numba) and the BLAS libraries on one thread each, and
#: glibc's default trimming of freed memory (None: unset). Dask's nanny sets MALLOC_TRIM_THRESHOLD_ to 64 kB in
#: its workers, and the carving, which allocates and frees large arrays per frame, runs about twice as slow there.
UNIT_ENVIRONMENT = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
                    "MALLOC_TRIM_THRESHOLD_": None}
#: One server start at a time (a Dask worker runs several units on threads).
_server_lock = threading.Lock()


@contextmanager
def _environment(values: dict[str, str | None]) -> Iterator[None]:
    before = {key: os.environ.get(key) for key in values}
    for key, value in values.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value
    try:
        yield
    finally:
        for key, value in before.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@contextmanager
def _children_allowed() -> Iterator[None]:
    """Let this process start children even where it is a daemon: Dask's nanny starts its workers as daemonic
    processes, which multiprocessing forbids to have children (it could not end them at exit). A unit's process
    ends with its unit, and is joined here; were the worker killed, its forkserver exits, and the unit's process
    finishes its unit (whose output is written atomically) and exits."""
    config = multiprocessing.current_process()._config  # multiprocessing's only record of the flag
    if not config.get("daemon"):
        yield
        return
    with _server_lock:  # one thread at a time lifts and restores the flag
        config["daemon"] = False
        try:
            yield
        finally:
            config["daemon"] = True


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where known): the default worker count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def start_server(preload: Sequence[str]) -> multiprocessing.context.BaseContext:
    """The forkserver context, its server started (once per process) with ``preload`` imported, on one thread.

    Returns at once: the server imports ``preload`` on its own while this process goes on, and the first unit's
    start waits for it. A command calls this first thing (before its own imports and the work list), so that on
    two cores the server's imports (1-2 s) overlap the command's instead of following them."""
    context = multiprocessing.get_context("forkserver")
    from multiprocessing import forkserver

    with _server_lock, _environment(UNIT_ENVIRONMENT):
        context.set_forkserver_preload(list(preload))  # only read when the server starts (the first batch)
        forkserver.ensure_running()
    return context


def _child(connection, function: Callable, args: tuple) -> None:
    """A unit step's process: run it, send the result back (an unpicklable result is that step's error)."""
    result = run_step(function, args)
    try:
        connection.send(result)
    except Exception as error:  # the value does not pickle: say so instead of dying silently
        connection.send({"ok": False, "error": f"the unit's result could not be sent back ({error.__class__.__name__}: {error})",
                         "input_error": False, "seconds": result.get("seconds", 0.0), "worker": result.get("worker")})
    connection.close()


def _death(process) -> str:
    code = process.exitcode
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"its worker process was killed by {name} (the out-of-memory killer sends SIGKILL)"
    return f"its worker process ended without a result (exit code {code})"


class Engine:
    """What runs a batch's unit steps: ``submit(token, function, args, priority)`` queues a step;
    ``next_result()`` blocks until one finishes and returns ``(token, result)`` (:func:`batch.units.run_step`'s
    dict), or None when nothing is queued or running; ``describe()`` says where they run. A context manager:
    leaving it ends what still runs (``close``)."""

    def describe(self) -> str:
        raise NotImplementedError

    def submit(self, token: Any, function: Callable, args: tuple, priority: int = 0) -> None:
        raise NotImplementedError

    def next_result(self) -> tuple[Any, dict] | None:
        raise NotImplementedError

    def close(self) -> None:
        """End what still runs and drop what is queued."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Queued(Engine):
    """An engine that holds its steps in this process until it starts them: higher priority first, then in
    submission order."""

    def __init__(self) -> None:
        self._queue: list = []
        self._order = itertools.count()

    def submit(self, token: Any, function: Callable, args: tuple, priority: int = 0) -> None:
        heapq.heappush(self._queue, (-priority, next(self._order), token, function, args))

    def _pop(self) -> tuple[Any, Callable, tuple]:
        _, _, token, function, args = heapq.heappop(self._queue)
        return token, function, args

    def close(self) -> None:
        self._queue.clear()


class LocalPool(_Queued):
    """Unit steps on fresh local processes, at most ``workers`` at once (see the module notes and :class:`Engine`)."""

    def __init__(self, workers: int, preload: Sequence[str] = ()) -> None:
        super().__init__()
        self.workers = max(1, int(workers))
        self.preload = tuple(preload)
        self._context = None
        self._running: dict[Any, tuple[Any, multiprocessing.Process]] = {}  # connection -> (token, process)

    def describe(self) -> str:
        return f"{self.workers} local process{'es' if self.workers > 1 else ''}"

    def _start_queued(self) -> None:
        while self._queue and len(self._running) < self.workers:
            if self._context is None:
                self._context = start_server(self.preload)
            token, function, args = self._pop()
            receiver, sender = self._context.Pipe(duplex=False)
            process = self._context.Process(target=_child, args=(sender, function, args))  # not a daemon: a unit may start processes of its own
            with _children_allowed():
                process.start()
            sender.close()  # the child holds the other end: EOF here once it exits
            self._running[receiver] = (token, process)

    def next_result(self) -> tuple[Any, dict] | None:
        self._start_queued()
        if not self._running:
            return None
        ready = multiprocessing.connection.wait(list(self._running))
        connection = ready[0]
        token, process = self._running.pop(connection)
        try:
            result = connection.recv()
        except (EOFError, OSError):  # it died before sending anything
            process.join()
            result = {"ok": False, "error": _death(process), "input_error": False, "seconds": 0.0, "worker": f"pid {process.pid}"}
        else:
            process.join()
        connection.close()
        return token, result

    def close(self) -> None:
        """End what still runs (an interrupt, an error in the client) and drop what is queued."""
        super().close()
        for connection, (_, process) in list(self._running.items()):
            process.terminate()
        for connection, (_, process) in list(self._running.items()):
            process.join(5)
            if process.is_alive():
                process.kill()
                process.join()
            connection.close()
        self._running.clear()


def run_in_process(function: Callable, args: tuple, preload: Sequence[str] = ()) -> dict:
    """One unit step in a fresh process of this machine (a Dask worker's task: see the module notes); returns
    :func:`batch.units.run_step`'s dict, a dead process included."""
    with LocalPool(1, preload) as pool:
        pool.submit(None, function, args)
        return pool.next_result()[1]


class InlinePool(_Queued):
    """Unit steps in this process, one after another (:class:`Engine`): for work whose units are cheap to start here
    and dear to start elsewhere (``evaluate --workers 1``: a method's model loaded once)."""

    def describe(self) -> str:
        return "this process"

    def next_result(self) -> tuple[Any, dict] | None:
        if not self._queue:
            return None
        token, function, args = self._pop()
        return token, run_step(function, args)
