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
