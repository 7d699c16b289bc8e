"""A Dask distributed cluster as the engine (``--cluster ADDRESS``), and a local one for tests and benchmarks.

A cluster is a scheduler and workers on machines that see the data (sequences, documents, output folders) at
the same paths (a shared file system) and have this package installed at the same version::

    dask scheduler                                      # on one machine; prints tcp://HOST:8786
    dask worker tcp://HOST:8786 --nthreads $(nproc)     # on every machine that should work: a unit per core

A worker runs each unit as local processes do (batch.local.run_in_process): in a fresh process of its machine,
on one thread, with glibc's memory trimming as usual (the nanny's setting made the carving 2.1x slower), while
its task's thread waits; so the results do not depend on the engine, and a unit that crashes fails alone, its
worker unharmed. A worker that dies (its machine lost) has its units rescheduled elsewhere; after Dask's
``allowed-failures`` (3) such deaths a unit fails alone (KilledWorker).

Why Dask and not Ray (benchmarks/bench_batch.py --engines separate ray, the 2-core machine, the same units in a
fresh process on either, 1 and 2 workers, load 1.3-3.6): Ray 22.0 / 15.4 s (reconstruct, 6 sequences),
45.0 / 26.7 s (track), 26.1 / 17.0 s (evaluate); Dask 21.5 / 14.5, 46.4 / 27.6, 24.4 / 13.6: alike. Dask's cluster
started in 0.8-1.5 s, Ray's head in 3.1-4.2 s; Dask distributed installs as pure-Python wheels (33 MB with its
dependencies), Ray as an 80 MB binary wheel (244 MB installed) that starts a GCS server, a raylet and an object
store per machine: a dependency that makes ``make test`` on a 2-core CI slower and more fragile, for nothing
measured in return.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Callable, Iterator

from sequences.errors import InputError

from .local import Engine, run_in_process
from .units import error_line

#: How long to wait for the scheduler to answer, s.
CONNECT_TIMEOUT = "15s"


class ClusterPool(Engine):
    """Unit steps on a Dask cluster at ``address`` (:class:`batch.local.Engine`)."""

    def __init__(self, address: str, preload: tuple[str, ...] = ()) -> None:
        try:
            from distributed import Client, as_completed
        except ImportError as error:
            raise InputError(None, f"--cluster needs Dask distributed, which does not import here ({error})") from error
        self.address, self.preload = address, tuple(preload)
        try:
            self.client = Client(address, timeout=CONNECT_TIMEOUT, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as error:
            raise InputError(None, f"--cluster {address}: no Dask scheduler answers there ({error_line(error)})") from error
        self._done = as_completed(loop=self.client.loop)
        self._pending: dict[str, tuple[Any, Any]] = {}  # future key -> (token, future)

    def describe(self) -> str:
        try:
            workers = self.client.scheduler_info(n_workers=-1)["workers"].values()
            threads = sum(int(w.get("nthreads", 1)) for w in workers)
            return f"Dask cluster {self.address} ({threads} units at once on {len(workers)} worker{'s' if len(workers) != 1 else ''})"
        except Exception:  # the report's words only
            return f"Dask cluster {self.address}"

    def submit(self, token: Any, function: Callable, args: tuple, priority: int = 0) -> None:
        future = self.client.submit(run_in_process, function, args, self.preload, pure=False, priority=priority)
        self._pending[future.key] = (token, future)
        self._done.add(future)

    def next_result(self) -> tuple[Any, dict] | None:
        if self._done.is_empty():
            return None
        future = next(self._done)
        token, _ = self._pending.pop(future.key)
        try:
            result = future.result()
        except Exception as error:  # the cluster lost the unit (KilledWorker after repeated worker deaths, ...)
            result = {"ok": False, "error": f"the cluster lost it: {error_line(error)}", "input_error": False, "seconds": 0.0, "worker": None}
        future.release()
        return token, result

    def close(self) -> None:
        """Cancel what is still queued or running (an interrupt, an error in the client) and disconnect."""
        if self._pending:
            self.client.cancel([future for _, future in self._pending.values()], force=True)
            self._pending.clear()
        self.client.close()


@contextmanager
def local_cluster(workers: int) -> Iterator[str]:
    """A Dask cluster on this machine (one worker running ``workers`` units at once), its scheduler's address while open."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=workers, processes=True, dashboard_address=None, host="127.0.0.1") as cluster:
        yield cluster.scheduler_address
