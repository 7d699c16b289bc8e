"""The options every batch command shares, checked in one wording: ``--workers N`` and ``--cluster ADDRESS``."""

from __future__ import annotations


def engine_problem(workers: int | None, cluster: str | None) -> str | None:
    """What is wrong with ``--workers`` and ``--cluster`` as given, in one line, or None."""
    if workers is not None and workers < 1:
        return f"--workers must be at least 1, got {workers}"
    if workers is not None and cluster:
        return "--workers and --cluster exclude each other: a cluster's workers are its own"
    return None
