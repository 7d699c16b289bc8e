"""Shared rigid geometry: quaternions (x, y, z, w), 4x4 poses, oriented boxes, REDWOOD75 axis remapping.

A pose maps object coordinates to camera coordinates: p_cam = R p_obj + t (metres, OpenCV camera).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# REDWOOD75 raw object axes (raw x = ShapeNet z, raw y = -ShapeNet y, raw z = ShapeNet x): the data layer owns them
from sequences.axes import RAW_FROM_SHAPENET, SHAPENET_FROM_RAW, raw_to_shapenet_points, shapenet_to_raw_points  # noqa: F401

#: The 12 edges of a box, as index pairs into :func:`box_corners`.
BOX_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]])


def quat_to_matrix(quaternion) -> np.ndarray:
    """(..., 4) quaternions x, y, z, w to (..., 3, 3) rotation matrices."""
    return Rotation.from_quat(np.asarray(quaternion, dtype=np.float64)).as_matrix()


def matrix_to_quat(matrix) -> np.ndarray:
    """(..., 3, 3) rotation matrices to (..., 4) quaternions x, y, z, w (w >= 0)."""
    q = Rotation.from_matrix(np.asarray(matrix, dtype=np.float64)).as_quat()
    return q * np.where(q[..., 3:4] < 0, -1.0, 1.0)


def pose_matrix(position, orientation) -> np.ndarray:
    """4x4 object-to-camera transform from position (3,) m and quaternion (4,) x y z w."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(orientation)
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T


def pose_from_matrix(T) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), quaternion (4,) x y z w) of a 4x4 transform."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), matrix_to_quat(T[:3, :3])


def invert(T) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    T = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def rigid(T) -> np.ndarray:
    """A 4x4 transform whose 3x3 block is the rotation nearest (Frobenius) that of ``T``; translation kept.

    Products of rigid transforms drift off the rotations by rounding (1e-16 each); a recursion that inverts its
    own output by transposing (a constant-velocity prediction) amplifies that drift instead of cancelling it.
    """
    T = np.asarray(T, dtype=np.float64)
    if not np.all(np.isfinite(T[:3, :3])):
        return np.array(T, copy=True)  # nothing to make rigid: a failed pose stays failed (SVD would raise)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, copy=True)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return out


def transform(T, points) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def untransform(T, points) -> np.ndarray:
    """(N, 3) points given in the frame a rigid 4x4 ``T`` maps into, in the frame it maps from (camera -> object
    for a pose): ``transform(invert(T), points)``, without forming the inverse."""
    T = np.asarray(T, dtype=np.float64)
    return (np.asarray(points, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]


def box_corners(extents, T=None) -> np.ndarray:
    """(8, 3) corners of a box centred on the origin with full side lengths ``extents``.

    Corner i has sign (-1)^(bit) per axis: bit 2 for x, bit 1 for y, bit 0 for z (matches :data:`BOX_EDGES`).
    Transformed by ``T`` when given.
    """
    signs = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=np.float64) * 2 - 1
    corners = signs * (np.asarray(extents, dtype=np.float64) / 2)
    return corners if T is None else transform(T, corners)


def rotation_about_y(angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about +y."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def shapenet_to_raw_pose(T) -> np.ndarray:
    """Pose of the ShapeNet-axes object to the pose of the same object in REDWOOD75's raw axes."""
    out = np.array(T, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3] @ SHAPENET_FROM_RAW
    return out


def raw_to_shapenet_pose(T) -> np.ndarray:
    """Pose in REDWOOD75's raw object axes to the pose in ShapeNet axes (cpas_toolbox's remapping)."""
    out = np.array(T, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3] @ RAW_FROM_SHAPENET
    return out


def shapenet_to_raw_extents(extents) -> np.ndarray:
    e = np.asarray(extents, dtype=np.float64)
    return e[..., [2, 1, 0]]


def raw_to_shapenet_extents(extents) -> np.ndarray:
    e = np.asarray(extents, dtype=np.float64)
    return e[..., [2, 1, 0]]
