"""Edits of an oriented box, as pure functions: nudges, turns, face drags, fitting, upright snapping.

A box is (position (3,) m in the camera frame, orientation (4,) x y z w object to camera,
extents (3,) full side lengths along object x, y, z in m). Nudges, turns and face drags act
along the box's own axes, which is how an annotator thinks of them ("move it along its height"),
or along the camera's as the annotator sees them (:func:`nudge_camera`, :func:`turn_camera`: right, down and
away from the camera; after a flip the box's +z may point at the camera, the camera's axes stay put).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: Smallest side length a face drag or a fit may leave (m).
MIN_EXTENT = 0.002


def _rotation(orientation) -> np.ndarray:
    return Rotation.from_quat(np.asarray(orientation, dtype=np.float64)).as_matrix()


def nudge(position, orientation, axis: int, step: float) -> np.ndarray:
    """Position moved by ``step`` metres along the box's own ``axis`` (0 x, 1 y, 2 z)."""
    return np.asarray(position, dtype=np.float64) + _rotation(orientation)[:, axis] * step


def turn(orientation, axis: int, degrees: float) -> np.ndarray:
    """Orientation turned by ``degrees`` about the box's own ``axis`` (0 x, 1 y, 2 z): a typed angle, a step, a
    90 turn or a 180 flip."""
    rotvec = np.zeros(3)
    rotvec[axis] = np.radians(degrees)
    q = (Rotation.from_quat(np.asarray(orientation, dtype=np.float64)) * Rotation.from_rotvec(rotvec)).as_quat()
    return q * (1.0 if q[3] >= 0 else -1.0)


def nudge_camera(position, axis: int, step: float) -> np.ndarray:
    """Position moved by ``step`` metres as seen from the camera: ``axis`` 0 to the right (camera +x), 1 down
    (camera +y), 2 away from the camera along the ray through the box centre (so it stays on the same pixel)."""
    position = np.asarray(position, dtype=np.float64)
    if axis == 2:
        direction = position / np.linalg.norm(position)
    else:
        direction = np.eye(3)[axis]
    return position + direction * step


def turn_camera(orientation, axis: int, degrees: float) -> np.ndarray:
    """Orientation turned by ``degrees`` about the camera's ``axis`` (0 x right, 1 y down, 2 z the view) through
    the box centre: R' = R_axis R (the box turns as the annotator sees it, whatever way it faces)."""
    rotvec = np.zeros(3)
    rotvec[axis] = np.radians(degrees)
    q = (Rotation.from_rotvec(rotvec) * Rotation.from_quat(np.asarray(orientation, dtype=np.float64))).as_quat()
    return q * (1.0 if q[3] >= 0 else -1.0)


def drag_face(position, orientation, extents, axis: int, sign: int, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Move the face on side ``sign`` (+1/-1) of ``axis`` outward by ``distance`` m; the opposite face stays put.

    Returns the new (position, extents); the side never shrinks below :data:`MIN_EXTENT`.
    """
    extents = np.asarray(extents, dtype=np.float64).copy()
    new_side = max(extents[axis] + distance, MIN_EXTENT)
    moved = new_side - extents[axis]
    extents[axis] = new_side
    position = np.asarray(position, dtype=np.float64) + _rotation(orientation)[:, axis] * (sign * moved / 2)
    return position, extents


def fit_to_points(points, position, orientation, extents, margin: float = 0.01, trim: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Shrink or grow the box to the camera-frame ``points`` inside it (grown by ``margin`` m), keeping its orientation.

    ``trim`` drops that fraction of points at each end of every axis (sensor outliers). Returns the
    new (position, extents), or None when fewer than 10 points lie in the box.
    """
    R = _rotation(orientation)
    local = (np.asarray(points, dtype=np.float64) - np.asarray(position, dtype=np.float64)) @ R
    half = np.asarray(extents, dtype=np.float64) / 2 + margin
    local = local[np.all(np.abs(local) <= half, axis=1)]
    if len(local) < 10:
        return None
    lo = np.quantile(local, trim, axis=0) if trim > 0 else local.min(axis=0)
    hi = np.quantile(local, 1 - trim, axis=0) if trim > 0 else local.max(axis=0)
    new_extents = np.maximum(hi - lo, MIN_EXTENT)
    centre_local = (lo + hi) / 2
    return np.asarray(position, dtype=np.float64) + R @ centre_local, new_extents


def upright_about_y(position, orientation, up=None) -> np.ndarray:
    """Orientation of a y-symmetric box snapped to a canonical turn about its axis.

    The box's y axis is kept (or replaced by ``up``, a camera-frame direction, e.g. an axis
    estimated from the points, flipped to agree with the current y); the free turn about it is
    chosen so that object +z points as much as possible towards the camera, which makes the
    unobservable angle consistent across frames.
    """
    R = _rotation(orientation)
    y = R[:, 1] if up is None else np.asarray(up, dtype=np.float64)
    y = y / np.linalg.norm(y)
    if up is not None and np.dot(y, R[:, 1]) < 0:
        y = -y
    to_camera = -np.asarray(position, dtype=np.float64)
    z = to_camera - np.dot(to_camera, y) * y
    if np.linalg.norm(z) < 1e-9:  # looking straight along the axis: keep the current z
        z = R[:, 2] - np.dot(R[:, 2], y) * y
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    q = Rotation.from_matrix(np.stack([x, y, z], axis=1)).as_quat()
    return q * (1.0 if q[3] >= 0 else -1.0)
