"""``--json``: the command's report as one JSON object on stdout, and nothing else there.

While the command runs, :func:`json_stdout` sends everything written to stdout (this process's prints, a
library's, a worker process's: file descriptor 1 itself) to stderr, and gives back the real stdout for the
report. A command that fails before it has a report (bad input: exit 2) prints ``{"error": ...}`` there.
"""

from __future__ import annotations

import io
import json
import math
import os
import sys
from contextlib import contextmanager, redirect_stdout
from pathlib import Path
from typing import Iterator, TextIO


@contextmanager
def json_stdout(enabled: bool = True) -> Iterator[TextIO]:
    """Within the body stdout goes to stderr; yields the stream the report goes to (the real stdout)."""
    if not enabled:
        yield sys.stdout
        return
    real = sys.stdout
    real.flush()
    saved = None
    try:  # the descriptor too: C libraries and child processes write to fd 1, not to sys.stdout
        fd = real.fileno()
        saved = os.dup(fd)
        os.dup2(sys.stderr.fileno(), fd)
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):  # a stream without a descriptor (tests)
        saved = None
    target = os.fdopen(os.dup(saved), "w", encoding="utf-8", closefd=True) if saved is not None else real
    try:
        with redirect_stdout(sys.stderr):
            yield target
    finally:
        sys.stderr.flush()
        if saved is not None:
            os.dup2(saved, fd)
            os.close(saved)
            target.flush()
            target.close()


@contextmanager
def json_report(command: str, enabled: bool) -> Iterator[TextIO]:
    """:func:`json_stdout`, and where the body raises InputError (bad input), the report ``{"command", "error"}`` on
    the real stdout before the error goes on to its one-line message."""
    from sequences.errors import InputError

    with json_stdout(enabled) as stdout:
        try:
            yield stdout
        except InputError as error:
            if enabled:
                write_json({"command": command, "error": str(error)}, stdout)
            raise


def _plain(value):
    np = sys.modules.get("numpy")  # not imported here: without NumPy loaded, no value is a NumPy one
    if np is not None and isinstance(value, np.generic):
        return value.item()
    if np is not None and isinstance(value, np.ndarray):
        return value.tolist()
    if hasattr(value, "__fspath__"):
        return os.fspath(value)
    raise TypeError(f"not JSON-serialisable: {type(value)}")


def write_json(report: dict, stream: TextIO) -> None:
    """``report`` as one JSON line (NaN as null: strict JSON)."""
    text = json.dumps(_nan_to_none(report), default=_plain, allow_nan=False)
    stream.write(text + "\n")
    stream.flush()


def _nan_to_none(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nan_to_none(v) for v in value]
    return value


def output_files(top: Path) -> dict[str, bytes]:
    """What a batch wrote under ``top`` (a folder, or one file), as runs are compared: relative path -> bytes, sorted,
    without the batch's own bookkeeping (``.batch/``, the export lock) and with the reports' timings left out."""
    top = Path(top)
    files = sorted(p for p in top.rglob("*") if p.is_file()) if top.is_dir() else [top]
    out = {}
    for path in files:
        rel = path.relative_to(top).as_posix() if top.is_dir() else path.name
        if rel.startswith(".batch/") or rel == ".export.lock":
            continue
        data = path.read_bytes()
        if rel.startswith("reports/") and rel.endswith(".json"):
            report = json.loads(data)
            report.pop("timings", None)
            data = json.dumps(report, sort_keys=True).encode()
        out[rel] = data
    return out
