"""Frames whose geometry leaves the spin free (free_spin.py), on a small synthetic mug.

A cylinder (the mug's body, axis y) with a knob on its -z side (the handle) turns about its axis
in front of a camera, 9 deg a frame. Frames that see the knob pin the spin down by their geometry;
in the others any spin fits the points.
"""

from __future__ import annotations

import numpy as np

from annotate.tracking.config import TrackingConfig
from annotate.tracking.free_spin import FreeSpinCheck
from evaluate.geometry import rotation_about_y
from sequences.camera import Camera

RADIUS, HEIGHT, KNOB_RADIUS = 0.04, 0.1, 0.014
KNOB_CENTRE = np.array([0.0, 0.0, -0.056])
CAMERA = Camera(fx=600.0, fy=600.0, cx=160.0, cy=120.0, width=320, height=240)


def _surface(step: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """Object-frame points (N, 3) and outward normals (N, 3) of the body and the knob, ~``step`` apart."""
    angles = np.arange(0.0, 2 * np.pi, step / RADIUS)
    heights = np.arange(-HEIGHT / 2, HEIGHT / 2, step)
    a, h = np.meshgrid(angles, heights)
    a, h = a.ravel(), h.ravel()
    body_n = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=1)
    body = body_n * RADIUS + np.stack([np.zeros_like(h), h, np.zeros_like(h)], axis=1)
    rng = np.random.default_rng(0)
    knob_n = rng.normal(size=(int(4 * np.pi * KNOB_RADIUS**2 / step**2), 3))
    knob_n /= np.linalg.norm(knob_n, axis=1, keepdims=True)
    knob_n = knob_n[knob_n[:, 2] < 0.3]  # the half sticking out of the body
    knob = KNOB_CENTRE + KNOB_RADIUS * knob_n
    return np.concatenate([body, knob]), np.concatenate([body_n, knob_n])


def _true_pose(i: int) -> np.ndarray:
    """Frame i: the knob faces the camera (object -z toward it) at frame 0 and turns away by 9 deg per frame."""
    T = np.eye(4)
    T[:3, :3] = rotation_about_y(np.radians(9.0 * i))
    T[:3, 3] = [0.0, 0.0, 0.5]
    return T


def _behind_body(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(N,) bool: object-frame points whose ray from the camera crosses the body (seen from the side: in x-z)."""
    c = (-T[:3, :3].T @ T[:3, 3])[[0, 2]]
    d = points[:, [0, 2]] - c
    s = np.clip(-(d @ c) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    closest = c + s[:, None] * d
    inside = np.linalg.norm(points[:, [0, 2]], axis=1) < RADIUS * 0.999  # the knob's half inside the body
    return inside | ((np.linalg.norm(closest, axis=1) < RADIUS * 0.98) & (s < 0.999))


def _scene(frames: int) -> dict[str, np.ndarray]:
    """Per frame: every third visible camera-frame point, in a scattered order like a voxel grid's."""
    points, normals = _surface()
    scene = {}
    for i in range(frames):
        T = _true_pose(i)
        cam = points @ T[:3, :3].T + T[:3, 3]
        seen = (np.einsum("ij,ij->i", normals @ T[:3, :3].T, -cam) > 0) & ~_behind_body(points, T)
        scene[str(i)] = cam[seen][np.random.default_rng(i).permutation(int(seen.sum()))[::3]]
    return scene


class _Tracker:
    """What FreeSpinCheck asks of a Tracker: its configuration and crops."""

    def __init__(self, scene: dict[str, np.ndarray]) -> None:
        self.config = TrackingConfig(min_points=40)
        self.scene = scene

    def crop(self, frame_id: str, pose: np.ndarray, margin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        points = self.scene[frame_id]
        return points, np.zeros_like(points)


def _knob_in_view(i: int) -> bool:
    """Whether frame i's camera sees the knob (its centre's side of the body faces the camera, with a margin)."""
    T = _true_pose(i)
    return (T[:3, :3] @ KNOB_CENTRE)[2] < -0.02


def test_the_frames_that_hide_the_knob_leave_the_spin_free_and_the_others_fix_it():
    frames = 40  # 360 deg: the knob in view, behind the body, and back
    check = FreeSpinCheck(_Tracker(_scene(frames)), _surface(0.003)[0])
    np.testing.assert_allclose(np.abs(check.axis), [0.0, 1.0, 0.0], atol=0.02)
    assert check.round()
    free = set(check.free_frames({str(i): _true_pose(i) for i in range(frames)}))
    hidden = {str(i) for i in range(frames) if (_true_pose(i)[:3, :3] @ KNOB_CENTRE)[2] > 0.045}  # well behind the body
    seen = {str(i) for i in range(frames) if _knob_in_view(i)}
    assert hidden and seen
    assert hidden <= free, "a frame whose knob is behind the body leaves the spin to the motion"
    assert not seen & free, "a frame that sees the knob has its spin fixed by its geometry"
