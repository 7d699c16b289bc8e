"""Exact k-nearest-neighbour search over a regular grid of cells, for point sets laid out like a voxel model.

The ICP's correspondence search asks for the few model points nearest to each of a frame's points, all
within a few centimetres. A model is voxel centroids, one per voxel: a grid of cells of about that size
holds a point or two each, and the nearest points of a query lie in the cells around its own. The search
visits the cells in shells of growing Chebyshev distance and stops once the k-th nearest point found is
nearer than any cell not yet visited can be (or than ``reach``), so its answer is the exact k nearest,
as scipy's KD-tree gives them (the same points and order but where two lie at the same distance).
Its speed against the KD-tree: see :class:`CellGrid`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: A grid of more cells than this takes coarser cells (a spread-out point set: memory and building time stay bounded).
MAX_CELLS = 1 << 22


class CellGrid:
    """The points (M, 3) sorted into cubic cells of side ``cell`` (m): a k-nearest search with a distance bound.

    Built in numpy in one pass (a sort of the cell numbers); a KD-tree of the same points costs more to build and
    about three times as much per query at a model's size (10,000 points, 5 neighbours per query).
    """

    def __init__(self, points: np.ndarray, cell: float) -> None:
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if not (cell > 0 and np.isfinite(cell)):
            raise ValueError(f"grid cell size must be positive and finite, got {cell}")
        self.points = points
        low = points.min(axis=0) if len(points) else np.zeros(3)
        high = points.max(axis=0) if len(points) else np.zeros(3)
        span = high - low
        while np.prod(np.floor(span / cell) + 1) > MAX_CELLS:
            cell *= 2.0
        self.cell = float(cell)
        self.origin = low
        self.dims = (np.floor(span / cell) + 1).astype(np.int64)
        index = np.minimum(np.floor((points - low) / cell).astype(np.int64), self.dims - 1)
        linear = (index[:, 0] * self.dims[1] + index[:, 1]) * self.dims[2] + index[:, 2]
        self.order = np.argsort(linear, kind="stable")
        self.starts = np.zeros(int(np.prod(self.dims)) + 1, dtype=np.int64)
        np.cumsum(np.bincount(linear, minlength=int(np.prod(self.dims))), out=self.starts[1:])

    def query(self, queries: np.ndarray, k: int, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """Per query point (Q, 3): the distances (Q, k) m, ascending, of its ``k`` nearest points strictly within ``reach``,
        and their indices (Q, k); a missing neighbour has distance inf and index M, as scipy's KD-tree reports it."""
        queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        distance = np.empty((len(queries), k))
        index = np.empty((len(queries), k), dtype=np.int64)
        _query(queries, int(k), float(reach), self.origin, self.cell, self.dims, self.starts, self.order, self.points, distance, index)
        return distance, index


@njit(cache=True, nogil=True)
def _visit(cell_id, q, queries, starts, order, points, top2, top):
    """Offer the points of one cell to the query's ``top`` (indices) and ``top2`` (squared distances), kept in order
    (equal distances: the lower index first)."""
    k = top.shape[0]
    for p in range(starts[cell_id], starts[cell_id + 1]):
        j = order[p]
        dx = queries[q, 0] - points[j, 0]
        dy = queries[q, 1] - points[j, 1]
        dz = queries[q, 2] - points[j, 2]
        d2 = (dx * dx + dy * dy) + dz * dz
        if d2 < top2[k - 1] or (d2 == top2[k - 1] and j < top[k - 1]):
            t = k - 1
            while t > 0 and (top2[t - 1] > d2 or (top2[t - 1] == d2 and top[t - 1] > j)):
                top2[t] = top2[t - 1]
                top[t] = top[t - 1]
                t -= 1
            top2[t] = d2
            top[t] = j


@njit(cache=True, nogil=True)
def _query(queries, k, reach, origin, cell, dims, starts, order, points, distance, index):
    m = points.shape[0]
    top2 = np.empty(k)
    top = np.empty(k, dtype=np.int64)
    shells = int(np.ceil(reach / cell)) + 1
    reach2 = reach * reach
    for q in range(queries.shape[0]):
        for j in range(k):
            top2[j] = np.inf
            top[j] = m
        # the distance from the query to the grid's box: reach or more, and nothing lies within reach
        outside2 = 0.0
        for a in range(3):
            gap = max(origin[a] - queries[q, a], queries[q, a] - (origin[a] + dims[a] * cell), 0.0)
            outside2 += gap * gap
        if outside2 < reach2:
            u0 = (queries[q, 0] - origin[0]) / cell
            u1 = (queries[q, 1] - origin[1]) / cell
            u2 = (queries[q, 2] - origin[2]) / cell
            c0, c1, c2 = int(np.floor(u0)), int(np.floor(u1)), int(np.floor(u2))
            # the distance (in cells) from the query to its own cell's nearest face
            face = min(u0 - c0, c0 + 1 - u0, u1 - c1, c1 + 1 - u1, u2 - c2, c2 + 1 - u2)
            for s in range(shells + 1):
                # the cells at Chebyshev distance s from the query's cell, within the grid, that may hold a point nearer
                # than the k-th found so far (and within reach): their box's distance from the query, in cells, decides
                limit = min(top2[k - 1], reach2) / (cell * cell)
                for x in range(max(c0 - s, 0), min(c0 + s, dims[0] - 1) + 1):
                    gx = max(x - u0, u0 - x - 1.0, 0.0)
                    gx *= gx
                    if gx > limit:
                        continue
                    for y in range(max(c1 - s, 0), min(c1 + s, dims[1] - 1) + 1):
                        gy = max(y - u1, u1 - y - 1.0, 0.0)
                        gxy = gx + gy * gy
                        if gxy > limit:
                            continue
                        row = (x * dims[1] + y) * dims[2]
                        if x == c0 - s or x == c0 + s or y == c1 - s or y == c1 + s:
                            for z in range(max(c2 - s, 0), min(c2 + s, dims[2] - 1) + 1):
                                gz = max(z - u2, u2 - z - 1.0, 0.0)
                                if gxy + gz * gz <= limit:
                                    _visit(row + z, q, queries, starts, order, points, top2, top)
                        else:  # inside the shell's x-y rim only its two z faces belong to it
                            for z in (c2 - s, c2 + s):
                                if 0 <= z < dims[2] and (z == c2 - s or s > 0):
                                    gz = max(z - u2, u2 - z - 1.0, 0.0)
                                    if gxy + gz * gz <= limit:
                                        _visit(row + z, q, queries, starts, order, points, top2, top)
                        limit = min(top2[k - 1], reach2) / (cell * cell)
                # every cell beyond shell s lies at least this far away (less a margin for rounding)
                bound = (s + face) * cell - 1e-12
                if bound >= reach or (bound > 0 and top2[k - 1] <= bound * bound):
                    break
        for j in range(k):
            if top2[j] < reach2 and top[j] < m:  # strictly within, as scipy's KD-tree has it
                distance[q, j] = np.sqrt(top2[j])
                index[q, j] = top[j]
            else:
                distance[q, j] = np.inf
                index[q, j] = m
