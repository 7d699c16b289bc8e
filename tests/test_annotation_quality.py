"""The benchmark suite's figures (evaluate.annotation_quality) against cases whose answer is known by construction."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from evaluate.annotation_quality import (
    OBSERVED_TOLERANCE,
    exterior_samples,
    mean_transform,
    observed_samples,
    revolution_fscore,
    pose_scores,
    posed_fscore,
    shape_scores,
    true_surface,
)


def _pose(rotvec_deg=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.6)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = t
    return T


def test_pose_scores_measure_known_errors():
    truth = {f"{i:02d}": _pose((10.0 * i, 5.0, 0.0), (0.01 * i, 0.0, 0.6)) for i in range(10)}
    poses = {}
    for i, (f, T) in enumerate(truth.items()):
        E = np.eye(4)
        E[:3, :3] = Rotation.from_rotvec(np.radians([1.1 * i, 0.0, 0.0])).as_matrix()  # 1.1 i degrees about the object's x
        E[:3, 3] = [0.0, 0.0, 0.001 * i]  # and i mm along the camera's z
        poses[f] = np.block([[T[:3, :3] @ E[:3, :3], (T[:3, 3] + E[:3, 3])[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
    flagged = {"09": True}
    scores = pose_scores(poses, flagged, truth, "none")
    assert scores["rot_median_deg"] == pytest.approx(4.95) and scores["rot_p90_deg"] == pytest.approx(8.91)
    assert scores["centre_median_mm"] == pytest.approx(4.5)
    assert scores["flagged_share"] == pytest.approx(0.1)
    assert scores["unflagged_over_5deg"] == 4  # frames 5 to 8 (9 is flagged)
    assert scores["unflagged_over_10mm"] == 0
    # a turn about the object's own y axis is no error for symmetry y
    spun = {f: T @ np.block([[Rotation.from_rotvec([0, 0.7, 0]).as_matrix(), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
            for f, T in truth.items()}
    assert pose_scores(spun, {}, truth, "y")["rot_p90_deg"] == pytest.approx(0.0, abs=1e-6)
    assert pose_scores(spun, {}, truth, "none")["rot_median_deg"] == pytest.approx(np.degrees(0.7))


def _cube(side=0.1) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=[side, side, side])


def test_observed_samples_are_the_faces_a_camera_measured():
    cube = _cube()
    points = trimesh.sample.sample_surface(cube, 6000, seed=0)[0]
    T = _pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.6))  # the camera looks at the object's -z face
    front = np.abs(points[:, 2] + 0.05) < 1e-9
    dense = trimesh.sample.sample_surface(cube, 60000, seed=1)[0]
    measured = dense[np.abs(dense[:, 2] + 0.05) < 1e-9] + T[:3, 3]  # the face measured about every 1 mm, camera frame
    observed = observed_samples(points, cube, [(T, measured)])
    assert observed[front].mean() > 0.99
    # of the other faces, only a strip along the measured face's edges lies within the tolerance of a measurement
    assert np.all(points[observed & ~front][:, 2] < -0.05 + OBSERVED_TOLERANCE) and (observed & ~front).sum() < 0.05 * (~front).sum()
    # the back face (+z) lies within reach of nothing; a measured point 1.5 tolerances off the surface observes nothing
    off = observed_samples(points, cube, [(T, measured + [0.0, 0.0, -1.5 * OBSERVED_TOLERANCE])])
    assert not off.any()


def test_observed_needs_the_camera_to_see_the_sample():
    """A measured point inside a thin wall's reach does not make the wall's far side observed."""
    wall = trimesh.creation.box(extents=[0.1, 0.1, 0.003])  # 3 mm thick: both faces within the tolerance of a point
    points, _ = trimesh.sample.sample_surface(wall, 4000, seed=1)
    T = _pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.5))
    near = np.abs(points[:, 2] + 0.0015) < 1e-9
    observed = observed_samples(points, wall, [(T, points[near] + T[:3, 3])])
    far = np.abs(points[:, 2] - 0.0015) < 1e-9
    assert observed[near].mean() > 0.99 and not observed[far].any()


def test_posed_and_shape_scores():
    cube = _cube()
    # six views, each turning one face of the cube to the camera (-z of the camera frame)
    turns = [(0, 0, 0), (0, 180, 0), (0, 90, 0), (0, -90, 0), (90, 0, 0), (-90, 0, 0)]
    truth_poses = {f"{i}": _pose(turn, (0.0, 0.0, 0.7)) for i, turn in enumerate(turns)}
    every_face = [(T, (np.asarray(trimesh.sample.sample_surface(cube, 20000, seed=2)[0]) @ T[:3, :3].T) + T[:3, 3]) for T in truth_poses.values()]
    surface = true_surface(cube, every_face)
    assert surface.observed_share == pytest.approx(1.0, abs=0.01)
    # the true mesh at the true poses
    assert posed_fscore(cube, truth_poses, surface, truth_poses) == pytest.approx(1.0, abs=0.01)
    perfect = shape_scores(cube, truth_poses, surface, truth_poses)
    assert perfect["shape_f5"] == pytest.approx(1.0, abs=0.01) and perfect["observed_recall5"] == pytest.approx(1.0, abs=0.01)
    # every pose 1 cm off along each camera axis: each face 1 cm off, the posed figure falls, the shape (aligned) does not
    shifted = {f: T + np.pad(np.array([[0.01], [0.01], [0.01]]), ((0, 1), (3, 0))) for f, T in truth_poses.items()}
    assert posed_fscore(cube, shifted, surface, truth_poses) < 0.15  # (only near the edges do shifted faces pass within 5 mm)
    assert shape_scores(cube, shifted, surface, truth_poses)["shape_f5"] == pytest.approx(1.0, abs=0.01)
    # a cube 2 cm larger: its faces lie 1 cm off the true ones, nothing within 5 mm
    bigger = shape_scores(_cube(0.12), truth_poses, surface, truth_poses)
    assert bigger["shape_f5"] < 0.2
    assert all(abs(v - 10.0) < 1.5 for v in bigger["face_errors_mm"].values())  # every face 1 cm out
    assert all(abs(v) < 1.0 for v in perfect["face_errors_mm"].values())


def test_mean_transform():
    a, b = _pose((0.0, 0.0, 10.0), (0.1, 0.0, 0.5)), _pose((0.0, 0.0, -10.0), (0.3, 0.0, 0.5))
    mean = mean_transform([a, b])
    np.testing.assert_allclose(mean[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(mean[:3, 3], [0.2, 0.0, 0.5])
    np.testing.assert_allclose(mean_transform([a, a, a]), a, atol=1e-12)


def test_faces_inside_the_solid_are_not_the_surface():
    """A body with a part joined into it (the faces inside overlap) and an open cup: the hidden faces are left out of the
    true surface, the cup's inner bottom (seen through its opening) stays in."""
    body = trimesh.creation.box(extents=[0.12, 0.08, 0.07])
    barrel = trimesh.creation.cylinder(radius=0.025, height=0.06, sections=64)
    barrel.apply_translation([0.0, 0.0, 0.045])  # from z 0.015 to 0.075: 0.04 m sticks out of the body's +z face (0.035)
    joined = trimesh.util.concatenate([body, barrel])
    points = trimesh.sample.sample_surface(joined, 20000, seed=3)[0]
    depth = np.min(np.array([0.06, 0.04, 0.035]) - np.abs(points), axis=1)  # how far within the body's box (m)
    under = np.hypot(points[:, 0], points[:, 1]) < 0.026  # the body's +z face the barrel covers, and the barrel
    inside = (depth > 0.001) | ((np.abs(points[:, 2] - 0.035) < 1e-9) & (np.hypot(points[:, 0], points[:, 1]) < 0.024))
    out = (depth < 1e-9) & ~under | (points[:, 2] > 0.036)  # (within 1 mm of where the barrel enters: undecided)
    outer = exterior_samples(points, joined)
    assert not outer[inside].any() and outer[out].all()
    # the surface kept: every face of the body but the disc the barrel covers, and the barrel's part outside it
    kept_area = body.area - np.pi * 0.025**2 + 2 * np.pi * 0.025 * 0.04 + np.pi * 0.025**2
    assert outer.mean() == pytest.approx(kept_area / joined.area, abs=0.01)
    # an open cup 8 cm wide and 9 cm deep (1 cm walls): its inner bottom lies in view of its opening
    profile = np.array([[0.0, -0.05], [0.04, -0.05], [0.04, 0.05], [0.03, 0.05], [0.03, -0.04], [0.0, -0.04]])  # (r, z)
    cup = trimesh.creation.revolve(profile, sections=64)
    samples = trimesh.sample.sample_surface(cup, 20000, seed=4)[0]
    inner_bottom = (np.abs(samples[:, 2] + 0.04) < 1e-6) & (np.hypot(samples[:, 0], samples[:, 1]) < 0.029)
    assert inner_bottom.sum() > 100 and exterior_samples(samples, cup).all()


def test_true_surface_leaves_out_the_hidden_faces():
    """The observed share of a body with a part joined into it is of its outer surface: every outer face measured is 100 %."""
    body = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    hidden = trimesh.creation.box(extents=[0.05, 0.05, 0.05])  # wholly inside: all of its faces hidden
    joined = trimesh.util.concatenate([body, hidden])
    turns = [(0, 0, 0), (0, 180, 0), (0, 90, 0), (0, -90, 0), (90, 0, 0), (-90, 0, 0)]
    views = [_pose(turn, (0.0, 0.0, 0.7)) for turn in turns]
    dense = trimesh.sample.sample_surface(body, 20000, seed=2)[0]
    surface = true_surface(joined, [(T, dense @ T[:3, :3].T + T[:3, 3]) for T in views])
    assert surface.observed_share == pytest.approx(1.0, abs=0.01)
    assert np.all(np.abs(surface.index.points).max(axis=1) > 0.05 - 1e-6)  # only the body's faces are kept
    # the -z face (the first view's) never measured: a sixth of the outer surface, the hidden faces still left out
    surface = true_surface(joined, [(T, dense @ T[:3, :3].T + T[:3, 3]) for T in views[1:]])
    assert surface.observed_share == pytest.approx(5 / 6, abs=0.01)
    unobserved = surface.index.points[~surface.observed]
    assert np.all(np.abs(unobserved[:, 2] + 0.05) < OBSERVED_TOLERANCE)


def test_revolution_fscore_tells_round_shapes_from_the_others():
    """A cylinder about y is its own turn; a square prism and a flattened cylinder (both 'symmetric' by category) are not."""
    cylinder = trimesh.creation.cylinder(radius=0.04, height=0.1, sections=128)
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # its axis along y
    assert revolution_fscore(cylinder) > 0.99
    square = trimesh.creation.box(extents=[0.08, 0.1, 0.08])
    flat = cylinder.copy()
    flat.apply_scale([1.0, 1.0, 0.5])  # 8 cm by 4 cm across
    # a square 8 cm across turned 30 or 60 deg: its corners stand up to 1.5 cm off the faces they turn onto
    assert revolution_fscore(square) < 0.8 and revolution_fscore(flat) < 0.6


def test_observed_scores_ignore_what_was_guessed_elsewhere():
    """A reconstruction whose front face is exact but whose unseen sides are guessed 1 cm too wide: the observed
    surface's recall stays whole (aligned on the whole shape, it slid 1 cm sideways onto the true sides: 0.23)."""
    cube = _cube()
    T = _pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.6))  # the camera sees the -z face only
    dense = trimesh.sample.sample_surface(cube, 60000, seed=1)[0]
    surface = true_surface(cube, [(T, dense[np.abs(dense[:, 2] + 0.05) < 1e-9] + T[:3, 3])])
    guess = trimesh.creation.box(extents=[0.12, 0.12, 0.11])
    guess.apply_translation([0.01, 0.01, 0.005])  # its -z face on the true one, reaching 2 cm past it along +x and +y
    scores = shape_scores(guess, {"0": T}, surface, {"0": T})
    assert scores["observed_recall5"] > 0.99
    # the front face's 2 cm overhang (about a sixth of its samples, nearest to the observed edge) is wrong, and counted
    assert 0.8 < scores["observed_precision5"] < 0.9
    assert scores["face_errors_mm"]["+x"] > 15.0 and scores["shape_f5"] < 0.5


def test_observed_precision_is_over_what_the_reconstruction_says_it_observed():
    """With the reconstruction's own labels (reconstruct.seen: the faces some frame measured), the observed part's
    precision is over those faces: a guess beside the seen face that the reconstruction labels unseen is no error of
    the seen part, and a face it claims to have seen is judged wherever it lies."""
    cube = _cube()
    T = _pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.6))  # the camera sees the -z face only
    dense = trimesh.sample.sample_surface(cube, 60000, seed=1)[0]
    surface = true_surface(cube, [(T, dense[np.abs(dense[:, 2] + 0.05) < 1e-9] + T[:3, 3])])
    # the true -z face, and behind it a guess 2 cm deeper and 1 cm wider on every side, all labelled unseen
    guess = trimesh.creation.box(extents=[0.12, 0.12, 0.12])
    guess.apply_translation([0.0, 0.0, 0.01])
    front = trimesh.creation.box(extents=[0.1, 0.1, 0.001])
    front.apply_translation([0.0, 0.0, -0.0505])
    joined = trimesh.util.concatenate([front, guess])
    seen = joined.triangles_center[:, 2] < -0.0505 - 1e-6  # the front slab's -z face
    scores = shape_scores(joined, {"0": T}, surface, {"0": T}, observed_faces=seen)
    assert scores["observed_precision5"] > 0.99 and scores["observed_recall5"] > 0.99
    # the nearest-true-sample stand-in counts the guess's wide rim beside the seen face (1 cm off it) as seen
    assert shape_scores(joined, {"0": T}, surface, {"0": T})["observed_precision5"] < scores["observed_precision5"] - 0.05
    # a face it claims to have seen is judged though no true sample near it was observed: the guess's back, 2 cm off
    back = seen | (joined.triangles_center[:, 2] > 0.069)
    assert shape_scores(joined, {"0": T}, surface, {"0": T}, observed_faces=back)["observed_precision5"] < 0.6
