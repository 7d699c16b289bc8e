"""The model panel: accumulated object points against the true box, mesh preview and export through reconstruct."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import viser
from test_app_fixtures import TRUE_EXTENTS, make_sequence

from annotate.app import App
from annotate.app_model import accumulate_model, reconstruct_module
from sequences.annotation import Annotation, FramePose
from sequences.reader import open_sequence


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    root, poses = make_sequence(tmp_path_factory.mktemp("model") / "box_seq", frames=4)
    return root, poses


def truth_document(seq, poses, extents=TRUE_EXTENTS) -> Annotation:
    doc = Annotation(seq.name, "other", "none", np.asarray(extents, dtype=float))
    for frame_id, (p, q) in zip(seq.ids, poses):
        doc.frames[frame_id] = FramePose(np.asarray(p), np.asarray(q), "manual")
    return doc


def test_accumulated_points_of_true_poses_lie_on_the_true_box(truth):
    root, poses = truth
    seq = open_sequence(root)
    points, colors = accumulate_model(seq, truth_document(seq, poses), margin=0.005)
    assert len(points) > 1000 and colors.shape == points.shape and colors.dtype == np.uint8
    # object frame: every point within the box grown by the crop margin, most of them on its surface
    assert np.all(np.abs(points) <= TRUE_EXTENTS / 2 + 0.005 + 1e-9)
    distance_to_surface = np.min(TRUE_EXTENTS / 2 - np.abs(points), axis=1)
    assert np.median(np.abs(distance_to_surface)) < 0.0015  # depth quantised to 1 mm
    # a wrong pose spreads the points: shifted by 2 cm, far fewer of them are on the surface
    wrong = truth_document(seq, [(p + [0.02, 0, 0], q) for p, q in poses])
    moved, _ = accumulate_model(seq, wrong, margin=0.005)
    on_surface = lambda pts: np.mean(np.abs(np.min(TRUE_EXTENTS / 2 - np.abs(pts), axis=1)) < 0.002)  # noqa: E731
    assert on_surface(moved) < on_surface(points) - 0.2
    empty, _ = accumulate_model(seq, Annotation(seq.name))
    assert empty.shape == (0, 3)


@pytest.mark.skipif(reconstruct_module() is None, reason="reconstruct pipeline not installed")
def test_mesh_preview_and_export_from_the_page(truth, tmp_path):
    root = tmp_path / "box_seq"
    shutil.copytree(truth[0], root)
    seq = open_sequence(root)
    from sequences.annotation import save_annotation

    save_annotation(truth_document(seq, truth[1]), root / "annotation.yaml")
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = App(server, seq)
    try:
        assert app.model.start(app.model._preview, wait=True)
        assert app.scene.mesh is not None, app.model.info.content
        vertices = np.asarray(app.scene.mesh_vertices)
        assert "observed (grey)" in app.model.info.content  # the preview says what was seen
        # the carved mesh (object frame) is about the true box: within the crop margin and 2 voxels
        assert np.all(np.abs(vertices) <= TRUE_EXTENTS / 2 + 0.02)
        assert np.all(vertices.max(axis=0) - vertices.min(axis=0) >= TRUE_EXTENTS * 0.6)
        app.model.out_dir.value = str(tmp_path / "gt")
        assert app.model.start(app.model._export, wait=True)
        assert "Exported" in app.model.info.content, app.model.info.content
        exported = json.loads((tmp_path / "gt" / "annotations.json").read_text())
        assert seq.name in exported
    finally:
        app.close()
        server.stop()


def test_accumulated_points_are_shown_below_the_box(truth, tmp_path):
    root = tmp_path / "box_seq"
    shutil.copytree(truth[0], root)
    seq = open_sequence(root)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    app = App(server, seq)
    try:
        app.commit_box(*truth[1][0])
        app.model.show_model.value = True
        app.model.refresh_model(wait=True)
        shown = np.asarray(app.scene.model.points)
        expected, _ = accumulate_model(seq, app.state.annotation)
        np.testing.assert_allclose(shown, expected.astype(np.float32))
        assert app.scene.model.name.startswith("/box/")  # object frame: it moves with the box
        app.model.show_model.value = False
        assert app.scene.model is None
    finally:
        app.close()
        server.stop()
