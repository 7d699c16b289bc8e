"""The annotation document: round trip, unknown keys kept, validation errors, atomic save with backup."""

from __future__ import annotations

import os

import numpy as np
import pytest
import yaml

from sequences import InputError, load_annotation, save_annotation
from sequences.annotation import Annotation, FramePose, annotation_path

DOC = """\
sequence: mug_0001
category: mug
symmetry: none
extents: [0.12, 0.10, 0.08]
reviewer: alice            # unknown top-level key: kept
frames:
  "0000001":
    position: [0.01, -0.02, 0.61]
    orientation: [0.0, 0.0, 0.0, 1.0]
    source: manual
    note: placed twice     # unknown frame key: kept
  "0000007":
    position: [0.02, -0.02, 0.63]
    orientation: [0.0, 0.7071067811865476, 0.0, 0.7071067811865476]
    source: tracked
    fitness: 0.93
"""


def test_round_trip_keeps_unknown_keys(tmp_path):
    path = tmp_path / "annotation.yaml"
    path.write_text(DOC)
    doc = load_annotation(path)
    assert doc.sequence == "mug_0001" and doc.category == "mug" and doc.symmetry == "none"
    assert np.allclose(doc.extents, [0.12, 0.10, 0.08])
    assert doc.frames["0000007"].source == "tracked"
    assert doc.extra == {"reviewer": "alice"}
    save_annotation(doc, path)
    again = yaml.safe_load(path.read_text())
    assert again["reviewer"] == "alice"
    assert again["frames"]["0000001"]["note"] == "placed twice"
    assert again["frames"]["0000007"]["fitness"] == 0.93
    assert load_annotation(path).to_dict() == doc.to_dict()


def test_pose_matrix_maps_object_to_camera(tmp_path):
    path = tmp_path / "annotation.yaml"
    path.write_text(DOC)
    pose = load_annotation(path).frames["0000007"]
    # 90 degrees about y: object +x goes to camera -z; p_cam = R p_obj + t
    p = pose.matrix @ np.array([0.1, 0, 0, 1.0])
    assert np.allclose(p[:3], [0.02, -0.02, 0.63 - 0.1])
    back = FramePose.from_matrix(pose.matrix)
    assert np.allclose(back.matrix, pose.matrix)


def test_an_anchor_posed_on_the_track_keeps_the_persons_box_through_a_round_trip(tmp_path):
    from scipy.spatial.transform import Rotation

    from annotate.engines import anchored_pose

    person = FramePose(np.array([0.01, -0.02, 0.61]), np.array([0.0, 0.0, 0.0, 1.0]), "refined", {"note": "mine"})
    estimate = np.eye(4)
    estimate[:3, :3] = Rotation.from_euler("x", 2.0, degrees=True).as_matrix()
    estimate[:3, 3] = [0.012, -0.02, 0.61]
    moved = anchored_pose(person, estimate, {"fitness": 0.9}, follows=True)
    assert moved.source == "refined" and np.allclose(moved.matrix, estimate) and np.allclose(moved.placed_matrix, person.matrix)
    # a second run moves it again from the person's box, never from the moved pose
    again = anchored_pose(moved, np.eye(4) @ estimate, {"fitness": 0.8}, follows=False)
    assert np.allclose(again.matrix, person.matrix) and "placed" not in again.extra
    path = tmp_path / "annotation.yaml"
    save_annotation(Annotation("s", "mug", "none", np.array([0.1, 0.1, 0.1]), {"0000001": moved}), path)
    loaded = load_annotation(path).frames["0000001"]
    assert np.allclose(loaded.matrix, estimate) and np.allclose(loaded.placed_matrix, person.matrix)
    assert FramePose(person.position, person.orientation).placed_matrix.tolist() == person.matrix.tolist()


def test_unquoted_frame_ids_keep_seven_digits(tmp_path):
    path = tmp_path / "annotation.yaml"
    path.write_text("category: can\nframes:\n  0000012:\n    position: [0, 0, 1]\n    orientation: [0, 0, 0, 1]\n")
    doc = load_annotation(path)
    assert list(doc.frames) == ["0000012"]
    assert doc.symmetry == "y"  # a can's default
    assert doc.sequence == tmp_path.name


@pytest.mark.parametrize("text, fragment", [
    ("category: cup\n", "category 'cup'"),
    ("symmetry: z\n", "symmetry 'z'"),
    ("extents: [0.1, 0.0, 0.1]\n", "empty box"),
    ("extents: [0.1, 0.1]\n", "extents must be a list of 3"),
    ("frames:\n  '1': {position: [0, .nan, 1], orientation: [0, 0, 0, 1]}\n", "NaN"),
    ("frames:\n  '1': {position: [0, 0, 1], orientation: [0, 0, 0, 2]}\n", "not a unit quaternion"),
    ("frames:\n  '1': {position: [0, 0, 1], orientation: [0, 0, 0, 1], source: guessed}\n", "source 'guessed'"),
    ("frames: [1, 2]\n", "frames must be a mapping"),
    ("frames:\n  '1': {position: [0, 0, 1], orientation: [0, 0, 0, 1], placed: [0, 0, 1]}\n", "placed must be a mapping"),
    ("frames:\n  '1': {position: [0, 0, 1], orientation: [0, 0, 0, 1], placed: {position: [0, 0, 1]}}\n", "placed orientation must be a list of 4"),
    ("frames:\n  '1': {position: [0, 0, 1], orientation: [0, 0, 0, 1], placed: {position: [0, 0, 1], orientation: [0, 0, 1, 1]}}\n", "placed orientation is not a unit"),
    ("- just\n- a list\n", "must be a mapping"),
    ("frames: {a: [1\n", "malformed YAML"),
])
def test_malformed_documents_are_one_line_errors(tmp_path, text, fragment):
    path = tmp_path / "annotation.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        load_annotation(path)
    message = str(info.value)
    assert message.startswith(str(path)) and fragment in message and "\n" not in message


def test_missing_document(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_annotation(tmp_path / "annotation.yaml")


def test_save_is_atomic_and_keeps_a_backup(tmp_path, monkeypatch):
    path = tmp_path / "annotation.yaml"
    doc = Annotation("s", "bowl", "y", np.array([0.15, 0.07, 0.15]))
    save_annotation(doc, path)
    first = path.read_text()
    doc.frames["0000001"] = FramePose(np.array([0, 0, 0.7]), np.array([0, 0, 0, 1.0]))
    save_annotation(doc, path)
    assert (tmp_path / "annotation.yaml.bak").read_text() == first
    second = path.read_text()

    # a crash during the write (before the rename) leaves the document as it was, and no temp file
    def crash(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", crash)
    doc.frames["0000002"] = FramePose(np.array([0, 0, 0.8]), np.array([0, 0, 0, 1.0]))
    with pytest.raises(OSError):
        save_annotation(doc, path)
    assert path.read_text() == second
    assert sorted(p.name for p in tmp_path.iterdir()) == ["annotation.yaml", "annotation.yaml.bak"]


def test_annotation_path(tmp_path):
    assert annotation_path(tmp_path) == tmp_path / "annotation.yaml"
    assert annotation_path(tmp_path, tmp_path / "other.yaml") == tmp_path / "other.yaml"
