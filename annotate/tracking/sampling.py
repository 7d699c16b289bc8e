"""Bounding the points a step works on: every k-th row of an array."""

from __future__ import annotations

import numpy as np


def every_kth(rows: np.ndarray, count: int) -> np.ndarray:
    """``rows`` itself where it holds at most ``count`` rows (0: no limit), otherwise every k-th row, the fewest k
    that leaves at most ``count``. A crop's voxels and pixels come in a spatially scattered order, so every k-th
    keeps their spread."""
    n = len(rows)
    if count <= 0 or n <= count:
        return rows
    return rows[:: int(np.ceil(n / count))]
