"""Objects symmetric about their y axis: a consistent rotation about the axis, and the axis from the points.

For ``symmetry: y`` the rotation about the object's y axis is unobservable: registration may
return any of them. :func:`closest_about_y` picks, among the equivalent rotations, the one
closest to a reference (the previous frame's), so poses stay continuous.

:func:`estimate_symmetry_axis` fits the axis of a surface of revolution: every surface normal
line of such a surface meets the axis (Pottmann & Randrup's line-geometry test). With the axis
as a Plücker line (direction a, moment a_bar = c x a) and a normal line (n_i, m_i = p_i x n_i),
meeting means n_i . a_bar + m_i . a = 0: a linear least-squares problem, solved with |a| = 1
and reweighted to shrug off outliers (the hand).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from evaluate.geometry import rotation_about_y


def closest_about_y(rotation: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``rotation @ Ry(theta)`` (3x3) with theta chosen to be closest (Frobenius / geodesic) to ``reference``."""
    M = reference.T @ rotation
    # trace(M Ry(theta)) = cos(theta) (M00 + M22) + sin(theta) (M20 - M02) + M11 is maximal at:
    theta = np.arctan2(M[2, 0] - M[0, 2], M[0, 0] + M[2, 2])
    return rotation @ rotation_about_y(theta)


def fit_axis_point(points: np.ndarray, normals: np.ndarray, axis, iterations: int = 5) -> tuple[np.ndarray, float]:
    """The point (3,) nearest the origin of the symmetry axis whose direction ``axis`` (3,) is known, of a surface of
    revolution sampled by ``points`` (N, 3) m with unit ``normals`` (N, 3), and the RMS residual (m) of the normal-line
    test (see the module doc). :func:`fit_symmetry_axis` with the direction held: where the shape leaves the direction
    free (a sphere's normal lines all meet at its centre), a known direction still fixes the line's place. The same
    Cauchy reweighting shrugs off outliers (the hand). Raises ValueError with fewer than 20 finite points."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1) & np.all(np.isfinite(normals), axis=1)
    points, N = points[finite], normals[finite]
    if len(points) < 20:
        raise ValueError(f"too few points ({len(points)}) to place a symmetry axis")
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    centre = points.mean(axis=0)
    Ma = np.cross(points - centre, N) @ a
    w = np.ones(len(points))
    for _ in range(iterations):
        sw = np.sqrt(w)
        moment = -np.linalg.lstsq(N * sw[:, None], Ma * sw, rcond=None)[0]
        w = _cauchy_weights(N @ moment + Ma)
    return _nearest_axis_point(a, moment, centre), float(np.sqrt(np.mean((N @ moment + Ma) ** 2)))


def _cauchy_weights(residuals: np.ndarray) -> np.ndarray:
    """Cauchy weights (N,) of the normal-line residuals (N,) m, scaled by their robust spread (MAD)."""
    scale = 1.4826 * np.median(np.abs(residuals)) + 1e-6
    return 1.0 / (1.0 + (residuals / (2.0 * scale)) ** 2)


def _nearest_axis_point(axis: np.ndarray, moment: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The point (3,) nearest the origin of the line with unit direction ``axis`` and moment ``moment`` about ``centre``."""
    point = np.cross(axis, moment) + centre  # a x (c x a) = c for c perpendicular to a
    return point - axis * (axis @ point)


def estimate_symmetry_axis(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    initial_axis=(0.0, 1.0, 0.0),
    normal_radius: float = 0.012,
    iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Axis of rotational symmetry of a surface sampled by ``points`` (N, 3) m: (direction, point, RMS residual).

    See :func:`fit_symmetry_axis`, which also says how well the direction is determined.
    """
    return fit_symmetry_axis(points, normals, initial_axis, normal_radius, iterations)[:3]


def fit_symmetry_axis(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    initial_axis=(0.0, 1.0, 0.0),
    normal_radius: float = 0.012,
    iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Axis of rotational symmetry of a surface sampled by ``points`` (N, 3) m (object or any frame).

    Returns (unit direction (3,), signed to agree with ``initial_axis``; the point of the axis
    closest to the origin (3,); RMS residual of the normal-line test in metres; conditioning).
    ``conditioning`` is the ratio of the smallest to the second-smallest singular value of the
    direction problem: near 0 the direction is sharply determined, near 1 another direction fits
    almost as well (a shallow bowl is nearly a sphere, whose normal lines all meet at its centre,
    so any axis through the centre fits: measured 0.2 on a synthetic bowl against 0.06-0.08 on a
    bottle and a can, whose axes came out 2.7 deg and 0.3-0.5 deg off). Normals are
    estimated (radius ``normal_radius``) when not given. Raises ValueError with fewer than 20
    finite points.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        finite &= np.all(np.isfinite(normals), axis=1)
        normals = normals[finite]
    points = points[finite]
    if len(points) < 20:
        raise ValueError(f"too few points ({len(points)}) to estimate a symmetry axis")
    if normals is None:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=30))
        normals = np.asarray(cloud.normals)
    centre = points.mean(axis=0)  # work about the centroid: the moment terms stay small and well scaled
    p = points - centre
    M = np.cross(p, normals)
    N = normals
    w = np.ones(len(p))
    axis = np.asarray(initial_axis, dtype=np.float64)
    axis /= np.linalg.norm(axis)
    moment = np.zeros(3)
    for _ in range(iterations):
        sw = np.sqrt(w)[:, None]
        Q, _ = np.linalg.qr(N * sw)
        Mw = M * sw
        A = Mw - Q @ (Q.T @ Mw)  # remove what the moment can explain: residual as a function of the direction alone
        _, singular, vt = np.linalg.svd(A, full_matrices=False)
        axis = vt[-1]
        moment = -np.linalg.lstsq(N * sw, Mw @ axis, rcond=None)[0]
        w = _cauchy_weights(N @ moment + M @ axis)  # the residuals: metres, a distance-like misfit of each normal line
    if axis @ np.asarray(initial_axis, dtype=np.float64) < 0:
        axis, moment = -axis, -moment
    point = _nearest_axis_point(axis, moment, centre)
    rms = float(np.sqrt(np.mean((N @ moment + M @ axis) ** 2)))
    conditioning = float(singular[-1] / max(singular[-2], 1e-300))
    return axis, point, rms, conditioning


def snap_upright(pose: np.ndarray, axis: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Correct a 4x4 object-to-camera pose so the object y axis is ``axis`` and the centre lies on the axis.

    ``axis`` (3,) and ``point`` (3,) describe the symmetry axis in the pose's object frame (e.g. from
    :func:`estimate_symmetry_axis` on the model). The smallest rotation taking y to the axis is applied;
    the box centre moves to the axis point nearest the old centre.
    """
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    y = np.array([0.0, 1.0, 0.0])
    v = np.cross(y, a)
    s, c = np.linalg.norm(v), float(y @ a)
    if s < 1e-12:
        R_fix = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        R_fix = np.eye(3) + K + K @ K * ((1 - c) / s**2)
    point = np.asarray(point, dtype=np.float64)
    origin = point - a * (a @ point)  # the axis point nearest the old centre (the object-frame origin)
    fix = np.eye(4)
    fix[:3, :3] = R_fix
    fix[:3, 3] = origin
    return np.asarray(pose, dtype=np.float64) @ fix


def estimate_axis(points_cam: np.ndarray, position, orientation, extents=None, normal_radius: float = 0.012) -> np.ndarray:
    """Camera-frame unit direction (3,) of the symmetry axis of camera-frame points around a box.

    The box (``position`` m, ``orientation`` x y z w object to camera) gives the starting axis (its
    y); the result is signed to agree with it. ``extents`` is accepted for the browser tool's call
    and unused. Raises ValueError with too few points.
    """
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(np.asarray(orientation, dtype=np.float64)).as_matrix()
    local = (np.asarray(points_cam, dtype=np.float64).reshape(-1, 3) - np.asarray(position, dtype=np.float64)) @ R
    axis, _, _ = estimate_symmetry_axis(local, normal_radius=normal_radius)
    return R @ axis
