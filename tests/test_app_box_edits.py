"""Box edits against analytic truth: nudges, turns, face drags, fitting, upright snapping."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotate import box_edits
from evaluate.geometry import box_corners, pose_matrix


def random_pose(seed: int):
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.2, 0.2, 3) + [0, 0, 0.8], Rotation.random(random_state=seed).as_quat()


def test_nudge_moves_along_the_box_axis():
    position, orientation = random_pose(0)
    R = Rotation.from_quat(orientation).as_matrix()
    moved = box_edits.nudge(position, orientation, 1, 0.005)
    np.testing.assert_allclose(moved - position, 0.005 * R[:, 1], atol=1e-15)
    # in the box's own frame the move is (0, 5 mm, 0)
    np.testing.assert_allclose(R.T @ (moved - position), [0, 0.005, 0], atol=1e-15)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_turns_and_flips(axis):
    _, orientation = random_pose(axis + 1)
    R = Rotation.from_quat(orientation).as_matrix()
    flipped = Rotation.from_quat(box_edits.turn(orientation, axis, 180)).as_matrix()
    # a flip keeps the axis and reverses the other two
    np.testing.assert_allclose(flipped[:, axis], R[:, axis], atol=1e-12)
    for other in {0, 1, 2} - {axis}:
        np.testing.assert_allclose(flipped[:, other], -R[:, other], atol=1e-12)
    # four quarter turns come back to the start; one moves the next axis onto the one after it
    q = orientation
    for _ in range(4):
        q = box_edits.turn(q, axis, 90)
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)
    quarter = Rotation.from_quat(box_edits.turn(orientation, axis, 90)).as_matrix()
    a, b = (axis + 1) % 3, (axis + 2) % 3
    np.testing.assert_allclose(quarter[:, a], R[:, b], atol=1e-12)


def test_drag_face_keeps_the_opposite_face():
    position, orientation = random_pose(7)
    extents = np.array([0.1, 0.2, 0.3])
    T = pose_matrix(position, orientation)
    new_position, new_extents = box_edits.drag_face(position, orientation, extents, 2, -1, 0.04)
    np.testing.assert_allclose(new_extents, [0.1, 0.2, 0.34])
    # the +z face's corners (bit 0 set) are where they were; the -z face moved 4 cm outwards
    old = box_corners(extents, T)
    new = box_corners(new_extents, pose_matrix(new_position, orientation))
    np.testing.assert_allclose(new[1::2], old[1::2], atol=1e-12)
    R = T[:3, :3]
    np.testing.assert_allclose(new[0::2] - old[0::2], np.tile(-0.04 * R[:, 2], (4, 1)), atol=1e-12)
    # a drag past the other face stops at the smallest side
    _, tiny = box_edits.drag_face(position, orientation, extents, 0, 1, -1.0)
    assert tiny[0] == box_edits.MIN_EXTENT


def test_fit_to_points_recovers_a_sampled_box():
    position, orientation = random_pose(3)
    truth = np.array([0.07, 0.11, 0.05])
    rng = np.random.default_rng(3)
    local = rng.uniform(-truth / 2, truth / 2, size=(5000, 3))
    local[:8] = box_corners(truth)  # the extremes are present
    points = local @ Rotation.from_quat(orientation).as_matrix().T + position
    far = rng.uniform(-1, 1, size=(500, 3)) + [2.0, 0, 0]  # clutter far outside the box
    start_position = position + [0.01, -0.005, 0.008]
    fitted = box_edits.fit_to_points(np.vstack([points, far]), start_position, orientation, [0.1, 0.14, 0.08], margin=0.01)
    assert fitted is not None
    np.testing.assert_allclose(fitted[1], truth, atol=1e-9)
    np.testing.assert_allclose(fitted[0], position, atol=1e-9)
    assert box_edits.fit_to_points(far, position, orientation, truth) is None


def test_upright_about_y_keeps_the_axis_and_faces_the_camera():
    position = np.array([0.1, -0.05, 0.7])
    tilted = (Rotation.from_euler("x", 180, degrees=True) * Rotation.from_euler("zy", [12, 70], degrees=True)).as_quat()
    R = Rotation.from_quat(tilted).as_matrix()
    snapped = Rotation.from_quat(box_edits.upright_about_y(position, tilted)).as_matrix()
    np.testing.assert_allclose(snapped[:, 1], R[:, 1], atol=1e-12)
    to_camera = -position - np.dot(-position, R[:, 1]) * R[:, 1]
    np.testing.assert_allclose(snapped[:, 2], to_camera / np.linalg.norm(to_camera), atol=1e-12)
    assert np.linalg.det(snapped) == pytest.approx(1.0)
    # the result does not depend on the starting turn about the axis (a consistent choice across frames)
    other = (Rotation.from_quat(tilted) * Rotation.from_euler("y", 123, degrees=True)).as_quat()
    np.testing.assert_allclose(Rotation.from_quat(box_edits.upright_about_y(position, other)).as_matrix(), snapped, atol=1e-12)
    # an estimated axis replaces the box's, signed to agree with it
    up = -np.array([0.0, -1.0, 0.1])
    axis = Rotation.from_quat(box_edits.upright_about_y(position, tilted, up)).as_matrix()[:, 1]
    assert np.dot(axis, R[:, 1]) > 0
    np.testing.assert_allclose(np.abs(axis), np.abs(up) / np.linalg.norm(up), atol=1e-12)
