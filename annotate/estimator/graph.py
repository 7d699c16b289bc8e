"""One pose graph over all frames, solved by GTSAM.

Nodes: the object's pose in each frame (GTSAM Pose3, object to camera). Factors, each error in GTSAM's right
tangent (w, v) of the object frame:
- registration: a frame registered to the model, a prior with the registration's information;
- chain step: two consecutive frames of a chain, a between factor with the later frame's information, scaled by
  the trust in its chain;
- anchor: a box a person placed, refined or accepted, a prior with the placement sigma;
- motion: every three consecutive frames keep a constant velocity (the change of the object-frame motion
  Log((T0^-1 T1)^-1 (T1^-1 T2)), the motion sigma per frame), so that where the points leave a direction free (a
  bowl's tilt seen into its dome, a thin object edge-on) the motion on either side carries it; every chain step also
  holds the chain's own motion with the motion sigma, an information floor; and neighbouring frames are tied by a
  between factor at identity ``WALK_FACTOR`` times looser, which only keeps the system positive definite.
Registration, chain and constant-velocity factors are Cauchy-robust (a frame whose points were half hand pulls at
most a little; a regrasp jerks the motion).
For ``symmetry: y`` the rotation about the object's y is removed from registration and chain factors: the data
do not measure it, and the anchors and the motion alone carry it.

GTSAM (Levenberg-Marquardt, sparse Cholesky, marginal covariances) rather than Open3D's PoseGraph: Open3D's has no
unary priors, no per-factor robust kernels beyond its line process, and no marginals, which the flags read.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

#: the random walk between neighbouring frames is this many times looser than the motion sigma: it keeps frames no
#: data reach determined, and pulls a steady turn towards standing still by a negligible amount
WALK_FACTOR = 100.0
#: the information left on a removed direction, as a share of the largest: keeps the matrix positive definite
REMOVED_SHARE = 1e-9


@dataclass
class Factor:
    """A registration (``j`` is None: a prior on frame ``i``) or chain step (frame ``i`` to ``j``): the measured pose
    (4x4; for a step T_i^-1 T_j), its information (6x6, (w, v)) and, for a step, the trust in its chain (0-1), which
    scales its information and the chain's motion it holds."""

    i: int
    j: int | None
    measured: np.ndarray
    information: np.ndarray
    weight: float = 1.0


def without_spin(information: np.ndarray) -> np.ndarray:
    """``information`` with the rotation about the object's y removed (symmetry y)."""
    keep = np.ones(6)
    keep[1] = 0.0
    out = information * keep[:, None] * keep[None, :]
    return out + REMOVED_SHARE * max(np.trace(out), 1.0) * np.diag(1 - keep)


def _noise(information: np.ndarray, robust_k: float | None) -> gtsam.noiseModel.Base:
    information = 0.5 * (information + information.T) + 1e-9 * max(np.trace(information), 1.0) * np.eye(6)
    gaussian = gtsam.noiseModel.Gaussian.Information(information)
    if robust_k is None:
        return gaussian
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust_k), gaussian)


def sigmas(deg: float, metres: float) -> np.ndarray:
    """A diagonal (6,) of standard deviations (rad, m) from per-axis degrees and metres."""
    return np.array([np.radians(deg)] * 3 + [metres] * 3)


def _steady(factor: "gtsam.CustomFactor", values: "gtsam.Values", jacobians: list | None) -> np.ndarray:
    """Constant velocity over three frames: Log((T0^-1 T1)^-1 (T1^-1 T2)), the change of the object-frame motion."""
    a, b, c = (values.atPose3(key) for key in factor.keys())
    A0, A1, B1, B2, C1, C2, L = (np.zeros((6, 6), order="F") for _ in range(7))
    first, second = a.between(b, A0, A1), b.between(c, B1, B2)
    error = gtsam.Pose3.Logmap(first.between(second, C1, C2), L)
    if jacobians is not None:
        jacobians[0] = L @ C1 @ A0
        jacobians[1] = L @ (C1 @ A1 + C2 @ B1)
        jacobians[2] = L @ C2 @ B2
    return error


@dataclass
class Solution:
    """Solved poses (n, 4, 4) and each frame's marginal covariance (n, 6, 6), (w, v)."""

    poses: np.ndarray
    covariances: np.ndarray


def solve(
    initial: np.ndarray,
    registrations: list[Factor],
    steps: list[Factor],
    anchors: dict[int, np.ndarray],
    anchor_sigmas: np.ndarray,
    motion_sigmas: np.ndarray,
    symmetric: bool,
    robust_k: float,
) -> Solution:
    """The poses of frames 0..n-1 (``initial``, (n, 4, 4)) that best fit all factors, and their marginals."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, pose in enumerate(initial):
        values.insert(k, gtsam.Pose3(pose))
    spinless = without_spin if symmetric else (lambda m: m)
    for f in registrations:
        graph.add(gtsam.PriorFactorPose3(f.i, gtsam.Pose3(f.measured), _noise(spinless(f.information), robust_k)))
    floor = np.diag(1.0 / motion_sigmas**2)
    for f in steps:
        graph.add(gtsam.BetweenFactorPose3(f.i, f.j, gtsam.Pose3(f.measured), _noise(f.weight * (spinless(f.information) + floor), robust_k)))
    anchor_noise = gtsam.noiseModel.Diagonal.Sigmas(anchor_sigmas)
    for k, pose in anchors.items():
        graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(pose), anchor_noise))
    motion_noise = gtsam.noiseModel.Diagonal.Sigmas(WALK_FACTOR * motion_sigmas)
    for k in range(len(initial) - 1):
        graph.add(gtsam.BetweenFactorPose3(k, k + 1, gtsam.Pose3(), motion_noise))
    velocity_noise = _noise(np.diag(1.0 / motion_sigmas**2), robust_k)
    for k in range(1, len(initial) - 1):
        graph.add(gtsam.CustomFactor(velocity_noise, [k - 1, k, k + 1], _steady))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    poses = np.stack([result.atPose3(k).matrix() for k in range(len(initial))])
    marginals = gtsam.Marginals(graph, result)
    covariances = np.stack([marginals.marginalCovariance(k) for k in range(len(initial))])
    return Solution(poses, covariances)
