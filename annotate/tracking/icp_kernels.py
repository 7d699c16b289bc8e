"""The ICP's per-point loops, compiled (numba): the nearest-model-point bookkeeping and the correspondence pairs.

An ICP iteration on a laptop frame's 2,100 points ran some 60 numpy calls of a few microseconds each, and
that overhead, not the arithmetic, was most of the iteration outside the nearest-point searches (measured: 0.65 of 1.2 ms).
Each loop here is one pass over the points. The arithmetic that decides a result is written in the
order the numpy code and nanoflann use (squared distances as ``(dx*dx + dy*dy) + dz*dz``, the error
summed in source order); numba leaves out fused multiply-adds unless asked for ``fastmath``, so the
results are the same to the last bit. The bounds are certificates with a slack, so their own rounding
decides only when a point is searched again, never which model point it pairs with.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _squared(position: np.ndarray, i: int, model: np.ndarray, j: int) -> float:
    dx = position[i, 0] - model[j, 0]
    dy = position[i, 1] - model[j, 1]
    dz = position[i, 2] - model[j, 2]
    return (dx * dx + dy * dy) + dz * dz


@njit(cache=True, nogil=True)
def _rank(i: int, position: np.ndarray, model: np.ndarray, candidates: np.ndarray, best: np.ndarray, other: np.ndarray) -> float:
    """Renew point ``i``'s ``best`` (its nearest candidate, the first of equals) and ``other`` (its distance to the
    nearest of the others, m); return the squared distance to ``best``."""
    nearest, second, pick = np.inf, np.inf, -1
    for k in range(candidates.shape[1]):
        c = candidates[i, k]
        d = _squared(position, i, model, c)
        if d < nearest:
            second = min(second, nearest)
            nearest, pick = d, c
        else:
            second = min(second, d)
    best[i] = pick
    other[i] = np.sqrt(second)
    return nearest


@njit(cache=True, nogil=True)
def _settled(d2: float, bound: float, distance: float, slack: float) -> bool:
    """Whether a kept nearest point (squared distance ``d2``) decides the point's pair, all other model points lying
    at least ``bound`` away: it is nearer than all of them, or it and they are beyond the cut."""
    bound = bound - slack
    return np.sqrt(d2) < bound or (d2 >= distance * distance and bound >= distance)


@njit(cache=True, nogil=True)
def advance(query, distance, slack, position, clear, other, best, candidates, model, d2):
    """Move the points to ``query`` (N, 3): lower each point's bounds by its move, renew ``d2`` (N,) to its kept
    nearest point, re-rank the points that bound no longer settles; return the rows still unsettled (a new
    search decides them: :func:`searched`)."""
    n = query.shape[0]
    stale = np.empty(n, dtype=np.int64)
    count = 0
    for i in range(n):
        sx = query[i, 0] - position[i, 0]
        sy = query[i, 1] - position[i, 1]
        sz = query[i, 2] - position[i, 2]
        moved = np.sqrt(sx * sx + sy * sy + sz * sz) + slack
        clear[i] -= moved
        other[i] -= moved
        position[i, 0], position[i, 1], position[i, 2] = query[i, 0], query[i, 1], query[i, 2]
        d = _squared(position, i, model, best[i])
        if not _settled(d, min(other[i], clear[i]), distance, slack):
            d = _rank(i, position, model, candidates, best, other)
            if not _settled(d, clear[i], distance, slack):
                stale[count] = i
                count += 1
        d2[i] = d
    return stale[:count]


@njit(cache=True, nogil=True)
def searched(rows, distance, index, size, reach, candidates, clear, position, model, best, other, d2):
    """Take a k-nearest search of ``rows`` (nearest_grid.CellGrid.query: ``distance``, ``index`` (R, K + 1), missing
    neighbours at index ``size``): the first K are the candidates, the next one bounds every other model point
    (``reach`` where there is none)."""
    k = candidates.shape[1]
    for r in range(rows.shape[0]):
        i = rows[r]
        for j in range(k):
            candidates[i, j] = index[r, j]
        clear[i] = distance[r, k] if index[r, k] < size else reach
        d2[i] = _rank(i, position, model, candidates, best, other)


@njit(cache=True, nogil=True)
def pairs(d2, best, distance, facing, camera, normals, offsets):
    """The (K, 2) int32 pairs (row, model point) of the rows whose nearest model point lies strictly within
    ``distance`` (with ``facing``: and whose model normal faces a camera at ``camera``, object frame), in row order,
    and their squared distances summed in that order."""
    n = d2.shape[0]
    out = np.empty((n, 2), dtype=np.int32)
    cut = distance * distance
    count = 0
    error2 = 0.0
    for i in range(n):
        if not d2[i] < cut:
            continue
        b = best[i]
        # the sum written out in one order, as ModelTarget.facing has it
        if facing and not (normals[b, 0] * camera[0] + normals[b, 1] * camera[1]) + normals[b, 2] * camera[2] > offsets[b]:
            continue
        out[count, 0] = i
        out[count, 1] = b
        error2 += d2[i]
        count += 1
    return out[:count], error2
