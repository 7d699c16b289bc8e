"""The slide check (slide.py): a flat object slid along its faces is found by the fitness of a wider crop,
against rendered frames whose true poses are known."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_tracking_render import render_sequence

from annotate.tracking import TrackingConfig
from annotate.tracking.config import scaled_to
from annotate.tracking.frames import FrameStore
from annotate.tracking.refine import build_model, min_hits_for
from annotate.tracking.slide import best_shift, shifted, slide_corrections, weak_direction
from annotate.tracking.tracker import FrameResult, Tracker
from sequences.reader import open_sequence

SLIDE = 0.02  # m, along the hinge (object x)


def laptop_mesh() -> trimesh.Trimesh:
    """An open laptop at 90 deg: a base in the x-z plane and a lid in the x-y plane, 30 cm wide along x (the hinge)."""
    base = trimesh.creation.box(extents=[0.30, 0.012, 0.22])
    base.apply_translation([0, 0, 0.11])
    lid = trimesh.creation.box(extents=[0.30, 0.22, 0.012])
    lid.apply_translation([0, 0.11, 0])
    mesh = trimesh.util.concatenate([base, lid])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def facing_poses(count: int) -> list[np.ndarray]:
    """Object-to-camera poses looking at the base's top and the lid's front (from object (0, 1, 1)), where the side
    faces that would pin the slide down are edge-on; a few degrees of wobble."""
    d = np.array([0.0, 1.0, 1.0]) / np.sqrt(2)
    R0 = np.stack([[1.0, 0.0, 0.0], np.cross(-d, [1.0, 0.0, 0.0]), -d])  # rows: camera x, y, z in object axes
    poses = []
    for k in range(count):
        wobble = Rotation.from_euler("xy", [4.0 * np.sin(k), 3.0 * np.cos(k)], degrees=True).as_matrix()
        T = np.eye(4)
        T[:3, :3] = wobble @ R0
        T[:3, 3] = [0.01 * np.sin(k), 0.01 * np.cos(k), 0.7]
        poses.append(T)
    return poses


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("slide") / "laptop_0001"
    mesh = laptop_mesh()
    truth = render_sequence(root, mesh, frames=6, seed=1, hand=False, poses=facing_poses(6))
    config = scaled_to(TrackingConfig(), mesh.extents)
    tracker = Tracker(FrameStore(open_sequence(root), config.stride, colors=False), mesh.extents, False, config)
    model = build_model(tracker, truth, config.max_global_frames)
    return tracker, truth, model.target(min_hits_for(model, config))


def test_the_weak_direction_of_two_faces_is_their_common_edge(scene):
    tracker, truth, target = scene
    frame_id = sorted(truth)[0]
    points, _ = tracker.crop(frame_id, truth[frame_id])
    local = (points - truth[frame_id][:3, 3]) @ truth[frame_id][:3, :3]
    direction, ratio = weak_direction(local, target, 2 * tracker.config.voxel_size, tracker.config.information_sigma)
    assert abs(direction[0]) > 0.99
    assert ratio < tracker.config.max_slide_ratio


def test_best_shift_of_a_plate_seen_whole():
    # a 30 cm plate's points, 2 cm beyond the model along x: the fitness is highest once they move back by 2 cm
    from annotate.tracking.registration import ModelTarget

    grid = np.stack(np.meshgrid(np.arange(-0.15, 0.1501, 0.002), np.arange(-0.1, 0.1001, 0.002), indexing="ij"), -1).reshape(-1, 2)
    plate = np.column_stack([grid[:, 0], np.zeros(len(grid)), grid[:, 1]])
    target = ModelTarget(plate, voxel_size=0.002)
    shift, fitness, at_zero, beyond = best_shift(plate + [SLIDE, 0, 0], target, np.array([1.0, 0, 0]), 0.04, 0.003)
    assert shift == pytest.approx(SLIDE, abs=0.001)
    assert fitness == pytest.approx(1.0)
    assert at_zero == pytest.approx(1 - SLIDE / 0.30, abs=0.01)
    assert beyond == pytest.approx(1 - (0.015 - 0.003) / 0.30, abs=0.005)  # past the peak the far edge sticks out (less the inlier distance)


def test_slid_frames_are_moved_back_and_the_others_are_left(scene):
    tracker, truth, target = scene
    ids = sorted(truth)
    slid = set(ids[1::2])
    results = {f: FrameResult(shifted(truth[f], np.array([SLIDE, 0, 0])) if f in slid else truth[f].copy(), True, {}) for f in ids}
    corrections = slide_corrections(tracker, results, target)
    assert set(corrections) == slid
    for f in slid:
        corrected = shifted(results[f].pose, corrections[f])
        assert np.linalg.norm(corrected[:3, 3] - truth[f][:3, 3]) < 0.002
    # manual frames (skip) and a disabled check are left alone
    assert slide_corrections(tracker, results, target, skip=slid) == {}
    from dataclasses import replace

    off = Tracker(tracker.store, tracker.extents, False, replace(tracker.config, slide_check=False))
    assert slide_corrections(off, results, target) == {}


def test_a_plate_whose_far_edge_is_hidden_gives_no_peak():
    # only x < 5 cm of the plate seen (a hand over the rest), 2 cm beyond the model's left edge: every shift that
    # brings the left edge back fits fully, so the fitness past the best shift is as high as at it
    from annotate.tracking.registration import ModelTarget

    grid = np.stack(np.meshgrid(np.arange(-0.15, 0.1501, 0.002), np.arange(-0.1, 0.1001, 0.002), indexing="ij"), -1).reshape(-1, 2)
    plate = np.column_stack([grid[:, 0], np.zeros(len(grid)), grid[:, 1]])
    seen = plate[plate[:, 0] < 0.05] - [SLIDE, 0, 0]
    shift, fitness, at_zero, beyond = best_shift(seen, ModelTarget(plate, voxel_size=0.002), np.array([1.0, 0, 0]), 0.04, 0.003)
    assert shift < -SLIDE + 0.003 and fitness == pytest.approx(1.0) and at_zero < 0.95
    assert fitness - beyond < TrackingConfig().min_slide_gain / 2


def _walk(count: int) -> dict[str, FrameResult]:
    """Frames moving 1 cm per frame along camera x, unrotated (so object and camera axes agree)."""
    out = {}
    for k in range(count):
        pose = np.eye(4)
        pose[:3, 3] = [0.01 * k, 0.0, 0.7]
        out[f"{k:06d}"] = FrameResult(pose, True, {})
    return out


def test_a_lone_slide_off_the_path_is_refused_and_flagged():
    from annotate.tracking.quality import flag_reasons
    from annotate.tracking.slide import against_the_motion

    results = _walk(7)
    ids = list(results)
    # frame 2 slides 2 cm along z, off the straight path its neighbours keep
    assert against_the_motion(results, {ids[2]: np.array([0.0, 0.0, 0.02])}, 0.002) == {ids[2]}
    # frames 3-5 slid together by 2 cm along x and back onto the path: 4 has both neighbours' support, 3 and 5 come
    # closer to their midpoints
    off = dict(results)
    for f in ids[3:6]:
        pose = results[f].pose.copy()
        pose[0, 3] -= 0.02
        off[f] = FrameResult(pose, True, {})
    back = {f: np.array([0.02, 0.0, 0.0]) for f in ids[3:6]}
    assert against_the_motion(off, back, 0.002) == set()
    # a slide judged by a neighbour whose own pose is in doubt is not judged at all
    assert against_the_motion(results, {ids[2]: np.array([0.0, 0.0, 0.02])}, 0.002, {ids[1]}) == set()
    # the refused slide flags the frame
    reasons = flag_reasons({"slide_rejected_m": 0.02}, TrackingConfig())
    assert len(reasons) == 1 and "20 mm" in reasons[0]
