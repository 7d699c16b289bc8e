"""Surface sampling of meshes and the per-object ground-truth shape index.

Chamfer distance and F-score compare point sets, so they depend on how many points are sampled from a
mesh (the REDWOOD75 paper shows the chamfer distance shrinking as the sample count grows): ``n`` is
therefore explicit everywhere, default 10000 as cpas_toolbox's ``num_gt_points``.  Sampling is
area-weighted (uniform over the surface) and seeded, so the same mesh, ``n`` and ``seed`` always give
the same points.

:class:`ShapeIndex` samples a ground-truth mesh once and builds its KD-tree once; every prediction and
every threshold of that object reuses it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

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
    return a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])


class ShapeIndex:
    """Ground-truth surface points of one object (object frame, metres) with their KD-tree, built once."""

    def __init__(self, points) -> None:
        self.points = points_array(points, "ShapeIndex points")
        self.tree = cKDTree(self.points, leafsize=_LEAF)

    @classmethod
    def from_mesh(cls, mesh, n: int = DEFAULT_SAMPLES, seed: int = 0) -> "ShapeIndex":
        """Sample ``n`` surface points of ``mesh`` (seeded) and index them."""
        return cls(sample_surface(mesh, n=n, seed=seed))

    def __len__(self) -> int:
        return len(self.points)

    def distances(self, points_pred: np.ndarray, upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(gt -> prediction, prediction -> gt) nearest-neighbour distances; both sets in this object's frame."""
        pred = points_array(points_pred, "points_pred")
        d_pred_to_gt = nearest_distances(pred, self.tree, upper_bound)
        # a midpoint-split tree builds ~3x faster; nearest distances do not depend on the tree shape
        d_gt_to_pred = nearest_distances(self.points, cKDTree(pred, leafsize=_LEAF, balanced_tree=False), upper_bound)
        return d_gt_to_pred, d_pred_to_gt

    def hits(self, points_pred, threshold: float) -> tuple[np.ndarray, np.ndarray]:
        """(gt points with a predicted point closer than ``threshold``, predicted points with a gt point
        closer than ``threshold``) as boolean arrays: exactly ``distances(...) < threshold``, faster.

        Points that share a cell of a grid with cells of diagonal just under ``threshold`` with a point of
        the other set are closer than ``threshold`` for sure; only the others need a KD-tree query.
        """
        if not np.isfinite(threshold) or threshold <= 0:
            raise ValueError(f"threshold must be a positive distance in metres, got {threshold}")
        pred = points_array(points_pred, "points_pred")
        hit_gt, hit_pred = _shared_cells(self.points, pred, threshold / np.sqrt(3) * (1 - 1e-9))
        bound = threshold * (1 + 1e-9)
        rest = np.flatnonzero(~hit_pred)
        if len(rest):
            hit_pred[rest] = nearest_distances(pred[rest], self.tree, bound) < threshold
        rest = np.flatnonzero(~hit_gt)
        if len(rest):
            hit_gt[rest] = nearest_distances(self.points[rest], cKDTree(pred, leafsize=_LEAF, balanced_tree=False), bound) < threshold
        return hit_gt, hit_pred

    def fscore(self, points_pred, threshold: float = 0.01) -> FScore:
        """F-score of predicted points (in this object's frame) at ``threshold`` m."""
        return fscore_from_hits(*self.hits(points_pred, threshold))

    def chamfer_distance(self, points_pred, squared: bool = False) -> float:
        """Chamfer distance (m, or m^2 if ``squared``) of predicted points in this object's frame."""
        return chamfer_from_distances(*self.distances(points_pred), squared)


def _shared_cells(a: np.ndarray, b: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Whether each point of ``a`` shares a grid cell (side ``cell``) with a point of ``b``, and vice versa."""
    ka, kb = np.floor(a / cell), np.floor(b / cell)
    lo = np.minimum(ka.min(axis=0), kb.min(axis=0))
    dims = np.maximum(ka.max(axis=0), kb.max(axis=0)) - lo + 1
    if np.prod(dims) >= 2.0**62:  # absurdly spread points: no shortcut
        return np.zeros(len(a), bool), np.zeros(len(b), bool)
    dims = dims.astype(np.int64)
    key_a = np.ravel_multi_index((ka - lo).astype(np.int64).T, dims)
    key_b = np.ravel_multi_index((kb - lo).astype(np.int64).T, dims)
    return np.isin(key_a, key_b), np.isin(key_b, key_a)
