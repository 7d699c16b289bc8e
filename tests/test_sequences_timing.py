"""Poses moved between a frame's colour and depth instants (sequences.timing), against an analytic motion: a body
spinning at a constant rate about a fixed axis of its own while its centre moves at a constant velocity, for which
the geodesic interpolation of the rotation and the linear one of the centre are exact; and the reconstruction of a box
whose depth is taken after its colour, against the same box's with depth and colour together."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import trimesh
import yaml
from PIL import Image
from scipy.spatial.transform import Rotation
from test_reconstruct_scenes import render_depth

import reconstruct.pipeline as pipeline
from sequences.annotation import load_annotation
from sequences.camera import Camera
from sequences.reader import FrameFiles, open_sequence
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


def _turntable(t_us: float) -> np.ndarray:
    """A box turning fast about the camera's vertical axis 0.5 m away (three quarters of a turn a second: 9 deg a frame,
    every side in 40 frames) while it rises."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xy", [-35.0, 270.0 * t_us / 1e6], degrees=True).as_matrix()
    T[:3, 3] = [0.0, 0.01 - 0.15 * t_us / 1e6, 0.5]  # rising at 15 cm/s (image y points down)
    return T


def _turntable_scene(root: Path, depth_offset: float) -> Path:
    """40 frames of a box on the turntable (Redwood names with timestamps), depth taken ``depth_offset`` frame periods
    after colour; the document holds the colour instants' true poses."""
    camera = Camera(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)
    box = trimesh.creation.box([0.08, 0.06, 0.05])
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    (root / "camera.yaml").write_text(yaml.safe_dump(camera.to_dict()))
    frames = {}
    for i in range(40):
        t_colour, t_depth = 1_000_000 + i * PERIOD_US, 1_000_000 + (i + depth_offset) * PERIOD_US
        depth = render_depth([box.copy().apply_transform(_turntable(t_depth))], camera)
        Image.fromarray(np.rint(depth * 1000).astype(np.uint16)).save(root / "depth" / f"{i:07d}-{int(t_depth):012d}.png")
        Image.fromarray(np.full((240, 320, 3), 128, np.uint8)).save(root / "rgb" / f"{i:07d}-{int(t_colour):012d}.png")
        T = _turntable(t_colour)
        frames[f"{i:07d}"] = {"position": T[:3, 3].tolist(), "orientation": Rotation.from_matrix(T[:3, :3]).as_quat().tolist(), "source": "manual"}
    doc = {"sequence": root.name, "category": "other", "symmetry": "none", "extents": [0.08, 0.06, 0.05], "frames": frames}
    (root / "annotation.yaml").write_text(yaml.safe_dump(doc))
    return root


def test_the_reconstruction_poses_each_depth_image_at_its_own_instant(tmp_path, monkeypatch):
    """Depth taken 0.4 frame periods after colour (3.6 deg and 2 mm of the box's motion), the document at the colour
    instants: posed at the depth instants, the carving's box matches the one of depth taken with the colour (a second
    scene, no offset; its views 3.6 deg apart from these, a millimetre apart) within 1.5 mm; posed at the colour
    instants it is 3.9 mm off."""
    def carved(root: Path):
        return pipeline.reconstruct_sequence(open_sequence(root), load_annotation(root / "annotation.yaml"), surface="carving")

    monkeypatch.setattr(pipeline, "BOX_BOUND_SLACK", 1.0)  # the carving's own fit: the box's bound would clip the smear

    reference = carved(_turntable_scene(tmp_path / "together", 0.0))
    late = _turntable_scene(tmp_path / "late", 0.4)
    np.testing.assert_allclose(carved(late).extents, reference.extents, atol=0.0015)
    monkeypatch.setattr(pipeline.timing, "at_depth_time", lambda sequence, poses: dict(poses))  # the colour instants
    assert np.abs(carved(late).extents - reference.extents).max() > 0.003
