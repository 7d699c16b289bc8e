"""Poses moved between a frame's colour and depth instants (sequences.timing), against an analytic motion: a body
spinning at a constant rate about a fixed axis of its own while its centre moves at a constant velocity, for which
the geodesic interpolation of the rotation and the linear one of the centre are exact."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from sequences.reader import FrameFiles
from sequences.timing import at_colour_time, at_depth_time, resample_poses

PERIOD_US = 33_333.0
AXIS = np.array([0.3, 0.8, -0.52]) / np.linalg.norm([0.3, 0.8, -0.52])
RATE = np.radians(90.0) / 1e6  # rad per microsecond: a quarter turn per second
START = Rotation.from_euler("xyz", [10.0, -40.0, 25.0], degrees=True).as_matrix()
VELOCITY = np.array([0.2, -0.05, 0.1]) / 1e6  # metres per microsecond (a hand's 23 cm/s)


def pose_at(t: float) -> np.ndarray:
    """The true object-to-camera pose at instant ``t`` (microseconds)."""
    T = np.eye(4)
    T[:3, :3] = START @ Rotation.from_rotvec(AXIS * RATE * t).as_matrix()
    T[:3, 3] = np.array([0.0, 0.0, 0.7]) + VELOCITY * t
    return T


def test_resampled_poses_follow_the_motion_between_and_beyond_the_track():
    times = np.arange(10) * PERIOD_US
    poses = np.stack([pose_at(t) for t in times])
    queries = np.array([-0.4, 0.25, 3.5, 3.999, 8.7, 9.45]) * PERIOD_US  # before, within and after the track
    got = resample_poses(poses, times, queries)
    want = np.stack([pose_at(t) for t in queries])
    np.testing.assert_allclose(got, want, atol=1e-9)
    # the track's order does not matter, a single pose stays put
    shuffled = np.random.default_rng(0).permutation(10)
    np.testing.assert_allclose(resample_poses(poses[shuffled], times[shuffled], queries), want, atol=1e-9)
    np.testing.assert_allclose(resample_poses(poses[:1], times[:1], queries), np.repeat(poses[:1], len(queries), axis=0))


def _sequence(colour: np.ndarray, depth: np.ndarray | None) -> SimpleNamespace:
    frames = [FrameFiles(f"{i:07d}", Path("c.png"), Path("d.png"), int(c), None if depth is None else int(d))
              for i, (c, d) in enumerate(zip(colour, colour if depth is None else depth))]
    return SimpleNamespace(frames=frames)


def test_colour_time_poses_move_to_the_depth_instants_and_back():
    colour = np.arange(12) * PERIOD_US
    depth = colour + 0.3 * PERIOD_US  # depth taken 0.3 frame periods after colour, as a PrimeSense pairs them
    sequence = _sequence(colour, depth)
    at_colour = {f.id: pose_at(f.color_time_us) for f in sequence.frames}
    moved = at_depth_time(sequence, at_colour)
    for f in sequence.frames:  # each pose where the object stood when its depth was taken: 2 mm and 2.7 deg away
        np.testing.assert_allclose(moved[f.id], pose_at(f.depth_time_us), atol=1e-9)
    back = at_colour_time(sequence, moved)
    for f in sequence.frames:
        np.testing.assert_allclose(back[f.id], at_colour[f.id], atol=1e-9)
    # without timestamps nothing moves
    untimed = _sequence(colour, None)
    untimed.frames = [FrameFiles(f.id, f.color_path, f.depth_path) for f in untimed.frames]
    unmoved = at_depth_time(untimed, at_colour)
    assert all(np.array_equal(unmoved[f], at_colour[f]) for f in at_colour)
