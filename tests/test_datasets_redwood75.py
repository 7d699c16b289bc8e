"""REDWOOD75 reader: agreement with cpas_toolbox's AnnotatedRedwoodDataset, frame lookup, masks, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from evaluate.datasets import open_dataset
from evaluate.datasets.redwood75 import Redwood75Dataset, frame_id
from sequences.errors import InputError


def _same_rotation(q_a, q_b) -> float:
    """Angle (deg) between two quaternions' rotations."""
    return np.degrees((Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude())


def test_counts_and_missing_meshes(redwood75_dir):
    data = Redwood75Dataset(redwood75_dir)
    assert len(data) == 75
    assert data.categories == ["bottle", "bowl", "mug"]
    with_mesh = {s.sequence for s in data if s.mesh_path is not None}
    assert with_mesh == {"00015", "00340", "00517", "00591", "00595", "00675"}
    assert len(data.missing_meshes) == 9
    symmetric = {s.category: s.symmetry for s in data}
    assert symmetric == {"bottle": "y", "bowl": "y", "mug": "none"}
    assert frame_id("0000210-000007004844.jpg") == "0000210"
    assert frame_id("frame_12.png") == "frame_12"


def test_remapping_by_hand(redwood75_dir):
    """Independent check of the axis remapping: raw x = ShapeNet z, raw y = -ShapeNet y, raw z = ShapeNet x."""
    raw = json.loads((redwood75_dir / "annotations.json").read_text())["00015"]
    sample = Redwood75Dataset(redwood75_dir).samples[0]
    ann = raw["pose_anns"][0]
    R_raw = Rotation.from_quat(ann["orientation"]).as_matrix()
    R = Rotation.from_quat(sample.orientation).as_matrix()
    # the ShapeNet z axis is the raw x axis, ShapeNet y is raw -y, ShapeNet x is raw z (in camera coordinates)
    np.testing.assert_allclose(R[:, 2], R_raw[:, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 1], -R_raw[:, 1], atol=1e-12)
    np.testing.assert_allclose(R[:, 0], R_raw[:, 2], atol=1e-12)
    np.testing.assert_allclose(sample.extents, 2 * np.array(raw["scale"])[[2, 1, 0]])
    np.testing.assert_allclose(sample.position, ann["position"])


@pytest.mark.slow  # imports torch and cpas_toolbox: 17 s measured on the loaded 2-core machine
def test_agrees_with_cpas_toolbox(redwood75_dir, tmp_path):
    redwood = pytest.importorskip("cpas_toolbox.datasets.redwood_dataset")
    root = tmp_path / "redwood"
    root.mkdir()
    theirs = redwood.AnnotatedRedwoodDataset(
        {"root_dir": str(root), "ann_dir": str(redwood75_dir), "camera_convention": "opencv", "scale_convention": "full", "remap_y_axis": "-y", "remap_x_axis": "z"}
    )
    ours = Redwood75Dataset(redwood75_dir, frames=root)
    assert len(theirs) == len(ours)
    for raw, sample in zip(theirs._raw_samples, ours.samples):
        q, extents = theirs._change_axis_convention(raw["orientation_q"], raw["extents"])
        assert raw["category_str"] == sample.category
        np.testing.assert_allclose(sample.position, raw["position"].numpy(), atol=1e-6)  # torch float32
        assert _same_rotation(q.numpy(), sample.orientation) < 1e-4
        np.testing.assert_allclose(sample.extents, extents.numpy(), rtol=1e-6)
        assert Path(raw["mesh_path"]).name == Path(json.loads((redwood75_dir / "annotations.json").read_text())[sample.sequence]["mesh"]).name
    # meshes: their load_mesh (open3d, rotated) against ours (trimesh, remapped), as point sets
    for sample in ours.samples[::5]:
        if sample.mesh_path is None:
            continue
        their_vertices = np.asarray(theirs.load_mesh(str(sample.mesh_path)).vertices)
        our_vertices = np.asarray(ours.mesh(sample).vertices)
        d_ab, _ = cKDTree(our_vertices).query(their_vertices)
        d_ba, _ = cKDTree(their_vertices).query(our_vertices)
        assert max(d_ab.max(), d_ba.max()) < 1e-7
        # the mesh fits the box: its bounds are the extents
        np.testing.assert_allclose(np.ptp(our_vertices, axis=0), sample.extents, atol=1e-6)


def _write_frames(root: Path, layout: str, sequence: str, category: str, rgb: str, depth: str) -> Path:
    seq = root / sequence if layout == "ours" else root / category / "rgbd" / sequence
    (seq / "rgb").mkdir(parents=True, exist_ok=True)
    (seq / "depth").mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((480, 640, 3), 100, np.uint8)).save(seq / "rgb" / rgb)
    Image.fromarray(np.full((480, 640), 2000, np.uint16)).save(seq / "depth" / depth)
    return seq


@pytest.mark.parametrize("layout", ["ours", "cpas"])
def test_frame_layouts_and_mask(redwood75_dir, tmp_path, layout):
    ann = json.loads((redwood75_dir / "annotations.json").read_text())["00015"]["pose_anns"][1]
    seq = _write_frames(tmp_path, layout, "00015", "mug", ann["rgb_file"], ann["depth_file"])
    data = Redwood75Dataset(redwood75_dir, frames=tmp_path)
    sample = next(s for s in data if s.sequence == "00015" and s.frame == "0000210")
    assert sample.color_path == seq / "rgb" / ann["rgb_file"]
    assert sample.depth_path == seq / "depth" / ann["depth_file"]
    assert data.color(sample).shape == (480, 640, 3)
    depth = data.depth(sample)
    assert depth.dtype == np.float32 and depth[0, 0] == pytest.approx(2.0)
    # the mask covers the projection of the box centre, and none of the pixels far away
    mask = data.mask(sample, None)
    u, v = sample.camera.project(sample.position[None])[0][0]
    assert mask[int(round(v)), int(round(u))]
    assert not mask[0, 0]
    # the object (~0.97 m) is in front of the wall (2 m): nothing is occluded
    np.testing.assert_array_equal(data.mask(sample, depth), mask)
    # a wall at 0.5 m in front of the object occludes it entirely
    assert not data.mask(sample, np.full_like(depth, 0.5)).any()
    # another sequence without frames: a clear error when a method needs them
    other = next(s for s in data if s.sequence == "00340")
    with pytest.raises(InputError, match="--frames"):
        data.color(other)


def _dataset_with(tmp_path: Path, redwood75_dir: Path, edit) -> Path:
    data = json.loads((redwood75_dir / "annotations.json").read_text())
    edit(data)
    folder = tmp_path / "bad"
    folder.mkdir()
    (folder / "annotations.json").write_text(json.dumps(data))
    return folder


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["00015"]["pose_anns"][0].__setitem__("orientation", [0.0, 0.0, 0.0, 2.0]), "unit quaternion"),
        (lambda d: d["00015"]["pose_anns"][0].__setitem__("position", [0.0, float("nan"), 1.0]), "non-finite"),
        (lambda d: d["00015"]["pose_anns"][0].__setitem__("position", [0.0, 1.0]), "list of 3"),
        (lambda d: d["00015"].pop("scale"), "missing key 'scale'"),
        (lambda d: d["00015"].__setitem__("scale", [0.1, -0.1, 0.1]), "positive"),
        (lambda d: d.__setitem__("00015", [1, 2]), "expected a mapping"),
    ],
)
def test_bad_annotations(tmp_path, redwood75_dir, edit, message):
    folder = _dataset_with(tmp_path, redwood75_dir, edit)
    with pytest.raises(InputError, match=message) as info:
        open_dataset(folder)
    assert "annotations.json" in str(info.value) and "\n" not in str(info.value)


def test_bad_folders(tmp_path):
    with pytest.raises(InputError, match="not found"):
        open_dataset(tmp_path / "nowhere")
    with pytest.raises(InputError, match="not a dataset folder"):
        open_dataset(tmp_path)
    (tmp_path / "annotations.json").write_text("{not json")
    with pytest.raises(InputError, match="malformed JSON"):
        open_dataset(tmp_path)


def test_toolkit_output_without_meshes_folder(tmp_path, redwood75_dir):
    """reconstruct-sequence writes meshes next to annotations.json: found there too."""
    folder = _dataset_with(tmp_path, redwood75_dir, lambda d: None)
    shutil.copy(redwood75_dir / "meshes" / "00517.obj", folder / "00517.obj")
    data = open_dataset(folder)
    assert {s.sequence for s in data if s.mesh_path is not None} == {"00517"}


def test_masks_written_by_the_toolkit_are_used(tmp_path, redwood75_dir):
    folder = _dataset_with(tmp_path, redwood75_dir, lambda d: None)
    sample = Redwood75Dataset(folder).samples[0]
    mask = np.zeros((480, 640), np.uint8)
    mask[100:120, 200:260] = 255
    (folder / "masks" / sample.sequence).mkdir(parents=True)
    Image.fromarray(mask).save(folder / "masks" / sample.sequence / f"{sample.frame}.png")
    data = Redwood75Dataset(folder)
    assert data.samples[0].mask_path is not None and data.samples[1].mask_path is None
    np.testing.assert_array_equal(data.mask(data.samples[0]), mask > 0)
    assert data.mask(data.samples[1]).sum() > 1000  # no file: the box is ray-cast
