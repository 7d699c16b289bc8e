"""The plane a static object stands on (reconstruct.support): found, cut away, and never found where there is none."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from reconstruct import support
from reconstruct.carving import make_grid
from reconstruct.pipeline import BOX_BOUND_SLACK, reconstruct_sequence
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
    # the same frames without the plane: the table's measurement band stays, a slab out to the box's bound
    slab = reconstruct_sequence(sequence, annotation, support_plane=False)
    np.testing.assert_allclose(slab.extents[[0, 2]], np.array(BOX)[[0, 2]] * (1 + BOX_BOUND_SLACK), atol=0.002)


def _on_a_table(radius_at, band: float = 0.004, voxel: float = 0.002):
    """A grid, the plane y = -0.04 (normal +y, band ``band``), and an occupancy: a solid of revolution about y standing
    on the plane (radius ``radius_at(height above the plane)``, 60 mm tall), the table's band everywhere and the space
    under the table."""
    grid = make_grid(np.array([0.1, 0.08, 0.1]), voxel)
    plane = support.SupportPlane(np.array([0.0, 1.0, 0.0]), 0.04, band, 1000, 1.0)
    c = grid.centres(np.float64).reshape(grid.shape + (3,))
    height = c[..., 1] + 0.04
    solid = (height >= 0) & (height <= 0.06) & (np.hypot(c[..., 0], c[..., 2]) <= radius_at(height))
    table = height < band
    return grid, plane, solid, solid | table, height


def test_the_support_keeps_the_objects_footprint_and_removes_the_rest_of_the_band():
    # a cylinder: everything of it stays; the band beyond its foot and the space beneath the table go
    grid, plane, solid, occupied, height = _on_a_table(lambda h: 0.03)
    cut = support.beyond_support(occupied, grid, plane)
    assert not (cut & solid & (height >= 0)).any()
    c = grid.centres(np.float64).reshape(grid.shape + (3,))
    radius = np.hypot(c[..., 0], c[..., 2])
    assert np.array_equal(cut, occupied & ((height < 0) | ~solid))
    assert not (cut & (height >= plane.band)).any()
    # a foot that flares out below the band (its radius shrinks 0.5 mm per mm of height) loses only the rim that
    # reaches out beyond the foot straight above the band
    grid, plane, solid, occupied, height = _on_a_table(lambda h: 0.035 - 0.5 * h)
    cut = support.beyond_support(occupied, grid, plane)
    lost = cut & solid & (height >= 0)
    assert lost.sum() < 0.05 * solid.sum()
    assert (radius[lost] > 0.035 - 0.5 * (plane.band + grid.voxel_size) - grid.voxel_size).all()


def test_an_object_thinner_than_the_tables_noise_keeps_the_band():
    # a 3 mm plate lying on the table: nothing of it stands above the band, so the band stays (only beneath is cut)
    grid, plane, solid, occupied, height = _on_a_table(lambda h: np.where(h < 0.003, 0.03, -1.0))
    cut = support.beyond_support(occupied, grid, plane)
    assert np.array_equal(cut, occupied & (height < 0))


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


def test_a_plane_through_the_object_is_no_support():
    # a shelf passing through the box's middle: the box's centre is not above it
    box = trimesh.creation.box(BOX)
    shelf = trimesh.creation.box((0.5, 0.004, 0.5))
    grid = make_grid(BOX, 0.002)
    assert support.find_support(_frames([box, shelf], CAMERA), CAMERA, grid, np.array(BOX)) is None


def _points(monkeypatch, table: np.ndarray, within: np.ndarray, cameras: np.ndarray) -> None:
    """find_support's candidates made by hand: ``table`` points outside the grid (3 frames), ``within`` inside it."""
    which = np.arange(len(table)) % len(cameras)
    monkeypatch.setattr(support, "_candidates", lambda *args: (table, np.full(len(table), 0.7), which, within,
                                                                 np.full(len(within), 0.7), cameras))


def test_what_makes_a_plane_the_support(monkeypatch):
    rng = np.random.default_rng(0)
    grid, extents = make_grid(BOX, 0.002), np.array(BOX)
    flat = np.column_stack([rng.uniform(-0.15, 0.15, 3000), np.full(3000, -0.04), rng.uniform(-0.15, 0.15, 3000)])
    flat[:, 1] += rng.normal(0, 0.001, 3000)
    box_points = rng.uniform(-0.5, 0.5, (2000, 3)) * np.array(BOX)  # measured inside the grid, all above the table
    above = np.array([[0.3, 0.5, 0.2], [-0.3, 0.4, 0.1], [0.0, 0.6, -0.4]])
    _points(monkeypatch, flat, box_points, above)
    found = support.find_support([], CAMERA, grid, extents)
    assert found is not None and found.normal[1] == pytest.approx(1.0, abs=0.01) and found.offset == pytest.approx(0.04, abs=0.001)
    # the object measured on both sides of it: another object's face passing through this one
    _points(monkeypatch, flat, box_points - [0.0, 0.05, 0.0], above)
    assert support.find_support([], CAMERA, grid, extents) is None
    # nothing measured of the object to test it by
    _points(monkeypatch, flat, box_points[:10], above)
    assert support.find_support([], CAMERA, grid, extents) is None
    # seen from below: the object's centre is not above the plane the cameras look at
    _points(monkeypatch, flat, box_points, above * [1, -1, 1])
    assert support.find_support([], CAMERA, grid, extents) is None
    # a 3 mm strip, not a plane: which way it tilts is noise
    strip = flat.copy()
    strip[:, 2] = rng.uniform(-0.0015, 0.0015, 3000) + 0.1
    _points(monkeypatch, strip, box_points, above)
    assert support.find_support([], CAMERA, grid, extents) is None
