"""Surface sampling of meshes and the per-object ground-truth shape index.

Chamfer distance and F-score compare point sets, so they depend on how many points are sampled from a
mesh (the REDWOOD75 paper shows the chamfer distance shrinking as the sample count grows): ``n`` is
therefore explicit everywhere, default 10000 as cpas_toolbox's ``num_gt_points``.  Sampling is
area-weighted (uniform over the surface) and seeded, so the same mesh, ``n`` and ``seed`` always give
the same points.

:class:`ShapeIndex` samples a ground-truth mesh once and builds its KD-tree once, and the cell grid of
its F-score test once per F-score distance; every prediction and every threshold of that object reuses
them.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from evaluate.metrics.hit_grid import CellGrid, HitGrid
from evaluate.metrics.shape_metrics import (
    FScore,
    chamfer_from_distances,
    fscore_from_hits,
    nearest_distances,
    points_array,
)

DEFAULT_SAMPLES = 10000
_LEAF = 32  # KD-tree leaf size: ~20 % faster nearest-neighbour queries than the default 16 on 10k points


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int) of a trimesh.Trimesh, open3d mesh or (V, F) pair."""
    if isinstance(mesh, tuple) and len(mesh) == 2:
        vertices, faces = mesh
    elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        vertices, faces = mesh.vertices, mesh.faces
    elif hasattr(mesh, "vertices") and hasattr(mesh, "triangles"):  # open3d.geometry.TriangleMesh
        vertices, faces = mesh.vertices, mesh.triangles
    else:
        raise ValueError("mesh: expected a trimesh.Trimesh, an open3d TriangleMesh or a (vertices, faces) pair")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
        raise ValueError(f"mesh: vertices must be finite (V, 3), got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"mesh: faces must be a non-empty (F, 3) index array, got shape {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError("mesh: face indices out of range")
    return vertices, faces.astype(np.int64)


def sample_surface(mesh, n: int = DEFAULT_SAMPLES, seed: int = 0) -> np.ndarray:
    """(n, 3) points uniformly distributed over the mesh surface (area-weighted), deterministic in ``seed``.

    Same frame and units as the mesh vertices.  Raises ValueError for a malformed mesh or zero area.
    """
    return sample_surface_faces(mesh, n, seed)[0]


def sample_surface_faces(mesh, n: int = DEFAULT_SAMPLES, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_surface`'s points (the same for the same ``seed``) and the face each lies on ((n,) indices)."""
    if int(n) != n or n < 1:
        raise ValueError(f"sample_surface: n must be a positive integer, got {n}")
    vertices, faces = mesh_arrays(mesh)
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = areas.sum()
    if not total > 0:
        raise ValueError("sample_surface: the mesh has zero surface area")
    rng = np.random.default_rng(seed)
    cumulative = np.cumsum(areas) / total
    tri = np.minimum(np.searchsorted(cumulative, rng.random(int(n)), side="right"), len(faces) - 1)
    u, v = rng.random((2, int(n)))
    flip = u + v > 1  # fold the unit square onto the triangle: uniform barycentric coordinates
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    return a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri]), tri


class ShapeIndex:
    """Ground-truth surface points of one object (object frame, metres) with their KD-tree, built once."""

    def __init__(self, points) -> None:
        self.points = points_array(points, "ShapeIndex points")
        # a midpoint-split tree builds ~40 % faster and answers these queries as fast (10k surface points)
        self.tree = cKDTree(self.points, leafsize=_LEAF, balanced_tree=False)
        self._grids: dict[float, HitGrid] = {}  # per F-score threshold, built on first use

    @classmethod
    def from_mesh(cls, mesh, n: int = DEFAULT_SAMPLES, seed: int = 0) -> "ShapeIndex":
        """Sample ``n`` surface points of ``mesh`` (seeded) and index them."""
        return cls(sample_surface(mesh, n=n, seed=seed))

    def __len__(self) -> int:
        return len(self.points)

    def distances(self, points_pred: np.ndarray, upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(gt -> prediction, prediction -> gt) nearest-neighbour distances; both sets in this object's frame."""
        pred = points_array(points_pred, "points_pred")
        d_pred_to_gt = nearest_distances(pred, self.tree, upper_bound, _workers(len(pred)))
        # a midpoint-split tree builds ~3x faster; nearest distances do not depend on the tree shape
        tree = cKDTree(pred, leafsize=_LEAF, balanced_tree=False)
        d_gt_to_pred = nearest_distances(self.points, tree, upper_bound, _workers(len(self.points)))
        return d_gt_to_pred, d_pred_to_gt

    def hits(self, points_pred, threshold: float) -> tuple[np.ndarray, np.ndarray]:
        """(gt points with a predicted point closer than ``threshold``, predicted points with a gt point
        closer than ``threshold``) as boolean arrays: exactly ``distances(...) < threshold``, faster.

        Cell grids (:mod:`evaluate.metrics.hit_grid`) decide most points: a predicted point in a cell
        within reach of a gt point's cell (the gt side dilated once per object and threshold), a gt
        point with a predicted point in a cell within its reach, and a predicted point outside the grid
        (more than ``threshold`` beyond the gt box along some axis: a miss).  Only the undecided points need a KD-tree query:
        predicted points against the prebuilt gt tree (each hit also settles its nearest gt point),
        then the gt points still undecided against a tree of just the predicted points near them.
        """
        if not np.isfinite(threshold) or threshold <= 0:
            raise ValueError(f"threshold must be a positive distance in metres, got {threshold}")
        pred = points_array(points_pred, "points_pred")
        return _hits(self.points, self.tree, self.prepare(threshold), pred, threshold)

    def prepare(self, threshold: float) -> HitGrid:
        """The cell grid :meth:`hits` uses at ``threshold`` m, built on first use and kept: once per
        object and F-score distance, for all its predictions."""
        grid = self._grids.get(threshold)
        if grid is None:
            grid = self._grids[threshold] = HitGrid(self.points, threshold, threshold * _CELL)
        return grid

    def fscore(self, points_pred, threshold: float = 0.01) -> FScore:
        """F-score of predicted points (in this object's frame) at ``threshold`` m."""
        return fscore_from_hits(*self.hits(points_pred, threshold))

    def chamfer_distance(self, points_pred, squared: bool = False) -> float:
        """Chamfer distance (m, or m^2 if ``squared``) of predicted points in this object's frame."""
        return chamfer_from_distances(*self.distances(points_pred), squared)


_PARALLEL_QUERIES = 1000  # fewer queries than this run on one thread
# Cell side as a fraction of the threshold: at threshold / 3.8 (57 offsets in reach) the grid certifies
# ~75 % of the predicted points' hits and ~90 % of the gt points' (10k-point surfaces, predictions off
# by ~1 cm); coarser cells leave more to the KD-tree, finer ones cost more to build than they save.
_CELL = 1 / 3.8


def _hits(points: np.ndarray, tree: cKDTree, grid: HitGrid, pred: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`ShapeIndex.hits` on a prepared grid."""
    if grid.built:
        hit_gt, hit_pred, far = grid.hits(pred)
    else:  # absurdly spread points: KD-trees alone
        hit_gt, hit_pred, far = np.zeros(len(points), bool), np.zeros(len(pred), bool), np.zeros(len(pred), bool)
    bound = threshold * (1 + 1e-9)  # the strict "< threshold" test stays exact
    rest = np.flatnonzero(~(hit_pred | far))
    if len(rest):
        d, nearest = tree.query(pred[rest], k=1, distance_upper_bound=bound, workers=_workers(len(rest)))
        hit_pred[rest] = d < threshold
        hit_gt[nearest[d < threshold]] = True  # a gt point closer than threshold to a prediction is a hit too
    rest = np.flatnonzero(~hit_gt)
    if len(rest):
        near = _points_near(pred, points[rest], threshold)
        if len(near):  # else no predicted point anywhere near: all of them miss
            # a midpoint-split tree builds ~3x faster; nearest distances do not depend on the tree shape
            sub = cKDTree(near, leafsize=_LEAF, balanced_tree=False)
            hit_gt[rest] = nearest_distances(points[rest], sub, bound, _workers(len(rest))) < threshold
    return hit_gt, hit_pred


def _workers(queries: int) -> int:
    """Threads for a KD-tree query: all cores when there are enough queries to pay for starting them."""
    return -1 if queries >= _PARALLEL_QUERIES else 1


def _points_near(points: np.ndarray, queries: np.ndarray, radius: float) -> np.ndarray:
    """The ``points`` that may lie within ``radius`` of some query point: the same nearest neighbours
    closer than ``radius`` as all ``points``.  A point that close lies in a query's cell or one of its
    26 neighbours on a grid of side ``radius``."""
    grid = CellGrid.around(queries, radius * (1 + 1e-9), 1)
    if grid is None:  # absurdly spread queries: keep them all
        return points
    cells = np.flatnonzero(grid.marked(grid.index(queries)))
    neighbours = grid.flat(np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3))
    return points[grid.marked((cells[:, None] + neighbours[None, :]).ravel())[grid.index(points)]]
