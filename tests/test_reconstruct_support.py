"""The plane a static object stands on (reconstruct.support): found, cut away, and never found where there is none."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from reconstruct import support
from reconstruct.carving import make_grid
from reconstruct.pipeline import reconstruct_sequence
from sequences.annotation import load_annotation
from sequences.camera import Camera
from sequences.reader import open_sequence
from test_reconstruct_scenes import orbit_poses, render_depth, write_scene

BOX = (0.06, 0.08, 0.04)  # metres: the object, a box centred on its origin


def _table(top: float, side: float = 0.5) -> trimesh.Trimesh:
    """A slab ``side`` wide whose top face lies at y = ``top`` (object frame)."""
    slab = trimesh.creation.box((side, 0.02, side))
    slab.apply_translation([0.0, top - 0.01, 0.0])
    return slab


def _frames(meshes_in_object: list[trimesh.Trimesh], camera: Camera, n: int = 12, fixed_in_camera: list[trimesh.Trimesh] = ()):
    """(pose, depth) of ``n`` views from above of meshes fixed in the object frame, and of meshes fixed in the camera's."""
    out = []
    for T in orbit_poses(n, upper_only=True, seed=3):
        meshes = [m.copy().apply_transform(T) for m in meshes_in_object] + [m.copy() for m in fixed_in_camera]
        out.append((T, render_depth(meshes, camera)))
    return out


CAMERA = Camera(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)


def test_a_box_on_a_table_is_reconstructed_without_the_table(tmp_path):
    box = trimesh.creation.box(BOX)
    scene = write_scene(tmp_path / "box_on_table", box, n_frames=24, upper_only=True, extra=_table(-BOX[1] / 2))
    sequence = open_sequence(scene.root)
    annotation = load_annotation(scene.root / "annotation.yaml")
    rec = reconstruct_sequence(sequence, annotation)
    plane = rec.report["support_plane"]
    np.testing.assert_allclose(plane["normal"], [0, 1, 0], atol=0.01)
    assert plane["offset_mm"] == pytest.approx(BOX[1] / 2 * 1000, abs=1.0)  # the table's top, 40 mm below the centre
    np.testing.assert_allclose(rec.extents, BOX, atol=0.003)
    # no frame saw the underside, but the table bounds it: its extent is no guess, and no warning names it
    assert rec.surface.faces["-y (bottom)"] == "support"
    assert "-y (bottom)" not in [face for face, _ in rec.surface.unmeasured_faces()]
    assert all(state == "measured" for face, state in rec.surface.faces.items() if face != "-y (bottom)")
    # the same frames without the plane: the table's measurement band stays, a slab out to the grid's margin
    slab = reconstruct_sequence(sequence, annotation, support_plane=False)
    assert slab.extents[0] > BOX[0] + 0.01 and slab.extents[2] > BOX[2] + 0.01


def test_the_support_keeps_the_objects_footprint_and_removes_the_rest_of_the_band():
    grid = make_grid(BOX, 0.002)
    plane = support.SupportPlane(np.array([0.0, 1.0, 0.0]), BOX[1] / 2, 0.004, 1000, 1.0)
    centres = grid.centres(np.float64).reshape(grid.shape + (3,))
    inside = np.all(np.abs(centres) <= np.array(BOX) / 2, axis=-1)
    band = (centres[..., 1] >= -BOX[1] / 2) & (centres[..., 1] < -BOX[1] / 2 + 0.004)
    below = centres[..., 1] < -BOX[1] / 2
    occupied = inside | band | below  # the object, the table's band and what lies under the table
    cut = support.beyond_support(occupied, grid, plane)
    assert not (cut & inside & ~below).any()  # the object's foot stays
    assert np.array_equal(cut, occupied & (below | (band & ~inside)))


def test_no_support_where_the_table_moves_with_the_camera():
    # a hand-held object: the table stays in the camera's frame, so in the object's frame it is a different plane each frame
    box = trimesh.creation.box(BOX)
    table_in_camera = trimesh.creation.box((2.0, 0.02, 2.0))
    table_in_camera.apply_translation([0.0, 0.07, 0.6])  # its top 6 cm below the optical axis (camera y points down)
    frames = _frames([box], CAMERA, fixed_in_camera=[table_in_camera])
    grid = make_grid(BOX, 0.002)
    candidates = support._candidates(frames, CAMERA, grid, np.array(BOX))[0]
    assert len(candidates) > 2 * support.MIN_POINTS  # the table is measured beside the object: enough to fit a plane
    assert support.find_support(frames, CAMERA, grid, np.array(BOX)) is None
    # the same views with the table fixed under the object find it
    found = support.find_support(_frames([box, _table(-BOX[1] / 2)], CAMERA), CAMERA, grid, np.array(BOX))
    assert found is not None and found.normal[1] == pytest.approx(1.0, abs=0.01)


def test_a_plane_through_the_object_is_no_support(monkeypatch):
    # a shelf passing through the box's middle: the box's own measurements lie on both sides of it
    box = trimesh.creation.box(BOX)
    shelf = trimesh.creation.box((0.5, 0.004, 0.5))
    grid = make_grid(BOX, 0.002)
    frames = _frames([box, shelf], CAMERA)
    assert support.find_support(frames, CAMERA, grid, np.array(BOX)) is None
    # the shelf would pass every other test
    monkeypatch.setattr(support, "MAX_BENEATH", 1.0)
    shelf_plane = support.find_support(frames, CAMERA, grid, np.array(BOX))
    assert shelf_plane is not None and abs(shelf_plane.offset) < 0.003
