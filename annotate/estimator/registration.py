"""Robust point-to-plane ICP of a frame's points to the object model, with its information matrix.

The unknown is the pose T (object to camera). A frame point p (camera frame) seen in the object frame is
q = T^-1 p; it pairs with the nearest model point m (normal n) whose normal faces the same way (so a mug's outer
wall never pairs with its inner wall), within a distance that shrinks from coarse to fine. The residual is
r = n . (q - m). With T <- T Exp(d), d = (w, v) in the object frame (GTSAM's Pose3 tangent order and side),
q <- q - w x q - v, so dr/dd = -[q x n, n]. Gauss-Newton with Cauchy weights (IRLS) solves for d.

The information of the result, H / (sigma^2 * max(1, N / N_ind)) with H = sum w J^T J, is what the pose graph
weighs the registration by: sigma is the per-point noise, and N_ind caps how many points count as independent,
since the errors of neighbouring points (a model slightly off, the sensor's structured noise) are not.

Written on numpy and SciPy's cKDTree rather than Open3D's registration_icp because that pairs without the
facing test and returns no information matrix in this parametrisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .config import EstimatorConfig
from .observations import Crop

#: nearest model points searched for one that faces the same way
FACING_CANDIDATES = 2
#: an iteration moving the pose less than this (rad, m) ends the stage: 0.02 deg and 0.05 mm
CONVERGED = (3.5e-4, 5e-5)
#: weight of the point-to-point term beside the point-to-plane one (its residuals count this much, squared)
POINT_WEIGHT = 0.3
#: the Cauchy weight's scale, as a share of the stage's correspondence distance
CAUCHY_SHARE = 0.25


@dataclass
class Model:
    """The object's surface: points (M, 3) and unit normals (M, 3) in the object frame (m), a KD-tree on them."""

    points: np.ndarray
    normals: np.ndarray

    def __post_init__(self) -> None:
        self.tree = cKDTree(self.points) if len(self.points) else None

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class Registration:
    """A pose (4x4, object to camera), its information (6x6 over (w, v), object frame), the share of the frame's
    points paired within the fine distance (fitness), their RMS residual (m) and how many there were."""

    pose: np.ndarray
    information: np.ndarray
    fitness: float
    rmse: float
    pairs: int

    @property
    def ok(self) -> bool:
        return self.pairs >= 6


def retract(pose: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """T Exp(d) for d = (w, v) in the object frame (first order in the coupling of w and v)."""
    out = pose.copy()
    out[:3, :3] = pose[:3, :3] @ Rotation.from_rotvec(delta[:3]).as_matrix()
    out[:3, 3] = pose[:3, 3] + pose[:3, :3] @ delta[3:]
    return out


def _pairs(model: Model, q: np.ndarray, n: np.ndarray, distance: float, facing_cos: float) -> tuple[np.ndarray, np.ndarray]:
    """For each object-frame point q (N, 3) with normal n: the index of the nearest model point within ``distance``
    whose normal is within acos(facing_cos) of n, or -1."""
    k = min(FACING_CANDIDATES, len(model))
    dist, index = model.tree.query(q, k=k, distance_upper_bound=distance)
    dist, index = dist.reshape(len(q), k), index.reshape(len(q), k)
    found = np.isfinite(dist)
    safe = np.where(found, index, 0)
    facing = found & (np.einsum("nkj,nj->nk", model.normals[safe], n) >= facing_cos)
    first = np.argmax(facing, axis=1)
    chosen = safe[np.arange(len(q)), first]
    ok = facing[np.arange(len(q)), first]
    return np.where(ok, chosen, -1), dist[np.arange(len(q)), first]


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x (K, 3, 3) of vectors (K, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    return out - np.transpose(out, (0, 2, 1))


def _system(model: Model, q: np.ndarray, n: np.ndarray, distance: float, facing_cos: float, with_points: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The normal equations (H (6, 6), g (6,)) of the pairs, their point-to-plane residuals (K,) and Cauchy weights
    (K,), and the paired mask (N,).

    Beside the point-to-plane term, a point-to-point term of weight POINT_WEIGHT^2: on a surface that turns into
    itself (a shallow bowl is nearly a sphere) the planes leave the pose free to slide, and a model's rim then
    holds it back; the points' tangential offsets measure that slide. It helps the pose converge, but is no evidence
    of it (a cylinder's samples would "fix" its spin): ``with_points=False`` gives the planes' equations alone, which
    the information is made of."""
    index, _ = _pairs(model, q, n, distance, facing_cos)
    paired = index >= 0
    qp, m, nm = q[paired], model.points[index[paired]], model.normals[index[paired]]
    residual = np.einsum("nj,nj->n", nm, qp - m)
    jacobian = -np.hstack([np.cross(qp, nm), nm])
    scale = CAUCHY_SHARE * distance
    weight = 1.0 / (1.0 + (residual / scale) ** 2)
    H = (jacobian * weight[:, None]).T @ jacobian
    g = (jacobian * weight[:, None]).T @ residual
    if POINT_WEIGHT > 0 and len(qp) and with_points:
        # d(q - m)/d(w, v) = [[q]x, -I]: its normal equations in closed form
        w = POINT_WEIGHT**2 * weight
        e = qp - m
        sq = w @ np.einsum("ij,ij->i", qp, qp)
        top_left = sq * np.eye(3) - (qp * w[:, None]).T @ qp
        top_right = _skew((w @ qp)[None])[0]
        H = H + np.block([[top_left, top_right], [top_right.T, w.sum() * np.eye(3)]])
        g = g + np.concatenate([-(w @ np.cross(qp, e)), -(w @ e)])
    return H, g, residual, weight, paired


def offset(init: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """d = (w, v) with pose ~ init Exp(d) (object frame of ``init``); the rotation's log map, exact below 180 deg."""
    R = init[:3, :3].T @ pose[:3, :3]
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))
    w = axis / 2 if angle < 1e-6 else axis * angle / (2 * np.sin(angle))
    return np.concatenate([w, init[:3, :3].T @ (pose[:3, 3] - init[:3, 3])])


def register(crop: Crop, model: Model, init: np.ndarray, config: EstimatorConfig, prior: np.ndarray | None = None, coarse: bool = True) -> Registration:
    """The pose of ``crop`` (camera frame) against ``model`` (object frame), from ``init`` (object to camera).

    ``prior`` (6x6 information over (w, v)) holds the pose near ``init`` where the points leave a direction free (a
    mug's spin with its handle hidden): a maximum a posteriori registration, whose returned information is the
    points' alone. Without ``coarse`` only the fine stage runs (a start already within the fine distance).
    """
    init = np.asarray(init, dtype=np.float64)
    pose = init.copy()
    prior = np.zeros((6, 6)) if prior is None else prior
    if len(crop) < 6 or len(model) < 6:
        return Registration(pose, np.zeros((6, 6)), 0.0, np.inf, 0)
    for distance in config.icp_distances if coarse else config.icp_distances[-1:]:
        for _ in range(config.icp_iterations):
            q = (crop.points - pose[:3, 3]) @ pose[:3, :3]
            n = crop.normals @ pose[:3, :3]
            H, g, r, _, _ = _system(model, q, n, distance, config.facing_cos)
            if len(r) < 6:
                return Registration(pose, np.zeros((6, 6)), 0.0, np.inf, int(len(r)))
            scale = config.point_sigma**2 * max(1.0, len(r) / config.independent_points)
            H = H / scale + prior
            g = g / scale + prior @ offset(init, pose)
            delta = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)
            pose = retract(pose, delta)
            if np.linalg.norm(delta[:3]) < CONVERGED[0] and np.linalg.norm(delta[3:]) < CONVERGED[1]:
                break
    fine = config.icp_distances[-1]
    q = (crop.points - pose[:3, 3]) @ pose[:3, :3]
    n = crop.normals @ pose[:3, :3]
    H, _, r, w, paired = _system(model, q, n, fine, config.facing_cos, with_points=False)
    count = int(paired.sum())
    information = H / (config.point_sigma**2 * max(1.0, count / config.independent_points))
    rmse = float(np.sqrt(np.average(r**2, weights=w))) if count else np.inf
    return Registration(pose, information, count / len(crop), rmse, count)
