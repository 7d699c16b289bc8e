"""icp.point_to_plane against Open3D's registration_icp: the same transform, fitness and RMSE, bit for bit."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from annotate.tracking import icp
from annotate.tracking.registration import ModelTarget, RegistrationParams, _icp_open3d, _source_cloud, open3d_threads
from evaluate.geometry import invert, transform


#: The Open3D release icp.py was matched to bit for bit; another release may order its sums otherwise,
#: so there the results must agree to rounding, not to the bit.
BIT_EXACT = o3d.__version__.startswith("0.20.")


def _assert_same(got, expected) -> None:
    """(transform, fitness, rmse) of icp.point_to_plane against Open3D's."""
    if BIT_EXACT:
        assert np.array_equal(got[0], expected[0]), np.abs(got[0] - expected[0]).max()
        assert got[1:] == expected[1:]
    else:
        np.testing.assert_allclose(got[0], expected[0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[1:], expected[1:], rtol=1e-9, atol=1e-12)


def _object_points(seed: int = 0) -> np.ndarray:
    """Points (N, 3) m on an asymmetric object (a box with a bump), object frame."""
    box = trimesh.creation.box(extents=[0.12, 0.08, 0.05])
    bump = trimesh.creation.icosphere(radius=0.025)
    bump.apply_translation([0.04, 0.03, 0.0])
    points, _ = trimesh.sample.sample_surface_even(trimesh.util.concatenate([box, bump]), 6000, seed=seed)
    return np.asarray(points)


def _pose(deg: float, mm: float, seed: int) -> np.ndarray:
    """A 4x4 rigid transform: ``deg`` about a random axis, ``mm`` along a random direction, 0.5 m ahead."""
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    axis = rng.normal(size=3)
    T[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(deg)).as_matrix()
    direction = rng.normal(size=3)
    T[:3, 3] = direction / np.linalg.norm(direction) * mm / 1000 + np.array([0.0, 0.0, 0.5])
    return T


def _view(model: np.ndarray, T_cam_obj: np.ndarray, seed: int, outliers: int = 300) -> np.ndarray:
    """A camera-frame view (N, 3): part of the model at ``T_cam_obj`` with 0.5 mm noise, plus points off the model
    (a hand near it and background far from it)."""
    rng = np.random.default_rng(seed)
    part = model[model[:, 2] > -0.01]
    seen = transform(T_cam_obj, part[rng.choice(len(part), min(2500, len(part)), replace=False)])
    hand = seen[rng.choice(len(seen), outliers)] + rng.normal(size=(outliers, 3)) * 0.02
    background = rng.uniform(-0.3, 0.3, size=(outliers, 3)) + np.array([0.0, 0.0, 0.8])
    return np.vstack([seen + rng.normal(size=seen.shape) * 0.0005, hand, background])


@pytest.mark.parametrize(
    "deg, mm, seed",
    [(0.5, 1.0, 0), (3.0, 5.0, 1), (8.0, 12.0, 2), (20.0, 30.0, 3)],  # small moves to ones that need fresh searches
)
def test_point_to_plane_equals_open3d_bit_for_bit(deg, mm, seed):
    model = _object_points()
    target = ModelTarget(model, voxel_size=0.003)
    T_cam_obj = _pose(deg, mm, seed)
    points = _view(model, T_cam_obj, seed)
    init = invert(_pose(0.0, 0.0, seed))  # T_obj_cam guess: the object ahead, unrotated
    source = _source_cloud(points, None)
    with open3d_threads(1):  # Open3D's reductions sum in one order only on one thread
        # all points in both stages, as registration_icp runs them (the thinned coarse stage: the test below)
        for params in (RegistrationParams(coarse_points=0), RegistrationParams(iterations=3, coarse_points=0),
                       RegistrationParams(max_distance=0.02, fine_distance=0.002, coarse_points=0)):
            expected = _icp_open3d("point_to_plane", source, target, init, params)
            got = icp.point_to_plane(source, target, init, params)
            _assert_same(got, expected)
            assert got[0].flags.f_contiguous  # Open3D's layout: numpy's later products round the same way


def test_point_to_plane_equals_open3d_at_identity_and_without_correspondences():
    model = _object_points(1)
    target = ModelTarget(model, voxel_size=0.003)
    rng = np.random.default_rng(5)
    cases = [
        (model[::3] + rng.normal(size=model[::3].shape) * 0.001, np.eye(4)),  # identity: Open3D skips the first transform
        (model[::3] + np.array([1.0, 0.0, 0.0]), np.eye(4)),  # nothing within the cut
    ]
    with open3d_threads(1):
        for points, init in cases:
            source = _source_cloud(points, None)
            expected = _icp_open3d("point_to_plane", source, target, init, RegistrationParams(coarse_points=0))
            got = icp.point_to_plane(source, target, init, RegistrationParams(coarse_points=0))
            _assert_same(got, expected)


def test_thinned_coarse_stage_equals_open3d_on_every_kth_point():
    """With ``coarse_points``, the coarse stage is Open3D's ICP on every k-th point and the fine stage on all of them."""
    model = _object_points(3)
    target = ModelTarget(model, voxel_size=0.003)
    T_cam_obj = _pose(6.0, 8.0, 4)
    points = _view(model, T_cam_obj, 4)
    init = invert(_pose(0.0, 0.0, 4))
    source = _source_cloud(points, None)
    params = RegistrationParams(coarse_points=1000)
    k = int(np.ceil(len(points) / 1000))
    assert k >= 3  # the test thins for real
    reg = o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-5, relative_rmse=1e-5, max_iteration=params.iterations)
    with open3d_threads(1):
        T = init
        for cloud, distance in ((_source_cloud(points[::k], None), params.max_distance), (source, params.fine_distance)):
            estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=max(params.kernel, distance / 2)))
            result = reg.registration_icp(cloud, target.cloud, distance, T, estimation, criteria)
            T = result.transformation
        got = icp.point_to_plane(source, target, init, params)
    _assert_same(got, (np.asarray(T), float(result.fitness), float(result.inlier_rmse)))
    # and it lands where the ICP on all points lands
    full = icp.point_to_plane(source, target, init, RegistrationParams(coarse_points=0))
    assert np.abs(got[0][:3, 3] - full[0][:3, 3]).max() < 2e-4
    assert icp.thinned(source, 0) is source and icp.thinned(source, len(points)) is source
    assert np.array_equal(np.asarray(icp.thinned(source, 1000).points), points[::k])


def test_nearest_model_points_follow_moving_points_exactly():
    """After every move, each point's kept model point is its nearest (brute force), or none within the cut."""
    rng = np.random.default_rng(0)
    model = _object_points(2)
    target = ModelTarget(model, voxel_size=0.003)
    query = model[rng.choice(len(model), 800, replace=False)] + rng.normal(size=(800, 3)) * 0.004
    nearest = icp.NearestModelPoints(target, query, reach=0.015)
    for step in range(12):
        angle = np.radians(rng.uniform(0.1, 3.0))
        R = Rotation.from_rotvec(rng.normal(size=3) * angle).as_matrix()
        query = query @ R.T + rng.normal(size=3) * 0.0005 * (1 + step % 4)
        distance = 0.01 if step < 6 else 0.004
        rows, index, d2 = nearest.within(query, distance)
        all_d2 = ((query[:, None, :] - model[None, :, :]) ** 2).sum(axis=2)
        truth = np.argmin(all_d2, axis=1)
        inside = np.flatnonzero(all_d2[np.arange(len(query)), truth] < distance**2)
        assert np.array_equal(rows, inside)
        assert np.array_equal(index, truth[inside])
        assert np.allclose(d2, all_d2[inside, truth[inside]], rtol=1e-12, atol=0)


def test_a_state_taken_over_for_every_kth_point_stays_exact():
    """A fine stage's state that takes over a coarse stage's every k-th point (their candidates and bounds, at the
    coarse stage's last positions) pairs every point with its nearest model point, as a fresh search does."""
    rng = np.random.default_rng(5)
    model = _object_points(2)
    target = ModelTarget(model, voxel_size=0.003)
    query = model[rng.choice(len(model), 900, replace=False)] + rng.normal(size=(900, 3)) * 0.004
    coarse = icp.NearestModelPoints(target, query[::3], reach=0.015)
    coarse.within(query[::3] + 0.001, 0.01)  # moved once: its positions and bounds are no longer the search's
    moved = query + [0.0012, 0.0, -0.0005]
    fine = icp.NearestModelPoints(target, moved, 0.006, coarse, np.arange(0, len(query), 3))
    fresh = icp.NearestModelPoints(target, moved, 0.006)
    for step in range(4):
        moved = moved + rng.normal(size=3) * 0.001
        got, want = fine.within(moved, 0.004), fresh.within(moved, 0.004)
        for a, b in zip(got, want):
            assert np.array_equal(a, b)
    all_d2 = ((moved[:, None, :] - model[None, :, :]) ** 2).sum(axis=2)
    truth = np.argmin(all_d2, axis=1)
    assert np.array_equal(got[1], truth[got[0]])


def test_identity_check_follows_eigen():
    T = np.eye(4)
    assert icp.is_identity(T)
    T[0, 3] = 1e-13
    assert icp.is_identity(T)  # within Eigen's default precision
    T[0, 3] = 1e-9
    assert not icp.is_identity(T)


def test_pairs_whose_model_surface_faces_away_from_the_camera_are_dropped():
    """icp.correspondences with a camera keeps exactly the nearest pairs whose oriented model normal faces it."""
    model = _object_points(4)
    rng = np.random.default_rng(2)
    views = model - model.mean(axis=0)  # outward: seen from outside
    target = ModelTarget(model, voxel_size=0.003, views=views)
    normals = np.asarray(target.cloud.normals)
    assert target.oriented and np.all(np.einsum("ij,ij->i", normals, views) >= 0)
    query = model[rng.choice(len(model), 700, replace=False)] + rng.normal(size=(700, 3)) * 0.002
    rows, index, _ = icp.NearestModelPoints(target, query, 0.015).within(query, 0.01)
    for camera in (np.array([0.0, 0.0, 0.5]), np.array([0.3, -0.2, 0.1]), np.zeros(3)):
        pairs, fitness, _ = icp.correspondences(icp.NearestModelPoints(target, query, 0.015), query, 0.01, camera)
        faces = normals[index] @ camera > np.einsum("ij,ij->i", normals[index], model[index])
        assert np.array_equal(pairs[:, 0], rows[faces]) and np.array_equal(pairs[:, 1], index[faces])
        assert fitness == faces.sum() / len(query)
    with pytest.raises(ValueError, match="not oriented"):
        ModelTarget(model, voxel_size=0.003).facing_planes()


