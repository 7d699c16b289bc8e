"""A batch's unit of work: what a worker runs, and how a rerun knows that the unit finished.

A :class:`Unit` is a module-level function with its arguments (pickled by reference: a worker on another machine
imports the same function from the same installed package), a key naming it in messages, and optionally a
finished marker. The function writes the unit's output atomically itself (a document saved by rename, an export
swapped in as one transaction) and returns a small summary (JSON-able: the report's), or raises: an InputError is
the unit's one-line error, anything else a bug reported with its class. Neither ends the batch.

Finished, defined once: the unit's marker file exists and records the state found now. The marker is a small
JSON file written atomically by the client after the unit's output is complete (so a kill at any moment before
leaves no marker, and the unit runs again); its ``state`` is a fingerprint of what the output was made from and
of the options, returned by the unit's function as ``summary["state"]`` and recomputed by ``Unit.state()`` on a
rerun. A document edited since, another option, or an export that lost the unit's entry gives another state (or
None), and the unit runs again.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from sequences.atomic import write_text_atomic
from sequences.errors import InputError

#: The longest error line kept from an unexpected exception (a bug's message can be pages long).
ERROR_CHARS = 300


@dataclass(frozen=True)
class Unit:
    """One independent piece of a batch (see the module notes).

    ``work(*args)`` returns the summary (or, with ``commit``, a (summary, value) pair whose value goes to the
    commit). ``commit(value, *commit_args)``: an optional second step that the units take one at a time, in their
    order (an export whose numbering must not depend on which unit finished first); it returns the summary.
    ``marker``: the finished marker's path (None: the unit always runs); ``state()``: the state now, computed by
    the client (None: not finished). ``size``: what the unit counts for in the progress bar (samples of a chunk).
    """

    key: str
    work: Callable[..., Any]
    args: tuple = ()
    marker: Path | None = None
    state: Callable[[], str | None] | None = None
    commit: Callable[..., dict] | None = None
    commit_args: tuple = ()
    size: int = 1


@dataclass
class Outcome:
    """What became of a unit: ``status`` is "done", "skipped" (finished by an earlier run) or "failed"."""

    key: str
    status: str
    seconds: float = 0.0
    summary: dict = field(default_factory=dict)
    error: str | None = None
    worker: str | None = None
    cpu: float = 0.0  # CPU seconds of the unit's steps (all their threads): what the unit costs on an idle machine

    def as_dict(self) -> dict:
        entry = {k: v for k, v in self.summary.items() if k not in ("state", "input_error")}
        entry.update({"unit": self.key, "status": self.status, "seconds": round(self.seconds, 3), "cpu_seconds": round(self.cpu, 3),
                      "error": self.error, "worker": self.worker})
        return entry


def error_line(error: BaseException) -> str:
    """An exception as one line: an InputError's own (it names the file), any other's class and message."""
    if isinstance(error, InputError):
        return str(error)
    return " ".join(f"{error.__class__.__name__}: {error}".split())[:ERROR_CHARS]


def run_step(function: Callable[..., Any], args: tuple) -> dict:
    """Run one step on a worker; never raises (exceptions do not all pickle: InputError's do not), returns
    ``{"ok", "value" | "error", "input_error", "seconds", "cpu", "worker"}``."""
    start, cpu = time.perf_counter(), time.process_time()  # the CPU time of this process, all its threads
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        value = function(*args)
    except KeyboardInterrupt:
        raise
    except BaseException as error:  # a unit's bug, or its SystemExit, is that unit's failure, not the worker's end
        return {"ok": False, "error": error_line(error), "input_error": isinstance(error, InputError),
                "seconds": time.perf_counter() - start, "cpu": time.process_time() - cpu, "worker": worker}
    return {"ok": True, "value": value, "seconds": time.perf_counter() - start, "cpu": time.process_time() - cpu, "worker": worker}


def sha256_text(*parts: Any) -> str:
    """A fingerprint of JSON-able parts (options, names) and bytes (file contents), in order."""
    digest = hashlib.sha256()
    for part in parts:
        data = part if isinstance(part, bytes) else json.dumps(part, sort_keys=True, default=str).encode("utf-8")
        digest.update(len(data).to_bytes(8, "little"))
        digest.update(data)
    return digest.hexdigest()


def file_bytes(path: str | Path) -> bytes | None:
    """A file's bytes, None when it cannot be read."""
    try:
        return Path(path).read_bytes()
    except OSError:
        return None


def listing(folder: str | Path, subfolders: tuple[str, ...]) -> list:
    """The files of ``folder``'s ``subfolders`` as (relative path, size, modification time in ns), sorted: a cheap
    fingerprint of a sequence's frames (a frame replaced or added changes it)."""
    folder = Path(folder)
    entries = []
    for sub in subfolders:
        try:
            with os.scandir(folder / sub) as scan:
                for entry in scan:
                    if entry.is_file():
                        info = entry.stat()
                        entries.append((f"{sub}/{entry.name}", info.st_size, info.st_mtime_ns))
        except OSError:
            continue
    return sorted(entries)


def read_marker(path: Path) -> dict | None:
    """A finished marker's record, None when absent or unreadable (then the unit is not finished)."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def finished(unit: Unit) -> dict | None:
    """The marker's record when ``unit`` is finished (see the module notes), else None."""
    if unit.marker is None or unit.state is None:
        return None
    record = read_marker(unit.marker)
    if record is None or not isinstance(record.get("state"), str):
        return None
    try:
        now = unit.state()
    except (OSError, ValueError, InputError):  # an input that cannot be read now: run the unit, it says why
        return None
    return record if now is not None and now == record["state"] else None


def write_marker(unit: Unit, summary: dict) -> None:
    """Record ``unit`` as finished (atomically; called after its output is complete). A unit without a state in
    its summary gets no marker (it will run again)."""
    if unit.marker is None or not isinstance(summary.get("state"), str):
        return
    record = {"unit": unit.key, "state": summary["state"], "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
              "summary": {k: v for k, v in summary.items() if k != "state"}}
    write_text_atomic(unit.marker, json.dumps(record, indent=1, default=str) + "\n")
