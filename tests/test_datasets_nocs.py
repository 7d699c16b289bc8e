"""NOCS REAL275 reader: decomposition of sRT, posed meshes against the instance masks, bad input."""

from __future__ import annotations

import pickle
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluate.datasets import open_dataset
from evaluate.datasets.masks import render_depth
from evaluate.datasets.nocs import NOCS_CAMERA, SHAPENET_FROM_NOCS, decompose_scaled_rotation, load_gts
from evaluate.geometry import quat_to_matrix, transform
from sequences.errors import InputError


def test_samples(nocs_dir):
    data = open_dataset(nocs_dir)
    assert [s.category for s in data] == ["bowl", "can", "camera", "mug", "laptop"]
    assert data.frames_without_truth == ["real_train/scene_1/0000"]
    assert [s.symmetry for s in data] == ["y", "y", "none", "none", "none"]
    laptop = data.samples[4]
    assert laptop.mesh_path is None and data.mesh(laptop) is None  # its mesh is missing from the sample
    for sample in data:
        R = quat_to_matrix(sample.orientation)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert sample.camera == NOCS_CAMERA


def test_scale_is_the_box_diagonal(nocs_dir):
    """NOCS folds the box diagonal into the rotation: the decomposed scale equals |extents|."""
    data = open_dataset(nocs_dir)
    gts = load_gts(nocs_dir / "gts" / "real_test" / "results_real_test_scene_1_0000.pkl")
    for i, sample in enumerate(data):
        R, scale, t = decompose_scaled_rotation(nocs_dir, gts["gt_RTs"][i])
        assert scale == pytest.approx(np.linalg.norm(sample.extents), rel=2e-3)
        np.testing.assert_allclose(gts["gt_RTs"][i][:3, :3], scale * R, atol=1e-4 * scale)
        # the sample's rotation is NOCS's composed with the ShapeNet remapping
        np.testing.assert_allclose(quat_to_matrix(sample.orientation), R @ SHAPENET_FROM_NOCS.T, atol=1e-9)
        np.testing.assert_allclose(sample.position, t)


def test_posed_meshes_match_instance_masks(nocs_dir):
    data = open_dataset(nocs_dir)
    for sample in data:
        mesh = data.mesh(sample)
        if mesh is None:
            continue
        np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), sample.extents, rtol=1e-3)
        silhouette = render_depth(transform(sample.pose, mesh.vertices), mesh.faces, sample.camera) > 0
        mask = data.mask(sample)
        iou = (silhouette & mask).sum() / (silhouette | mask).sum()
        assert iou > 0.9, (sample.label, iou)
        # a wrong pose (rotated 90 degrees about the camera's optical axis) misses clearly
        wrong = sample.pose.copy()
        wrong[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix() @ wrong[:3, :3]
        moved = render_depth(transform(wrong, mesh.vertices), mesh.faces, sample.camera) > 0
        assert (moved & mask).sum() / (moved | mask).sum() < iou - 0.1


def test_decompose_rejects_non_similarity(tmp_path):
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    sRT = np.eye(4)
    sRT[:3, :3] = 0.2 * R
    R2, s, _ = decompose_scaled_rotation(tmp_path, sRT)
    assert s == pytest.approx(0.2)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    sRT[:3, :3] = np.diag([0.1, 0.2, 0.2])
    with pytest.raises(InputError, match="uniformly scaled"):
        decompose_scaled_rotation(tmp_path, sRT)
    sRT[:3, :3] = np.diag([0.2, 0.2, -0.2])
    with pytest.raises(InputError, match="reflection"):
        decompose_scaled_rotation(tmp_path, sRT)


def test_refuses_code_in_pickle(tmp_path, nocs_dir):
    root = tmp_path / "nocs"
    shutil.copytree(nocs_dir, root)
    gts = root / "gts" / "real_test" / "results_real_test_scene_1_0000.pkl"
    gts.chmod(0o644)
    gts.write_bytes(pickle.dumps({"gt_RTs": np.zeros((5, 4, 4)), "hook": shutil.rmtree}))
    with pytest.raises(InputError, match="refusing"):
        open_dataset(root)
