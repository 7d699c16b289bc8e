"""Dense cell grids that decide most "closer than r" tests of an F-score without a KD-tree (exactly).

A point lies in cell ``floor(p / s)`` of a grid with side ``s`` (m).  If two points lie in
cells ``c`` and ``c + o``, each coordinate differs by less than ``(|o_i| + 1) s``, so every pair of
points of the two cells is closer than ``r`` when ``sum(((|o_i| + 1) s)^2) < r^2``: those offsets
``o`` are the *reach* of the grid at ``r``.  A cell within reach of a cell holding a ground-truth
point holds only points that are hits.  The test is one-sided (a point outside the reach may still be
a hit) and exact: the distances it certifies are strictly below ``r`` with a relative margin of 1e-9,
far above floating-point rounding, so it never disagrees with a KD-tree's ``distance < r``.

Grids are dense boolean arrays over the ground-truth points' box, padded by the reach and by more
than ``r``: a query point outside the grid is a certain miss.  A grid over an absurdly large box (more than ``MAX_CELLS`` cells) is not
built; callers then fall back to KD-tree queries alone.
"""

from __future__ import annotations

import numpy as np

MAX_CELLS = 1 << 24  # 16 MB of booleans: a 1.6 m cube at 6.25 mm cells
#: Cell indices up to this: a coordinate's cell is computed with an error under 1e-9 cells, well
#: inside the 1e-9 relative margin of the certified distances (1 km from the origin at 1 mm cells).
MAX_INDEX = 1 << 20
_MARGIN = 1 - 1e-9  # certified distances stay below r * _MARGIN: exact despite rounding


def reach(cell: float, radius: float) -> np.ndarray:
    """(K, 3) int offsets o such that every point of cell c + o is closer than ``radius`` to every
    point of cell c (grid side ``cell``, metres); (0, 0, 0) first."""
    r = int(np.ceil(radius / cell))
    o = np.stack(np.meshgrid(*[np.arange(-r, r + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    o = o[(((np.abs(o) + 1) * cell) ** 2).sum(axis=1) < (radius * _MARGIN) ** 2]
    return o[np.argsort(np.abs(o).sum(axis=1), kind="stable")]


class CellGrid:
    """A dense grid of side ``cell`` (m) over the box lo..hi padded by ``pad`` cells.  Flat cell indices index a boolean array of ``size + 1`` entries whose last entry,
    index -1, stands for every point outside the grid (never marked)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, cell: float, pad: int) -> None:
        self.cell, self.pad = cell, pad
        # the same arithmetic as index(): the box's extreme points land exactly pad cells inside
        self.first = np.floor(lo * (1 / cell)) - pad
        self.dims = (np.floor(hi * (1 / cell)) + pad - self.first + 1).astype(np.int64)
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], dtype=np.int64)
        self.size = int(np.prod(self.dims.astype(np.float64)))

    @classmethod
    def around(cls, points: np.ndarray, cell: float, pad: int) -> "CellGrid | None":
        """The grid over ``points``' box padded by ``pad`` cells; None if it would exceed MAX_CELLS or
        lie so far from the origin (over MAX_INDEX cells) that rounding could misplace a point."""
        lo, hi = points.min(axis=0), points.max(axis=0)
        if max(np.abs(lo).max(), np.abs(hi).max()) / cell > MAX_INDEX:
            return None
        grid = cls(lo, hi, cell, pad)
        return grid if grid.size <= MAX_CELLS else None

    def index(self, points: np.ndarray) -> np.ndarray:
        """Flat cell index (int64) of each point; -1 for points outside the grid."""
        # per axis on contiguous rows: ~3x faster than on the short last axis of (N, 3)
        k = np.floor(np.ascontiguousarray(points.T) * (1 / self.cell))
        k -= self.first[:, None]
        clipped = np.clip(k, 0, (self.dims - 1)[:, None])  # a far point's index may not fit an int64
        outside = (k[0] != clipped[0]) | (k[1] != clipped[1]) | (k[2] != clipped[2])
        # exact in float64: flat indices stay below MAX_CELLS
        flat = (clipped[0] * self.strides[0] + clipped[1] * self.strides[1] + clipped[2]).astype(np.int64)
        flat[outside] = -1
        return flat

    def flat(self, offsets: np.ndarray) -> np.ndarray:
        """Flat index steps of (K, 3) cell offsets (valid from cells at least |o| from the border)."""
        return offsets.astype(np.int64) @ self.strides

    def marked(self, flat_indices: np.ndarray) -> np.ndarray:
        """Boolean array (size + 1): True at the given flat indices, never at -1 (outside)."""
        out = np.zeros(self.size + 1, dtype=bool)
        out[flat_indices] = True
        out[-1] = False
        return out


class HitGrid:
    """One object's points (e.g. its ground-truth surface samples) on a grid of side ``cell`` (m), built
    once per radius, to decide for many query sets (predictions) which pairs are closer than
    ``radius``, both ways: query points in a cell within reach of a point's cell (the points' cells
    dilated once by the reach), and points with a query point in a cell within their reach (one
    gather per point cell and offset, nearest offsets first, stopping for the cells already decided).
    Query points outside the grid are at least ``radius`` from every point along some axis."""

    def __init__(self, points: np.ndarray, radius: float, cell: float) -> None:
        self.offsets = reach(cell, radius)
        # pad so that the dilation never wraps and a query outside the grid is >= radius away
        pad = max(int(np.abs(self.offsets).max()), int(np.ceil(radius * (1 + 1e-9) / cell)) + 1)
        self.grid = CellGrid.around(points, cell, pad)
        if self.grid is None:
            return
        self.cells, self.inverse = np.unique(self.grid.index(points), return_inverse=True)
        self.steps = self.grid.flat(self.offsets)
        # every point cell is >= pad cells from the border: the flat steps never wrap
        self.near = self.grid.marked((self.cells[:, None] + self.steps[None, :]).ravel())

    @property
    def built(self) -> bool:
        return self.grid is not None

    def hits(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points certainly with a query point closer than the radius, queries certainly closer than
        the radius to a point, queries certainly not: outside the grid)."""
        index = self.grid.index(queries)
        occupied = self.grid.marked(index)
        points_hit = np.zeros(len(self.cells), dtype=bool)
        undecided = self.cells
        for group in np.array_split(self.steps, _GATHER_GROUPS):
            found = occupied[undecided[:, None] + group[None, :]].any(axis=1)
            points_hit[np.flatnonzero(~points_hit)[found]] = True
            undecided = undecided[~found]
            if len(undecided) == 0:
                break
        return points_hit[self.inverse], self.near[index], index < 0


_GATHER_GROUPS = 4  # the reach's offsets, nearest first, in this many gathers
