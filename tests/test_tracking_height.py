"""A hinged object's centre along its base's normal from the faces its frames see (annotate/tracking/height.py)."""

from __future__ import annotations

import numpy as np
import pytest
from test_tracking_render import object_offset, posed_off

from annotate.tracking.height import Levels, frame_levels, height_offsets, measure_levels

#: a laptop of 0.30 x 0.24 x 0.25 m about its box centre: the underside at y = -0.120, the base 16 mm thick (its top
#: face, the keyboard, at -0.104), the lid rising at -z to its top edge at +0.120
BOTTOM, THICKNESS, TOP = -0.120, 0.016, 0.120


def _grid(xs, ys, zs, normal) -> tuple[np.ndarray, np.ndarray]:
    """Points on the grid of ``xs`` x ``ys`` x ``zs`` (m) and their normal (repeated)."""
    points = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
    normal = np.asarray(normal, dtype=np.float64)
    return points, np.tile(normal / np.linalg.norm(normal), (len(points), 1))


def _frame(*parts) -> tuple[np.ndarray, np.ndarray]:
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


XS, ZS = np.linspace(-0.15, 0.15, 61), np.linspace(-0.10, 0.12, 45)
UNDERSIDE = _grid(XS, [BOTTOM], ZS, (0, -1, 0))
KEYBOARD = _grid(XS, [BOTTOM + THICKNESS], ZS, (0, 1, 0))
# the lid's top edge: a strip tilted back with the lid (its normal 17 deg off +y), its median 1 mm below the top
LID_EDGE = _grid(XS, np.linspace(TOP - 0.002, TOP, 5), [-0.125], (0, 0.95, -0.3))
LID_INNER = _grid(XS, np.linspace(-0.09, 0.10, 39), [-0.11], (0, 0.3, 0.95))
# the +x side: the base's (the whole depth) and the lid's (behind the hinge, at -z)
BASE_SIDE = _grid([0.15], np.linspace(BOTTOM, BOTTOM + THICKNESS, 17), ZS, (1, 0, 0))
# (from the hinge, 20 mm inside the base's back edge, to the lid's back)
LID_SIDE = _grid([0.15], np.linspace(BOTTOM + THICKNESS, TOP, 60), np.linspace(-0.125, -0.08, 10), (1, 0, 0))


def test_a_frame_measures_each_face_it_sees_on_the_faces_own_points():
    # seen from below and from the +x side: the underside and the end face
    below = frame_levels(*_frame(UNDERSIDE, BASE_SIDE, LID_SIDE, LID_INNER), lid_side=-1.0)
    assert below.bottom == pytest.approx(BOTTOM, abs=1e-12)
    assert np.isnan(below.keyboard) and np.isnan(below.top)
    # the base's side, on the half away from the lid (the lid's side, behind the hinge, is 240 mm tall): its height
    # between the 1st and 99th percentiles, which fall on its first and last rows (each holds 1/17 of its points)
    assert below.thickness == pytest.approx(THICKNESS, abs=1e-12)
    # seen from above: the keyboard and the lid's top edge (the strip's median)
    above = frame_levels(*_frame(KEYBOARD, LID_EDGE, LID_INNER), lid_side=-1.0)
    assert above.keyboard == pytest.approx(BOTTOM + THICKNESS, abs=1e-12)
    assert above.top == pytest.approx(TOP - 0.001, abs=1e-12)
    assert np.isnan(above.bottom) and np.isnan(above.thickness)
    # the lid taken to rise at +z: the half "away" from it is the lid's, whose side (up to the box centre) is taken
    # for the base's: 120 mm, no thickness of a base (height_offsets refuses it)
    wrong = frame_levels(*_frame(UNDERSIDE, BASE_SIDE, LID_SIDE), lid_side=1.0)
    assert wrong.thickness == pytest.approx(0.120, abs=0.005)
    # too few points: nothing measured
    assert all(np.isnan(v) for v in frame_levels(np.zeros((5, 3)), np.zeros((5, 3)), -1.0))


def test_a_hands_fingers_on_the_end_do_not_set_the_thickness():
    # fingers on the +x end, 12 mm outside the side's plane and reaching 50 mm above the base: off the side's plane
    fingers = _grid([0.162], np.linspace(-0.125, -0.07, 30), np.linspace(0.02, 0.05, 8), (1, 0, 0))
    with_fingers = frame_levels(*_frame(UNDERSIDE, BASE_SIDE, fingers), lid_side=-1.0)
    assert with_fingers.thickness == pytest.approx(THICKNESS, abs=1e-12)
    # a hand alone at an end (no side of the base seen): its surfaces facing along x start above the underside
    hand = _grid([0.162], np.linspace(-0.10, -0.05, 30), np.linspace(0.02, 0.10, 20), (1, 0, 0))
    assert np.isnan(frame_levels(*_frame(UNDERSIDE, hand), lid_side=-1.0).thickness)


def test_offsets_put_every_frame_halfway_between_the_underside_and_the_lids_top():
    nan = float("nan")
    height = (TOP - 0.001) - BOTTOM  # the lid's edge median over the keyboard, plus the thickness
    # frames 0-2 seen from below, their boxes right; frames 5-7 from above, their boxes 4 mm low (the object lies
    # 4 mm higher in them); frames 3-4 see no face along y
    below = Levels(BOTTOM, nan, nan, THICKNESS)
    above = Levels(nan, BOTTOM + THICKNESS + 0.004, TOP - 0.001 + 0.004, nan)
    offsets = height_offsets([below, below, below, None, Levels(nan, nan, nan, nan), above, above, above])
    # the centre halfway up the measured height: the frames below at its half (0.5 mm low, half the lid edge's 1 mm
    # shortfall), the frames above 4 mm higher; frames 3-4 interpolated between
    expected = np.array([0, 0, 0, 0.004 / 3, 0.008 / 3, 0.004, 0.004, 0.004]) + BOTTOM + height / 2
    assert np.allclose(offsets, expected, atol=1e-12)
    # the keyboard alone gives the same centre as the lid's top (the thickness below it)
    keyboard_only = Levels(nan, BOTTOM + THICKNESS + 0.004, nan, nan)
    assert np.allclose(height_offsets([below, above, keyboard_only]), [expected[0], expected[-1], expected[-1]], atol=1e-12)
    # a palm under the base, 20 mm below its underside: that frame's measure left out, its offset interpolated
    palm = Levels(BOTTOM - 0.020, nan, nan, nan)
    offsets = height_offsets([below, below, palm, below, above, above])
    assert np.allclose(offsets, np.array([0, 0, 0, 0, 0.004, 0.004]) + BOTTOM + height / 2, atol=1e-12)
    # a thickness of a quarter of the height or more (the lid's side taken for the base's), or a height far from the placed
    # box's (15 % at most): no laptop measured, nothing moved
    lid_taken = Levels(BOTTOM, nan, nan, 0.120)
    assert np.array_equal(height_offsets([lid_taken, above]), [0.0, 0.0])
    assert np.allclose(height_offsets([below, above], box_height=0.25), [expected[0], expected[-1]], atol=1e-12)
    assert np.array_equal(height_offsets([below, above], box_height=0.20), [0.0, 0.0])
    # no thickness, or no frame seeing both the keyboard and the lid's top: no height, nothing moved
    assert np.array_equal(height_offsets([Levels(BOTTOM, nan, nan, nan), above]), [0.0, 0.0])
    assert np.array_equal(height_offsets([below, Levels(nan, nan, TOP, nan)]), [0.0, 0.0])
    assert np.array_equal(height_offsets([None, None]), [0.0, 0.0])


@pytest.mark.slow
def test_a_rendered_laptops_keyboard_and_lid_edge_lie_where_they_are(rendered_laptop):
    _, mesh, truth = rendered_laptop
    # every box 4 mm up along y: the laptop lies 4 mm lower in them
    tracker, ids, poses = posed_off(rendered_laptop, object_offset(translation_m=(0.0, 0.004, 0.0)))
    vertices = mesh.vertices
    lid = -np.sign(np.median(vertices[vertices[:, 1] > 0, 2]))
    front = vertices[:, 2] * lid > 0  # the base alone
    keyboard, top = vertices[front, 1].max() - 0.004, vertices[:, 1].max() - 0.004
    levels = [measure_levels(tracker, f, poses[f], -lid) for f in ids]
    # the rendered frames see the laptop from above: the keyboard and the lid's top edge, not the underside
    assert all(np.isnan(lv.bottom) for lv in levels)
    # measured: the keyboard within 0.03 mm; the lid edge's median 0.5-0.6 mm below the top (the strip tilted back)
    assert max(abs(lv.keyboard - keyboard) for lv in levels) < 1e-4, [lv.keyboard - keyboard for lv in levels]
    assert all(-0.001 < lv.top - top < 0 for lv in levels), [lv.top - top for lv in levels]


@pytest.mark.slow
def test_without_a_thickness_measured_no_frame_is_moved(rendered_laptop):
    from annotate.tracking.engine import _lid_side
    from annotate.tracking.height import centred_heights
    from annotate.tracking.refine import build_model

    _, mesh, _ = rendered_laptop
    tracker, ids, poses = posed_off(rendered_laptop, object_offset(translation_m=(0.0, 0.004, 0.0)))
    # the lid's side, from the model of all frames (its points above the box centre)
    vertices = mesh.vertices
    lid = np.sign(np.median(vertices[vertices[:, 1] > 0, 2]))
    assert _lid_side(tracker, build_model(tracker, poses, len(ids), [ids[0]]), np.eye(4)) == lid
    # the rendered frames see the laptop from above only: no end face of the base (its thickness) and no underside,
    # so the frames above cannot be tied to any height: all left where they are
    out = centred_heights(tracker, ids, poses, lid, every=2)
    assert all(np.array_equal(out[f], poses[f]) for f in ids)


def test_each_frame_is_moved_along_its_own_y_by_its_offset(monkeypatch):
    from types import SimpleNamespace

    import annotate.tracking.height as height

    nan = float("nan")
    ids = [f"{k:03d}" for k in range(6)]
    rotation = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    poses = {f: np.eye(4) for f in ids}
    for k, f in enumerate(ids):
        poses[f][:3, :3] = rotation
        poses[f][:3, 3] = [0.01 * k, -0.02, 0.6]
    # frames 0-2 seen from below, centred; frames 3-5 from above, the object 4 mm higher in their boxes
    below = Levels(BOTTOM, nan, nan, THICKNESS)
    above = Levels(nan, BOTTOM + THICKNESS + 0.004, TOP - 0.001 + 0.004, nan)
    seen = {f: below if k < 3 else above for k, f in enumerate(ids)}
    monkeypatch.setattr(height, "measure_levels", lambda tracker, f, pose, side: seen[f])
    tracker = SimpleNamespace(store=SimpleNamespace(errors={}), config=SimpleNamespace(worker_count=lambda: 1), box=np.array([0.30, 0.24, 0.25]))
    out = height.centred_heights(tracker, ids, poses, -1.0, every=1)
    middle = BOTTOM + ((TOP - 0.001) - BOTTOM) / 2  # the centre the faces give in a centred box: 0.5 mm low
    for k, f in enumerate(ids):
        moved = np.linalg.inv(poses[f]) @ out[f]  # the move in the box's own frame: along its y alone
        assert np.allclose(moved[:3, :3], np.eye(3), atol=1e-12)
        assert np.allclose(moved[:3, 3], [0.0, middle + (0.004 if k >= 3 else 0.0), 0.0], atol=1e-12)
