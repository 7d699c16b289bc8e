"""Bounding the points a step works on: every k-th row of an array."""

from __future__ import annotations

import numpy as np


def every_kth(rows: np.ndarray, count: int) -> np.ndarray:
    """``rows`` itself where it holds at most ``count`` rows (0: no limit), otherwise every k-th row, the fewest k
    that leaves at most ``count``. A crop's voxels and pixels come in a spatially scattered order, so every k-th
    keeps their spread."""
    k = every_kth_stride(len(rows), count)
    return rows if k == 1 else rows[::k]


def every_kth_stride(n: int, count: int) -> int:
    """The k of :func:`every_kth` for ``n`` rows: 1 where ``n`` <= ``count`` (or ``count`` is 0)."""
    return 1 if count <= 0 or n <= count else int(np.ceil(n / count))
