"""Smoothing the refined poses where the geometry leaves a direction weakly determined.

Registration pins a pose down only in the directions the surface constrains: a mug whose handle
is out of view (or in the hand) is a surface of revolution, and its rotation about its axis is
then free to within the noise of a few handle points (measured: ICP to the true model, started
2-3 deg off about the axis, stopped 1-4 deg off in the frames that see fewer than 15 handle
points). Objects held in a hand move smoothly, so such a direction is better taken from the
neighbouring frames that do see it.

Each frame's registration is summarised by its information matrix ``H_i`` (6x6, point-to-plane
Gauss-Newton, per (rad, m) of an object-frame perturbation ``T_i exp(d_i)`` with ``d = (w, tau)``,
divided by the point noise squared). The correction ``d_i`` of every frame minimises

    sum_i d_i' H_i d_i  +  sum_i |rotational acceleration_i|^2 / s_r^2 + |acceleration of the centre_i|^2 / s_t^2

linearised about the current poses: a banded linear solve (6 unknowns per frame), repeated a
few times about the corrected poses. Where ``H_i``
is strong the pose stays; where it is weak the acceleration terms interpolate from the neighbours.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_banded
from scipy.spatial.transform import Rotation

from .registration import ModelTarget


_EY_SKEW = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])  # the cross-product matrix of e_y


def registration_information(points_obj: np.ndarray, target: ModelTarget, distance: float, sigma: float) -> np.ndarray:
    """Point-to-plane information (6x6) of object-frame points (N, 3) m against the model's points and normals.

    Only points within ``distance`` (m) of a model point count; ``sigma`` is the point noise (m).
    Order of the perturbation: rotation (rad, object frame), then translation (m, object frame).
    """
    points_obj = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3)
    if len(points_obj) == 0 or len(target) == 0 or not target.cloud.has_normals():
        return np.zeros((6, 6))
    dist, index = target.nearest(points_obj, distance)
    near = np.isfinite(dist)
    p = points_obj[near]
    n = np.asarray(target.cloud.normals)[index[near]]
    J = np.hstack([np.cross(n, p), -n])  # d(residual)/d(w, tau) of n . (p - model point)
    return J.T @ J / sigma**2


def smooth_poses(
    poses: list[np.ndarray],
    information: list[np.ndarray],
    rotation_acceleration: float,
    translation_acceleration: float,
    free_y: bool = False,
    priors: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
    iterations: int = 3,
) -> list[np.ndarray]:
    """Consecutive poses (4x4 object to camera) corrected by the least-squares trade of registration and smoothness.

    ``information[i]`` (6x6) is frame i's registration information (see module doc);
    ``rotation_acceleration`` (rad per frame squared) and ``translation_acceleration`` (m per frame
    squared) are the expected accelerations. ``free_y`` (symmetry y) leaves the rotation about the
    object's y axis as it is (it is unobservable and kept consistent elsewhere) and smooths the
    axis direction instead of the whole rotation, so an arbitrary spin does not count as motion.
    ``priors``: frame index -> (target correction d (6,), information (6x6)), e.g. where a person
    placed the box: adds (d_i - target)' info (d_i - target).
    """
    n = len(poses)
    if n < 3:
        return [p.copy() for p in poses]
    dofs = [0, 2, 3, 4, 5] if free_y else [0, 1, 2, 3, 4, 5]
    sel = np.eye(6)[dofs]  # 6 -> k reduction
    current = [np.asarray(p, dtype=np.float64).copy() for p in poses]
    applied = np.zeros((n, 6))  # the correction so far, per frame (additive to first order)
    for _ in range(iterations):  # relinearised: a frame turns a few degrees per frame
        delta = _solve_step(current, information, rotation_acceleration, translation_acceleration, free_y, priors or {}, applied, sel)
        for i in range(n):
            R, t = current[i][:3, :3].copy(), current[i][:3, 3].copy()
            current[i][:3, :3] = R @ Rotation.from_rotvec(delta[i, :3]).as_matrix()
            current[i][:3, 3] = t + R @ delta[i, 3:]
        applied += delta
        if np.abs(delta).max() < 1e-7:
            break
    return current


def _solve_step(poses, information, rotation_acceleration, translation_acceleration, free_y, priors, applied, sel) -> np.ndarray:
    """One Gauss-Newton step (n, 6) about ``poses``, whose corrections so far are ``applied`` (n, 6)."""
    n, k = len(poses), sel.shape[0]
    R = np.stack([p[:3, :3] for p in poses])
    t = np.stack([p[:3, 3] for p in poses])
    A = np.zeros((n * k, n * k))
    b = np.zeros(n * k)
    for i in range(n):
        A[i * k : (i + 1) * k, i * k : (i + 1) * k] += sel @ information[i] @ sel.T
        b[i * k : (i + 1) * k] += sel @ information[i] @ applied[i]
    for i, (target, info) in priors.items():
        A[i * k : (i + 1) * k, i * k : (i + 1) * k] += sel @ info @ sel.T
        b[i * k : (i + 1) * k] += sel @ info @ (applied[i] - np.asarray(target, dtype=np.float64))
    # rotational acceleration, body frame: phi_i = log(R_i' R_(i+1)); phi_i(d) ~ phi_i + Q_i w_(i+1) - w_i
    phi = Rotation.from_matrix(np.einsum("nji,njk->nik", R[:-1], R[1:])).as_rotvec()
    Q = np.einsum("nji,njk->nik", R[:-1], R[1:])
    wr, wt = 1.0 / rotation_acceleration, 1.0 / translation_acceleration
    for i in range(1, n - 1):
        rows = np.zeros((3, 3 * 6))
        if free_y:
            # the axis direction a_j = R_j e_y in the camera frame: its second difference, blind to the spin
            # (a_j(d) ~ a_j - R_j [e_y]x w_j)
            for j, c in enumerate((1.0, -2.0, 1.0)):
                rows[:, 6 * j : 6 * j + 3] = -c * R[i - 1 + j] @ _EY_SKEW
            residual = R[i + 1][:, 1] - 2 * R[i][:, 1] + R[i - 1][:, 1]
        else:
            # acc_i = phi_i - phi_(i-1) (both about the same axis to first order) as a linear function of w_(i-1..i+1)
            rows[:, 0:3] = np.eye(3)  # + w_(i-1)  (from - (Q_(i-1) w_i - w_(i-1)))
            rows[:, 6:9] = -np.eye(3) - Q[i - 1]  # - w_i - Q_(i-1) w_i
            rows[:, 12:15] = Q[i]  # + Q_i w_(i+1)
            residual = phi[i] - phi[i - 1]
        _accumulate(A, b, wr * rows, wr * residual, i - 1, sel, k)
        # centre acceleration, camera frame: t_j(d) = t_j + R_j tau_j
        rows = np.zeros((3, 3 * 6))
        rows[:, 3:6] = R[i - 1]
        rows[:, 9:12] = -2 * R[i]
        rows[:, 15:18] = R[i + 1]
        residual = t[i + 1] - 2 * t[i] + t[i - 1]
        _accumulate(A, b, wt * rows, wt * residual, i - 1, sel, k)
    # banded symmetric positive (semi)definite system: a tiny ridge keeps an unconstrained frame in place
    # (a millionth of the smoothness weight: far below any evidence, so it never drags a weak direction back)
    A[np.diag_indices_from(A)] += 1e-6 * min(wr, wt) ** 2
    # general banded solver: LAPACK's symmetric one (solveh_banded) measured 2-5 s per call here,
    # against under 1 ms for this one, on a loaded machine with threaded OpenBLAS
    bandwidth = 3 * k - 1
    banded = np.zeros((2 * bandwidth + 1, n * k))
    for d in range(-bandwidth, bandwidth + 1):
        banded[bandwidth - d, max(d, 0) : n * k + min(d, 0)] = np.diagonal(A, d)
    delta = solve_banded((bandwidth, bandwidth), banded, -b).reshape(n, k) @ sel
    return delta


def _accumulate(A: np.ndarray, b: np.ndarray, J: np.ndarray, r: np.ndarray, first: int, sel: np.ndarray, k: int) -> None:
    """Add |J d + r|^2 over three consecutive frames starting at ``first`` to the normal equations (A, b)."""
    Jk = np.hstack([J[:, 6 * j : 6 * j + 6] @ sel.T for j in range(3)])
    s = slice(first * k, (first + 3) * k)
    A[s, s] += Jk.T @ Jk
    b[s] += Jk.T @ r
