"""Free-space votes against model voxels, registration information, and the information-weighted smoothing."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from annotate.tracking.freespace import free_space_votes
from annotate.tracking.registration import ModelTarget
from annotate.tracking.smooth import registration_information, smooth_poses
from sequences.camera import Camera


class _PlaneStore:
    """A FrameStore stand-in: every frame sees a wall at ``depth`` m (stride 2), one frame unreadable."""

    def __init__(self, depth: float) -> None:
        camera = Camera()
        self.sequence = SimpleNamespace(camera=camera)
        self.stride = 2
        self.errors = {"bad": "unreadable"}
        self._depth = np.full((camera.height // 2, camera.width // 2), depth, np.float32)

    def image(self, frame_id: str):
        return self._depth, None


def test_free_space_votes_count_frames_that_see_through_a_point():
    store = _PlaneStore(1.0)
    # object frame = camera frame shifted: points in front of, on and behind the wall, and outside the image
    points = np.array([[0.0, 0.0, 0.9], [0.05, 0.0, 1.0], [0.0, 0.02, 1.2], [5.0, 0.0, 1.0]])
    poses = {f: np.eye(4) for f in ("a", "b", "c", "bad")}
    through, seen = free_space_votes(points, poses, store, tolerance=0.01)
    # three readable frames: the point 10 cm in front of the wall is seen through by all, the one on it seen by
    # all; the one behind the wall is hidden (no vote), the one outside the image gets none
    assert through.tolist() == [3, 0, 0, 0]
    assert seen.tolist() == [0, 3, 0, 0]


def _cylinder(radius: float = 0.04, height: float = 0.1, n: int = 3000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    y = rng.uniform(-height / 2, height / 2, n)
    normals = np.stack([np.cos(angle), np.zeros(n), np.sin(angle)], axis=1)
    return normals * radius + np.outer(y, [0, 1, 0]), normals


def test_information_of_a_cylinder_leaves_the_spin_and_the_slide_along_its_axis_free():
    points, _ = _cylinder()
    target = ModelTarget(points, voxel_size=0.004)
    H = registration_information(points[::3], target, distance=0.004, sigma=0.002)
    # a surface of revolution about y: rotation about y and translation along y do not move it (up to the
    # model's estimated normals, 1-3 deg off): compared within the rotations and within the translations
    assert H[1, 1] < 1e-2 * min(H[0, 0], H[2, 2])
    assert H[4, 4] < 1e-2 * min(H[3, 3], H[5, 5])
    # the other directions: sum of (lever arm)^2 / sigma^2, about n * r^2 / 2 / sigma^2 for tilts about x
    n = len(points[::3])
    tilt = H[0, 0]
    assert 0.1 * n * 0.04**2 / 0.002**2 < tilt < 2 * n * 0.04**2 / 0.002**2


def _rotating_poses(n: int = 40) -> list[np.ndarray]:
    """A box turning at a constant 3 deg per frame about a tilted axis while moving 2 mm per frame."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    poses = []
    for i in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(axis * np.radians(3.0 * i)).as_matrix()
        T[:3, 3] = [0.002 * i, 0.0, 0.6]
        poses.append(T)
    return poses


def test_smoothing_takes_a_weak_direction_from_the_neighbours_and_keeps_the_strong_ones():
    truth = _rotating_poses()
    strong = np.diag([1e8, 1e8, 1e8, 1e10, 1e10, 1e10])  # about 0.006 deg and 0.01 mm
    weak_y = strong.copy()
    weak_y[1, 1] = 1.0  # the spin about the object's y is not observed
    rng = np.random.default_rng(0)
    noisy, information = [], []
    for i, T in enumerate(truth):
        P = T.copy()
        if 10 <= i < 25:  # these frames spun off by up to 3 deg about their own y
            P[:3, :3] = P[:3, :3] @ Rotation.from_rotvec([0, np.radians(rng.uniform(-3, 3)), 0]).as_matrix()
            information.append(weak_y)
        else:
            information.append(strong)
        noisy.append(P)
    out = smooth_poses(noisy, information, np.radians(0.5), 0.0005)
    errors = [np.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude()) for a, b in zip(out, truth)]
    before = [np.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude()) for a, b in zip(noisy, truth)]
    assert max(before[10:25]) > 1.5
    assert max(errors) < 0.1, np.round(errors, 2)
    assert max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(out, truth)) < 1e-4


def test_smoothing_of_a_symmetric_object_follows_its_axis_whatever_the_spin():
    truth = _rotating_poses(30)
    strong = np.diag([1e8, 0.0, 1e8, 1e10, 1e10, 1e10])  # symmetry y: the spin carries no information
    weak_x = np.diag([1.0, 0.0, 1e8, 1e10, 1e10, 1e10])
    rng = np.random.default_rng(1)
    posed, information = [], []
    for i, T in enumerate(truth):
        P = T.copy()
        spin = 0.3 * (i % 2)  # the registration returns any spin: it jumps by 17 deg from frame to frame
        tilt = np.radians(rng.uniform(1.5, 3.0)) if 10 <= i < 16 else 0.0  # these frames tilted off about their x
        P[:3, :3] = P[:3, :3] @ Rotation.from_rotvec([0, spin, 0]).as_matrix() @ Rotation.from_rotvec([tilt, 0, 0]).as_matrix()
        posed.append(P)
        information.append(weak_x if 10 <= i < 16 else strong)
    out = smooth_poses(posed, information, np.radians(0.5), 0.0005, free_y=True)
    axis_error = [np.degrees(np.arccos(np.clip(a[:3, 1] @ b[:3, 1], -1, 1))) for a, b in zip(out, truth)]
    assert max(axis_error) < 0.1, np.round(axis_error, 2)
    # the spin is left as it was: the output differs from the input by a tilt only (no rotation about y)
    for a, b in zip(out, posed):
        assert abs(Rotation.from_matrix(b[:3, :3].T @ a[:3, :3]).as_rotvec()[1]) < 1e-3


def test_a_placed_box_sets_a_direction_no_frame_observes():
    truth = _rotating_poses(20)
    weak_y = np.diag([1e8, 0.0, 1e8, 1e10, 1e10, 1e10])  # no frame sees the spin about y
    spun = []
    for T in truth:  # every frame spun 2 deg off about its y, smoothly (the smoothness alone cannot tell)
        P = T.copy()
        P[:3, :3] = P[:3, :3] @ Rotation.from_rotvec([0, np.radians(2.0), 0]).as_matrix()
        spun.append(P)
    # a box placed on frame 5 at the true pose, with a person's confidence (1 deg, 2 mm per axis)
    D = np.linalg.inv(spun[5]) @ truth[5]
    target = np.concatenate([Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]])
    info = np.diag([1 / np.radians(1.0) ** 2] * 3 + [1 / 0.002**2] * 3)
    out = smooth_poses(spun, [weak_y] * len(spun), np.radians(0.5), 0.0005, priors={5: (target, info)})
    errors = [np.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude()) for a, b in zip(out, truth)]
    assert max(errors) < 0.05, np.round(errors, 3)


def test_a_suspect_frame_keeps_its_information_where_the_refinement_confirmed_its_chains():
    from annotate.tracking import TrackingConfig
    from annotate.tracking.refine import refinement_confirmed
    from annotate.tracking.tracker import FrameResult

    config = TrackingConfig()  # chain-disagreement thresholds 5 deg, 10 mm; min fitness 0.5
    tracker = SimpleNamespace(config=config, symmetric=False)
    chained = {f: np.eye(4) for f in "abcdef"}

    def moved(deg: float, metres: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("x", deg, degrees=True).as_matrix()
        T[:3, 3] = [metres, 0.0, 0.0]
        return T

    results = {
        "a": FrameResult(moved(2.0, 0.003), True, {"fitness": 0.8}),  # a small correction: confirmed
        "b": FrameResult(moved(20.0, 0.0), True, {"fitness": 0.9}),  # slid 20 deg (a near-sphere)
        "c": FrameResult(moved(0.0, 0.015), True, {"fitness": 0.9}),  # slid 15 mm
        "d": FrameResult(moved(1.0, 0.0), True, {"fitness": 0.3}),  # fits poorly
        "e": FrameResult(moved(1.0, 0.0), False, {"fitness": 0.9}),  # failed
        "g": FrameResult(np.eye(4), True, {"fitness": 0.9}),  # no chains' pose
    }
    assert refinement_confirmed(tracker, results, chained) == {"a"}
