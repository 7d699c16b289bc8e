"""Real-frame layouts: YCB-Video's videos and BOP scenes open as sequences, each object with its truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy.spatial import cKDTree

from sequences.errors import InputError
from sequences.reader import open_sequence
from sequences.synth import generate_sequence, load_truth
from sequences.synth.options import CaptureOptions, SensorOptions
from sequences.truth import open_truth


@pytest.fixture(scope="module")
def ycbv_dir():
    from conftest import SHARED

    path = SHARED / "ycbv_real"
    if not (path / "0001" / "poses.json").exists():
        pytest.skip(f"YCB-Video frames not found at {path} (../shared is absent)")
    return path


def test_ycbv_video_opens_with_its_camera(ycbv_dir):
    sequence = open_sequence(ycbv_dir / "0001")
    assert sequence.layout == "ycbv" and len(sequence) == 20 and sequence.ids[0] == "000001"
    camera = sequence.camera
    assert (camera.fx, camera.cy, camera.depth_scale) == pytest.approx((1066.778, 241.3109, 1e-4))
    depth = sequence.depth("000001")
    assert depth.shape == (480, 640) and 0.8 < np.median(depth[depth > 0]) < 1.6  # a table about a metre away


@pytest.mark.parametrize("video, name, category", [("0001", "002_master_chef_can", "can"), ("0001", "003_cracker_box", "other"),
                                                   ("0002", "006_mustard_bottle", "bottle"), ("0002", "011_banana", "other")])
def test_ycbv_truth_puts_the_measured_object_on_its_model(ycbv_dir, video, name, category):
    """Independent check of the axes and the centring: the depth inside the object's label, taken into the object frame
    by the truth, lies on the model's points (read here from the file, converted by hand: x, z, -y)."""
    root = ycbv_dir / video
    sequence, truth = open_sequence(root), open_truth(root, name)
    assert truth.category == category and truth.symmetry == ("y" if category in ("can", "bottle") else "none")
    raw = np.loadtxt(ycbv_dir / "models" / name / "points.xyz")
    centre = (raw.min(0) + raw.max(0)) / 2
    model = np.stack([raw[:, 0] - centre[0], raw[:, 2] - centre[2], -(raw[:, 1] - centre[1])], axis=1)
    np.testing.assert_allclose(truth.extents, np.ptp(model, axis=0), atol=1e-9)
    tree = cKDTree(model)
    for frame_id in ("000001", "000020"):
        points, _ = sequence.camera.backproject(sequence.depth(frame_id), truth.mask(frame_id))
        T = truth.poses[frame_id]
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        distance = tree.query((points - T[:3, 3]) @ T[:3, :3])[0]
        assert np.median(distance) < 0.005, (name, frame_id, np.median(distance))


def test_ycbv_bad_object_is_refused(ycbv_dir):
    with pytest.raises(InputError, match="not in this video"):
        open_truth(ycbv_dir / "0001", "025_mug")


def _bop_scene(tmp_path, source, truth, shift_mm):
    """A BOP scene written from a synthetic sequence: depth in 0.1 mm units, the model in millimetres and moved off
    its box centre by ``shift_mm`` (the poses moved to match)."""
    scene = tmp_path / "dataset" / "test" / "000001"
    for sub in ("rgb", "depth", "mask_visib"):
        (scene / sub).mkdir(parents=True)
    (tmp_path / "dataset" / "models").mkdir()
    model = truth.mesh.copy()
    model.vertices = np.asarray(model.vertices) * 1000.0 + shift_mm
    model.export(tmp_path / "dataset" / "models" / "obj_000007.ply")
    cameras, gts = {}, {}
    for image_id, frame_id in enumerate(source.ids):
        Image.fromarray(source.color(frame_id)).save(scene / "rgb" / f"{image_id:06d}.png")
        Image.fromarray((source.depth_raw(frame_id).astype(np.uint32) * 10).astype(np.uint16)).save(scene / "depth" / f"{image_id:06d}.png")
        Image.fromarray((truth.mask(frame_id) * 255).astype(np.uint8)).save(scene / "mask_visib" / f"{image_id:06d}_000001.png")
        cameras[str(image_id)] = {"cam_K": source.camera.K.ravel().tolist(), "depth_scale": 0.1}
        T = truth.poses[frame_id]
        t_model = T[:3, 3] * 1000.0 - T[:3, :3] @ np.asarray(shift_mm)  # the model's origin, in mm
        gts[str(image_id)] = [{"obj_id": 3, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0, 0, 500]},
                              {"obj_id": 7, "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": t_model.tolist()}]
    (scene / "scene_camera.json").write_text(json.dumps(cameras))
    (scene / "scene_gt.json").write_text(json.dumps(gts))
    return scene


def test_bop_scene_opens_with_its_truth(tmp_path):
    root = generate_sequence(tmp_path / "can", "can", frames=3, seed=1, capture=CaptureOptions(sensor=SensorOptions.ideal()))
    source, truth = open_sequence(root), load_truth(root)
    scene = _bop_scene(tmp_path, source, truth, np.array([12.0, -30.0, 5.0]))
    sequence = open_sequence(scene)
    assert sequence.layout == "bop" and sequence.ids == ["000000", "000001", "000002"]
    assert sequence.camera.depth_scale == pytest.approx(1e-4)
    np.testing.assert_allclose(sequence.depth("000001"), source.depth(source.ids[1]), atol=1e-6)
    bop = open_truth(scene, "obj_000007")
    assert bop.category == "other" and bop.symmetry == "none"
    np.testing.assert_allclose(bop.extents, truth.extents, atol=1e-6)
    for image_id, frame_id in enumerate(source.ids):
        np.testing.assert_allclose(bop.poses[f"{image_id:06d}"], truth.poses[frame_id], atol=1e-9)
        assert np.array_equal(bop.mask(f"{image_id:06d}"), truth.mask(frame_id))
    assert isinstance(bop.mesh, trimesh.Trimesh)
    with pytest.raises(InputError, match="appears in no image"):
        open_truth(scene, "obj_000009")
