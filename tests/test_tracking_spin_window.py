"""The spin of suspect frames from a window of their neighbours (annotate/tracking/spin_window.py)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from annotate.tracking.spin_window import windowed_spins

AXIS = Rotation.from_rotvec(np.radians([2.0, 0.0, -1.0])).apply([0.0, 1.0, 0.0])  # the body's axis, object frame
POINT = np.array([0.0, 0.0, -0.012])  # ... through a point off the box centre (a mug's handle shifts the box)


def _spun(spin_deg: float) -> np.ndarray:
    """4x4 object-frame spin about the body's axis."""
    S = np.eye(4)
    S[:3, :3] = Rotation.from_rotvec(np.radians(spin_deg) * AXIS).as_matrix()
    S[:3, 3] = POINT - S[:3, :3] @ POINT
    return S


def _motion(count: int) -> list[np.ndarray]:
    """A hand turning the object smoothly: a spin of 2 deg per frame about its axis, on a moving, tilted pose."""
    base = np.eye(4)
    base[:3, :3] = Rotation.from_rotvec([0.4, -0.3, 0.2]).as_matrix()
    out = []
    for i in range(count):
        moved = base.copy()
        moved[:3, 3] = [0.01 * i, 0.0, 0.6]
        out.append(moved @ _spun(2.0 * i))
    return out


def _spin_error_deg(pose: np.ndarray, truth: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(truth[:3, :3].T @ pose[:3, :3]).as_rotvec())))


def test_a_jittered_spin_is_brought_back_to_the_smooth_motion():
    truth = _motion(20)
    jitter = [4.0 if i % 2 else -4.0 for i in range(20)]  # the spin alternating from frame to frame
    poses = [p @ _spun(j) for p, j in zip(truth, jitter)]
    selected = [2 <= i <= 17 for i in range(20)]
    out = windowed_spins(poses, selected, 2, AXIS, POINT)
    # five frames' mean: the alternating +-4 deg leaves 0.8 deg (one frame's worth of it over five)
    for i in range(20):
        if selected[i]:
            assert abs(_spin_error_deg(out[i], truth[i]) - 0.8) < 1e-6
        else:
            assert np.array_equal(out[i], poses[i])
    # the turn is about the body's axis: its point stays where it was in the camera
    for i in range(2, 18):
        assert np.allclose(out[i][:3, :3] @ POINT + out[i][:3, 3], poses[i][:3, :3] @ POINT + poses[i][:3, 3], atol=1e-12)


def test_a_smooth_spin_is_kept_and_the_window_is_cut_at_the_ends():
    truth = _motion(12)
    out = windowed_spins(truth, [True] * 12, 3, AXIS, POINT)
    # a constant turn averages to itself over a symmetric window
    assert max(_spin_error_deg(o, t) for o, t in zip(out, truth)) < 1e-9
    # at the ends the window shrinks to stay symmetric: the first and last frames keep their poses
    poses = [p @ _spun(5.0) if i in (0, 11) else p for i, p in enumerate(truth)]
    out = windowed_spins(poses, [True] * 12, 3, AXIS, POINT)
    assert np.array_equal(out[0], poses[0]) and np.array_equal(out[11], poses[11])
    # frame 1 averages frames 0-2 only: 5 deg / 3 of frame 0's error
    assert abs(_spin_error_deg(out[1], truth[1]) - 5.0 / 3.0) < 1e-6


def test_only_the_spin_is_averaged_not_the_tilt():
    truth = _motion(9)
    tilt = np.eye(4)
    tilt[:3, :3] = Rotation.from_rotvec(np.radians(3.0) * np.cross(AXIS, [1.0, 0.0, 0.0]) / np.linalg.norm(np.cross(AXIS, [1.0, 0.0, 0.0]))).as_matrix()
    poses = [p @ tilt if i == 4 else p for i, p in enumerate(truth)]
    out = windowed_spins(poses, [i == 4 for i in range(9)], 2, AXIS, POINT)
    # the tilt is not the spin's to fix: the frame keeps it (to second order: 3 deg off the axis, 2e-3 deg)
    assert abs(_spin_error_deg(out[4], truth[4]) - 3.0) < 0.01
    assert windowed_spins([], [], 2, AXIS, POINT) == []


def test_a_failed_frame_neither_moves_nor_pulls_its_neighbours():
    truth = _motion(10)
    poses = [p @ _spun(30.0) if i == 5 else p for i, p in enumerate(truth)]  # its registration failed: a start only
    usable = [i != 5 for i in range(10)]
    out = windowed_spins(poses, [True] * 10, 2, AXIS, POINT, usable)
    assert np.array_equal(out[5], poses[5])
    # its neighbours average the others only (a 30 deg outlier would have moved them by 6 deg)
    assert max(_spin_error_deg(out[i], truth[i]) for i in range(10) if i != 5) < 1e-9
    everyone = windowed_spins(poses, [True] * 10, 2, AXIS, POINT)
    assert abs(_spin_error_deg(everyone[4], truth[4]) - 6.0) < 1e-6
