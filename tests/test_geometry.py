"""Shared geometry: poses, boxes and REDWOOD75's raw axes."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from evaluate import geometry as g


def test_pose_round_trip_and_inverse():
    rng = np.random.default_rng(0)
    q = Rotation.random(random_state=1).as_quat()
    t = rng.normal(size=3)
    T = g.pose_matrix(t, q)
    p, q2 = g.pose_from_matrix(T)
    assert np.allclose(p, t)
    assert np.isclose(abs(np.dot(q, q2)), 1.0)
    assert np.allclose(g.invert(T) @ T, np.eye(4))
    pts = rng.normal(size=(5, 3))
    assert np.allclose(g.transform(g.invert(T), g.transform(T, pts)), pts)


def test_box_corners_and_edges():
    corners = g.box_corners([0.2, 0.4, 0.6])
    assert np.allclose(corners.min(0), [-0.1, -0.2, -0.3]) and np.allclose(corners.max(0), [0.1, 0.2, 0.3])
    lengths = np.linalg.norm(corners[g.BOX_EDGES[:, 0]] - corners[g.BOX_EDGES[:, 1]], axis=1)
    assert sorted(np.round(lengths, 9).tolist()) == [0.2] * 4 + [0.4] * 4 + [0.6] * 4


def test_redwood_raw_axes():
    # raw x = ShapeNet z, raw y = -ShapeNet y, raw z = ShapeNet x
    assert np.allclose(g.shapenet_to_raw_points([[1, 2, 3]]), [[3, -2, 1]])
    assert np.allclose(g.raw_to_shapenet_points(g.shapenet_to_raw_points([[1, 2, 3]])), [[1, 2, 3]])
    assert np.allclose(g.shapenet_to_raw_extents([0.1, 0.2, 0.3]), [0.3, 0.2, 0.1])
    # the same physical point lands at the same camera point in both conventions
    T = g.pose_matrix([0.1, 0.2, 0.7], Rotation.random(random_state=3).as_quat())
    p_sn = np.array([[0.01, 0.02, 0.03]])
    T_raw = g.shapenet_to_raw_pose(T)
    assert np.allclose(g.transform(T_raw, g.shapenet_to_raw_points(p_sn)), g.transform(T, p_sn))
    assert np.allclose(g.raw_to_shapenet_pose(T_raw), T)
    assert np.isclose(np.linalg.det(g.RAW_FROM_SHAPENET), 1.0)


def test_untransform_takes_points_back_through_a_rigid_transform_as_its_inverse_does():
    rng = np.random.default_rng(4)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    T[:3, 3] = [0.05, -0.2, 0.8]
    points = rng.normal(size=(50, 3)) * 0.1
    assert np.allclose(g.untransform(T, g.transform(T, points)), points, atol=1e-12)
    assert np.allclose(g.untransform(T, points), g.transform(g.invert(T), points), atol=1e-12)
    # float32 points (a depth crop) come back as float64
    assert g.untransform(T, points.astype(np.float32)).dtype == np.float64


def test_rigid_takes_the_rotation_of_the_polar_decomposition():
    rng = np.random.default_rng(7)
    R = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    A = rng.normal(size=(3, 3))
    S = np.eye(3) + 0.05 * (A + A.T)  # symmetric, positive definite: a stretch and shear of the points
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R @ S, [0.1, -0.2, 0.7]
    out = g.rigid(T)
    np.testing.assert_allclose(out[:3, :3], R, atol=1e-12)  # R S = R (polar), nearest in Frobenius
    np.testing.assert_array_equal(out[:3, 3], T[:3, 3])
    np.testing.assert_array_equal(out[3], [0.0, 0.0, 0.0, 1.0])
    # a rotation stays as it is (to rounding), and never becomes a reflection
    np.testing.assert_allclose(g.rigid(g.pose_matrix([0, 0, 1], [0.1, 0.2, 0.3, 0.927]))[:3, :3],
                               g.quat_to_matrix([0.1, 0.2, 0.3, 0.927]), atol=1e-14)
    assert np.linalg.det(g.rigid(np.diag([1.0, 1.0, -1.0, 1.0]))[:3, :3]) > 0
    # a failed (non-finite) pose stays as it is instead of raising
    assert np.isnan(g.rigid(np.full((4, 4), np.nan))).all()
