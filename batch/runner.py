"""Running a batch: skip the finished units, run the others on an engine, commit in order, report.

:func:`run_batch` is the one loop the three commands share. Every unit's first step goes to the engine at once
(the engine runs N at a time); a unit with an ordered second step (``Unit.commit``) takes it when every unit
before it has taken its own or failed, one at a time, ahead of the first steps still queued. The client writes a
unit's finished marker after its last step succeeded (:mod:`batch.units`), prints a line per unit as it ends
(above the progress bar), and returns the outcomes in the units' order.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Sequence

from tqdm import tqdm

from .units import Outcome, Unit, finished, write_marker

if TYPE_CHECKING:  # the engines import multiprocessing's and Dask's machinery: only when a batch runs
    from .local import Engine

#: The ordered steps' priority on the engine: ahead of the first steps still queued, so the order never waits long.
COMMIT_PRIORITY = 10


@dataclass
class Batch:
    """A batch's outcomes (in the units' order), its engine in words, and its wall time in seconds."""

    outcomes: list[Outcome]
    engine: str
    seconds: float
    extra: dict = field(default_factory=dict)

    @property
    def failed(self) -> list[Outcome]:
        return [o for o in self.outcomes if o.status == "failed"]

    def counts(self) -> dict[str, int]:
        return {status: sum(o.status == status for o in self.outcomes) for status in ("done", "skipped", "failed")}

    def as_dict(self) -> dict:
        """The report's batch part (``--json``)."""
        return {"engine": self.engine, "seconds": round(self.seconds, 3), "cpu_seconds": round(sum(o.cpu for o in self.outcomes), 3), **self.counts(),
                "units": [o.as_dict() for o in self.outcomes]}


def progress_bar(total: int, desc: str, noun: str, quiet: bool = False, initial: int = 0, log: bool = True) -> tqdm:
    """A bar with counts and time left on stderr: redrawn in place on a terminal; in a log (stderr not a terminal)
    a line every 5 s, or none without ``log``."""
    interactive = sys.stderr.isatty()
    return tqdm(total=total, initial=initial, desc=desc, unit=noun, file=sys.stderr, dynamic_ncols=True, disable=quiet or not (interactive or log),
                mininterval=0.1 if interactive else 5.0, smoothing=0.1)


def make_engine(workers: int, cluster: str | None, preload: Sequence[str] = (), inline: bool = False) -> Engine:
    """The engine: a Dask cluster at ``cluster``'s address, else this process (one worker and ``inline``), else
    ``workers`` local processes."""
    if cluster:
        from .cluster import ClusterPool

        return ClusterPool(cluster, tuple(preload))
    from .local import InlinePool, LocalPool

    return InlinePool() if inline and workers == 1 else LocalPool(workers, preload)


def run_batch(units: Sequence[Unit], *, workers: int = 1, cluster: str | None = None, redo: bool = False, desc: str = "batch",
              noun: str = "unit", quiet: bool = False, preload: Sequence[str] = (), describe: Callable[[Outcome], str] | None = None,
              inline: bool = False, engine: Engine | None = None) -> Batch:
    """Run ``units`` (see the module notes); a unit's failure is its outcome, never an exception here.

    ``workers``: local processes (without ``cluster``); ``cluster``: a Dask scheduler's address; ``redo``: run the
    finished units too; ``desc``, ``noun``: the progress bar's; ``preload``: modules the local processes import
    once; ``describe(outcome)``: the line printed when a unit is done (default: its key and time); ``inline``: one
    worker is this process (:class:`batch.local.InlinePool`); ``engine``: one made by the caller (tests), used
    instead of ``workers`` and ``cluster``.
    """
    start = time.perf_counter()
    outcomes: list[Outcome | None] = [None] * len(units)
    if not redo:
        for i, unit in enumerate(units):
            record = finished(unit)
            if record is not None:
                summary = record.get("summary") if isinstance(record.get("summary"), dict) else {}
                outcomes[i] = Outcome(unit.key, "skipped", 0.0, summary)
    skipped = [units[i].key for i, o in enumerate(outcomes) if o is not None]
    if skipped and not quiet:
        shown = ", ".join(skipped[:5]) + (f" and {len(skipped) - 5} more" if len(skipped) > 5 else "")
        tqdm.write(f"skipping {len(skipped)} finished unit{'s' if len(skipped) > 1 else ''} ({shown}); --redo runs them again", file=sys.stderr)
    todo = [i for i, o in enumerate(outcomes) if o is None]
    bar = progress_bar(sum(u.size for u in units), desc, noun, quiet, initial=sum(units[i].size for i in range(len(units)) if outcomes[i] is not None))
    engine = engine if engine is not None else make_engine(workers, cluster, preload, inline)
    words = engine.describe()  # before the run: a cluster's client is closed after it
    waiting: dict[int, tuple[dict, object, float]] = {}  # first steps done, their commit not started: (summary, value, seconds)
    first_summary: dict[int, dict] = {}  # the first step's summary of the unit committing
    committing = False
    next_commit = 0

    def end(i: int, outcome: Outcome) -> None:
        outcomes[i] = outcome
        bar.update(units[i].size)
        if outcome.status == "failed":
            bar.write(f"error: {outcome.error}" if outcome.summary.get("input_error") else f"error: {outcome.key}: {outcome.error}", file=sys.stderr)
        elif not quiet:
            bar.write(describe(outcome) if describe else f"{outcome.key}: done in {outcome.seconds:.1f} s", file=sys.stderr)

    cpu = [0.0] * len(units)

    def done(i: int, summary: dict, seconds: float, worker: str | None) -> None:
        try:
            write_marker(units[i], summary)
        except OSError as error:  # the output stands; only a rerun will not know that it is finished
            bar.write(f"warning: {units[i].key}: finished marker not written ({error}); a rerun repeats this unit", file=sys.stderr)
        end(i, Outcome(units[i].key, "done", seconds, summary, worker=worker, cpu=cpu[i]))

    def failed(i: int, error: str, input_error: bool, seconds: float, worker: str | None) -> None:
        end(i, Outcome(units[i].key, "failed", seconds, {"input_error": True} if input_error else {}, error, worker, cpu[i]))

    def advance_commits() -> None:
        """Start the next unit's ordered commit when every unit before it has ended (one commit at a time)."""
        nonlocal committing, next_commit
        while not committing and next_commit < len(units):
            i = next_commit
            if outcomes[i] is not None:  # skipped, failed, or done without a commit
                next_commit += 1
            elif i in waiting:
                summary, value, seconds = waiting.pop(i)
                first_summary[i] = summary
                engine.submit(("commit", i, seconds), units[i].commit, (value, *units[i].commit_args), COMMIT_PRIORITY)
                committing = True
                next_commit += 1
            else:
                return  # its first step still runs

    try:
        with engine:
            for i in todo:
                engine.submit(("work", i, 0.0), units[i].work, units[i].args)
            while True:
                advance_commits()
                item = engine.next_result()
                if item is None:
                    break
                (step, i, before), result = item
                seconds, worker = before + float(result.get("seconds", 0.0)), result.get("worker")
                cpu[i] += float(result.get("cpu", 0.0))
                if step == "commit":
                    committing = False
                    summary = first_summary.pop(i)
                if not result["ok"]:
                    failed(i, result.get("error") or "failed", bool(result.get("input_error")), seconds, worker)
                elif step == "commit":
                    done(i, {**summary, **(result["value"] or {})}, seconds, worker)
                elif units[i].commit is None:
                    done(i, dict(result["value"] or {}), seconds, worker)
                else:
                    value = result["value"]
                    if isinstance(value, tuple) and len(value) == 2 and isinstance(value[0], dict):
                        waiting[i] = (value[0], value[1], seconds)
                    else:
                        failed(i, "its first step returned no (summary, value) pair", False, seconds, worker)
    finally:
        bar.close()
    return Batch(list(outcomes), words, time.perf_counter() - start)
