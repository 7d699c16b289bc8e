"""Metric module against independent truth: analytic volumes, known angles, hand-made point sets."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from evaluate.metrics import (
    FScore,
    ShapeIndex,
    axis_aligned_iou,
    box_iou,
    box_iou_batch,
    chamfer_distance,
    fscore,
    rotation_error,
    sample_surface,
    squared_chamfer_distance,
    symmetric_box_iou,
    symmetric_box_iou_batch,
    translation_error,
)
from evaluate.metrics import hit_grid, sampling
from evaluate.metrics.box_iou import _rotated_about_y


def pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rot(axis: str, degrees: float) -> np.ndarray:
    return Rotation.from_euler(axis, degrees, degrees=True).as_matrix()


def iou_of_volumes(inter, va, vb):
    return inter / (va + vb - inter)


# --- box IoU: analytic cases ----------------------------------------------------------------------

def test_identical_boxes_have_iou_one_in_any_pose():
    for seed in range(5):
        R = Rotation.random(random_state=seed).as_matrix()
        T = pose(R, np.random.default_rng(seed).normal(size=3))
        assert box_iou([0.1, 0.2, 0.3], T, [0.1, 0.2, 0.3], T) == 1.0  # exactly: a perfect prediction scores 1
        assert box_iou_batch(np.full((3, 3), 0.1), np.stack([T] * 3), np.full((3, 3), 0.1), np.stack([T] * 3)).tolist() == [1.0] * 3
        assert symmetric_box_iou([0.1, 0.2, 0.3], T, [0.1, 0.2, 0.3], T) == 1.0


def test_axis_aligned_overlap_matches_product_of_interval_overlaps():
    # A = [-1,1]x[-0.5,0.5]x[-1.5,1.5]; B shifted by (0.5, 0.2, -1): overlap 1.5 * 0.8 * 2.0.
    ea, eb = np.array([2.0, 1.0, 3.0]), np.array([2.0, 1.0, 3.0])
    inter = 1.5 * 0.8 * 2.0
    expected = iou_of_volumes(inter, 6.0, 6.0)
    assert box_iou(ea, pose(), eb, pose(t=(0.5, 0.2, -1.0))) == pytest.approx(expected, abs=1e-12)
    # the same in an arbitrary common frame
    G = pose(Rotation.random(random_state=7).as_matrix(), (0.3, -0.2, 1.5))
    assert box_iou(ea, G, eb, G @ pose(t=(0.5, 0.2, -1.0))) == pytest.approx(expected, abs=1e-12)


def test_box_rotated_45_degrees_inside_bigger_box():
    # a unit cube rotated 45° about z fits inside a 4-cube: IoU = 1 / 64
    assert box_iou([4, 4, 4], pose(), [1, 1, 1], pose(rot("z", 45))) == pytest.approx(1 / 64, abs=1e-14)


def test_two_squares_rotated_45_degrees_about_common_axis():
    # unit cubes sharing centre, one rotated 45° about z: the xy cross-section is a regular octagon
    # of area 2 (sqrt(2) - 1) (inscribed in the unit square), height 1.
    inter = 2 * (np.sqrt(2) - 1)
    assert box_iou([1, 1, 1], pose(), [1, 1, 1], pose(rot("z", 45))) == pytest.approx(iou_of_volumes(inter, 1, 1), abs=1e-14)


def test_disjoint_and_touching_boxes_have_iou_zero():
    assert box_iou([1, 1, 1], pose(), [1, 1, 1], pose(t=(3, 0, 0))) == 0.0
    assert box_iou([1, 1, 1], pose(), [1, 1, 1], pose(t=(1.0, 0, 0))) == pytest.approx(0.0, abs=1e-12)  # face contact
    assert box_iou([1, 1, 1], pose(), [1, 1, 1], pose(t=(1.0, 1.0, 0))) == pytest.approx(0.0, abs=1e-12)  # edge contact
    assert box_iou([1, 1, 1], pose(), [1, 1, 1], pose(t=(1.0, 1.0, 1.0))) == pytest.approx(0.0, abs=1e-12)  # corner
    # touching rotated boxes: a cube resting on another's face, rotated about the contact normal
    assert box_iou([1, 1, 1], pose(), [1, 1, 1], pose(rot("z", 30), (0, 0, 1.0))) == pytest.approx(0.0, abs=1e-12)


def test_contained_box_gives_volume_ratio():
    R = Rotation.random(random_state=3).as_matrix()
    small = pose(R @ rot("y", 20), (0.01, 0.0, 0.02))
    assert box_iou([1, 1, 1], pose(R), [0.2, 0.3, 0.4], small) == pytest.approx(0.024, abs=1e-13)
    assert box_iou([0.2, 0.3, 0.4], small, [1, 1, 1], pose(R)) == pytest.approx(0.024, abs=1e-13)
    # containment makes the union the bigger box: the IoU is the volume ratio to the last bit
    assert box_iou([1, 1, 1], pose(R), [0.2, 0.3, 0.4], small) == (0.2 * 0.3 * 0.4) / 1.0


def test_coplanar_faces_are_counted_once():
    # same top face plane (y = 0.5), B half as wide, shifted in x: inter = 0.5 * 1 * 1
    assert box_iou([1, 1, 1], pose(), [1, 1, 1], pose(t=(0.5, 0, 0))) == pytest.approx(1 / 3, abs=1e-12)
    # B flush with A's top and side faces, smaller: contained, shares 2 faces
    assert box_iou([1, 1, 1], pose(), [0.5, 0.5, 1], pose(t=(0.25, 0.25, 0))) == pytest.approx(0.25, abs=1e-12)
    # with a common arbitrary rotation (faces coplanar only up to rounding)
    G = pose(Rotation.random(random_state=11).as_matrix(), (0.1, 0.2, 0.7))
    assert box_iou([1, 1, 1], G, [0.5, 0.5, 1], G @ pose(t=(0.25, 0.25, 0))) == pytest.approx(0.25, abs=1e-12)


def test_nearly_coplanar_faces_stay_exact():
    # identical boxes, one rotated about y by tiny angles: IoU from the exact 2D octagon area
    e = np.array([0.1, 0.2, 0.15])
    G = Rotation.random(random_state=3).as_matrix()
    for phi in [1e-13, 1e-11, 1e-9, 1e-7, 1e-4]:
        c, s = np.cos(phi), np.sin(phi)
        hx, hz = e[0] / 2, e[2] / 2
        # area of the square [-hx,hx]x[-hz,hz] minus 4 corner triangles cut by the rotated rectangle
        # (small angle: each cut is a right triangle); computed with a 2D clip below instead of a formula
        poly = [(hx, hz), (-hx, hz), (-hx, -hz), (hx, -hz)]
        for nx, nz, h in [(c, -s, hx), (-c, s, hx), (s, c, hz), (-s, -c, hz)]:
            out = []
            for i in range(len(poly)):
                P, Q = poly[i], poly[(i + 1) % len(poly)]
                dp, dq = nx * P[0] + nz * P[1] - h, nx * Q[0] + nz * Q[1] - h
                if dp <= 0:
                    out.append(P)
                if dp * dq < 0:
                    w = dp / (dp - dq)
                    out.append((P[0] + w * (Q[0] - P[0]), P[1] + w * (Q[1] - P[1])))
            poly = out
        area = 0.5 * abs(sum(poly[i][0] * poly[i - 1][1] - poly[i - 1][0] * poly[i][1] for i in range(len(poly))))
        v = np.prod(e)
        expected = iou_of_volumes(area * e[1], v, v)
        got = box_iou(e, pose(G, (0.3, 0.1, 0.5)), e, pose(G @ rot("y", np.degrees(phi)), (0.3, 0.1, 0.5)))
        assert got == pytest.approx(expected, abs=1e-11)


def test_zero_volume_boxes_have_iou_zero():
    assert box_iou([0, 1, 1], pose(), [0, 1, 1], pose()) == 0.0  # defined: 0/0 -> 0
    assert box_iou([0, 1, 1], pose(), [1, 1, 1], pose()) == 0.0
    assert box_iou([1, 1, 1], pose(), [0, 0, 0], pose()) == 0.0


def test_box_iou_is_symmetric_and_batch_matches_single():
    rng = np.random.default_rng(5)
    n = 50
    ea, eb = rng.uniform(0.05, 0.2, (n, 3)), rng.uniform(0.05, 0.2, (n, 3))
    Ta = np.stack([pose(Rotation.random(random_state=i).as_matrix(), rng.normal(size=3) * 0.03) for i in range(n)])
    Tb = np.stack([pose(Rotation.random(random_state=100 + i).as_matrix(), rng.normal(size=3) * 0.03) for i in range(n)])
    batch = box_iou_batch(ea, Ta, eb, Tb)
    assert batch.shape == (n,)
    np.testing.assert_allclose(batch, box_iou_batch(eb, Tb, ea, Ta), atol=1e-12)
    np.testing.assert_allclose(batch[:5], [box_iou(ea[i], Ta[i], eb[i], Tb[i]) for i in range(5)], atol=0)
    assert np.all((batch >= 0) & (batch <= 1))


def test_box_iou_scratch_buffers_do_not_leak_between_calls_chunks_or_threads():
    """The polygon work reuses per-thread scratch arrays (box_iou._Workspace): a batch spanning several
    chunks, a later call and concurrent threads must all give each pair's own one-pair value."""
    import threading

    from evaluate.metrics.box_iou import _CHUNK

    rng = np.random.default_rng(11)
    n = _CHUNK // 3  # 8 faces per pair: about 2.7 chunks of polygon rows
    ea, eb = rng.uniform(0.02, 0.2, (n, 3)), rng.uniform(0.02, 0.2, (n, 3))
    Ta = np.stack([pose(Rotation.random(random_state=i).as_matrix(), rng.normal(size=3) * 0.02) for i in range(n)])
    Tb = np.stack([pose(Rotation.random(random_state=500 + i).as_matrix(), rng.normal(size=3) * 0.02) for i in range(n)])
    single = np.array([box_iou(ea[i], Ta[i], eb[i], Tb[i]) for i in range(n)])
    first = box_iou_batch(ea, Ta, eb, Tb)
    np.testing.assert_array_equal(first, single)
    box_iou_batch(eb[::-1], Tb[::-1], ea[::-1], Ta[::-1])  # overwrites the scratch arrays
    np.testing.assert_array_equal(first, single)  # the returned array is the caller's own
    results = {}

    def run(k: int) -> None:
        order = np.random.default_rng(k).permutation(n)
        results[k] = (order, [box_iou_batch(ea[order], Ta[order], eb[order], Tb[order]) for _ in range(5)])

    threads = [threading.Thread(target=run, args=(k,)) for k in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for order, values in results.values():
        for value in values:
            np.testing.assert_array_equal(value, single[order])


def test_box_iou_monte_carlo_cross_check():
    # loose, independent check: fraction of seeded uniform points of A that fall inside B
    rng = np.random.default_rng(0)
    for i in range(3):
        ea, eb = rng.uniform(0.5, 1.5, 3), rng.uniform(0.5, 1.5, 3)
        Ta = pose(Rotation.random(random_state=i).as_matrix(), rng.normal(size=3) * 0.2)
        Tb = pose(Rotation.random(random_state=50 + i).as_matrix(), rng.normal(size=3) * 0.2)
        pts = (rng.random((400_000, 3)) - 0.5) * ea
        cam = pts @ Ta[:3, :3].T + Ta[:3, 3]
        in_b = np.all(np.abs((cam - Tb[:3, 3]) @ Tb[:3, :3]) <= eb / 2, axis=1)
        inter = in_b.mean() * np.prod(ea)
        mc = iou_of_volumes(inter, np.prod(ea), np.prod(eb))
        assert box_iou(ea, Ta, eb, Tb) == pytest.approx(mc, abs=5e-3)


@pytest.mark.parametrize("bad", [
    dict(extents_a=[np.nan, 1, 1]),
    dict(extents_a=[-1, 1, 1]),
    dict(extents_a=[1, 1]),
    dict(T_a=np.full((4, 4), np.nan)),
    dict(T_a=np.diag([2.0, 1, 1, 1])),  # not a rotation
])
def test_box_iou_rejects_bad_input(bad):
    args = dict(extents_a=[1, 1, 1], T_a=pose(), extents_b=[1, 1, 1], T_b=pose())
    args.update(bad)
    with pytest.raises(ValueError):
        box_iou(**args)


# --- symmetric IoU --------------------------------------------------------------------------------

def _fine_grid_max(e_gt, T_gt, e_pred, T_pred, n=20000):
    angles = np.arange(n) * np.pi / n
    Tp = _rotated_about_y(np.broadcast_to(T_pred, (n, 4, 4)), angles)
    return box_iou_batch(np.broadcast_to(e_gt, (n, 3)), np.broadcast_to(T_gt, (n, 4, 4)), np.broadcast_to(e_pred, (n, 3)), Tp).max()


@pytest.mark.slow
def test_symmetric_iou_is_at_least_the_fine_grid_maximum():
    rng = np.random.default_rng(1)
    for k in range(2):
        e_gt = rng.uniform(0.05, 0.2, 3)
        e_pred = e_gt * rng.uniform(0.8, 1.2, 3)
        Rg = Rotation.random(random_state=k).as_matrix()
        T_gt = pose(Rg, (0, 0, 0.6))
        T_pred = pose(Rg @ Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix(), rng.normal(size=3) * 0.01 + (0, 0, 0.6))
        ours = symmetric_box_iou(e_gt, T_gt, e_pred, T_pred)
        assert ours >= _fine_grid_max(e_gt, T_gt, e_pred, T_pred) - 1e-9
        assert ours <= 1.0


def test_symmetric_iou_fine_grid_for_unrelated_and_flat_boxes():
    # independent random orientations (many local maxima) and a flat box (kinks where faces align)
    rng = np.random.default_rng(2)
    cases = [
        (rng.uniform(0.05, 0.2, 3), pose(Rotation.random(random_state=21).as_matrix(), (0, 0, 0.5)),
         rng.uniform(0.05, 0.2, 3), pose(Rotation.random(random_state=22).as_matrix(), (0.01, 0.0, 0.5))),
        (np.array([0.2, 0.02, 0.1]), pose(rot("x", 3), (0, 0, 0.5)), np.array([0.18, 0.02, 0.12]), pose(rot("y", 50), (0.002, 0, 0.5))),
    ]
    for e_gt, T_gt, e_pred, T_pred in cases:
        ours = symmetric_box_iou(e_gt, T_gt, e_pred, T_pred)
        assert ours >= _fine_grid_max(e_gt, T_gt, e_pred, T_pred, n=6000) - 1e-9


def test_symmetric_iou_recovers_a_box_turned_about_its_axis():
    # the prediction is the truth turned by 37° about the symmetry axis: symmetric IoU is 1
    R = Rotation.random(random_state=4).as_matrix()
    e = np.array([0.08, 0.2, 0.05])
    iou, angle = symmetric_box_iou_batch(e, pose(R, (0, 0, 1)), e, pose(R @ rot("y", 37), (0, 0, 1)), return_angle=True)
    assert iou[0] == pytest.approx(1.0, abs=1e-12)
    assert np.mod(angle[0] + np.radians(37), np.pi / 1) == pytest.approx(0.0, abs=1e-9) or \
        np.mod(angle[0] + np.radians(37), np.pi) == pytest.approx(np.pi, abs=1e-9)
    assert box_iou(e, pose(R, (0, 0, 1)), e, pose(R @ rot("y", 37), (0, 0, 1))) < 0.9


# --- axis-aligned (NOCS) IoU ----------------------------------------------------------------------

def test_axis_aligned_iou_uses_camera_aligned_bounding_boxes():
    # a unit cube rotated 45° about z has an axis-aligned box sqrt(2) x sqrt(2) x 1
    r2 = np.sqrt(2)
    assert axis_aligned_iou([1, 1, 1], pose(), [1, 1, 1], pose(rot("z", 45))) == pytest.approx(1 / (r2 * r2), abs=1e-12)
    assert axis_aligned_iou([1, 1, 1], pose(), [1, 1, 1], pose(t=(0.5, 0, 0))) == pytest.approx(1 / 3, abs=1e-12)
    assert axis_aligned_iou([1, 1, 1], pose(), [1, 1, 1], pose(t=(2, 0, 0))) == 0.0
    # symmetric: rotating the prediction by 2 pi i / 20 about y finds the 18° turn back
    e = [0.5, 1, 0.2]
    assert axis_aligned_iou(e, pose(), e, pose(rot("y", 18)), symmetry="y") == pytest.approx(1.0, abs=1e-12)
    assert axis_aligned_iou(e, pose(), e, pose(rot("y", 18))) < 0.9


# --- pose errors ----------------------------------------------------------------------------------

def test_translation_error_known_distances():
    assert translation_error([0, 0, 0], [0.03, 0.04, 0]) == pytest.approx(0.05)
    np.testing.assert_allclose(translation_error(np.zeros((2, 3)), [[1, 0, 0], [0, 2, 0]]), [1, 2])
    with pytest.raises(ValueError):
        translation_error([0, 0, np.nan], [0, 0, 0])


def test_rotation_error_known_angles():
    for axis in "xyz":
        for deg in [0.0, 1e-5, 3.0, 90.0, 179.0, 180.0]:
            assert rotation_error(np.eye(3), rot(axis, deg)) == pytest.approx(deg, abs=1e-9)
    R = Rotation.random(random_state=2).as_matrix()
    assert rotation_error(R, R @ rot("x", 25)) == pytest.approx(25, abs=1e-9)
    batch = rotation_error(np.stack([np.eye(3)] * 3), np.stack([rot("z", d) for d in (5, 10, 15)]))
    np.testing.assert_allclose(batch, [5, 10, 15], atol=1e-9)


def test_symmetric_rotation_error():
    # turning about y is free; tilting is not; upside down is 180 degrees
    assert rotation_error(np.eye(3), rot("y", 123), symmetry="y") == pytest.approx(0, abs=1e-12)
    assert rotation_error(np.eye(3), rot("x", 30) @ rot("y", 70), symmetry="y") == pytest.approx(30, abs=1e-9)
    assert rotation_error(np.eye(3), rot("x", 180), symmetry="y") == pytest.approx(180, abs=1e-12)
    assert rotation_error(np.eye(3), rot("z", 180) @ rot("y", 10), symmetry="y") == pytest.approx(180, abs=1e-12)
    # rounding that pushes the dot product past 1 must not give NaN
    R = Rotation.random(random_state=9).as_matrix()
    assert np.isfinite(rotation_error(R, R.copy(), symmetry="y"))


def test_rotation_error_rejects_nan_and_non_rotations():
    bad = np.eye(3)
    bad[0, 0] = np.nan
    for sym in ("none", "y"):
        with pytest.raises(ValueError):
            rotation_error(np.eye(3), bad, symmetry=sym)
    with pytest.raises(ValueError):
        rotation_error(np.eye(3), 2 * np.eye(3))
    with pytest.raises(ValueError):
        rotation_error(np.eye(3), np.eye(3), symmetry="z")


# --- chamfer and F-score --------------------------------------------------------------------------

def test_chamfer_distance_hand_made_sets():
    a = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    b = np.array([[0.0, 0, 0.1], [1.0, 0, 0.1], [3.0, 0, 0]])
    # a->b: 0.1, 0.1 (mean 0.1); b->a: 0.1, 0.1, 2.0 (mean 2.2 / 3)
    assert chamfer_distance(a, b) == pytest.approx((0.1 + 2.2 / 3) / 2)
    assert squared_chamfer_distance(a, b) == pytest.approx((0.01 + (0.01 + 0.01 + 4.0) / 3) / 2)
    assert chamfer_distance(a, b, squared=True) == squared_chamfer_distance(a, b)
    assert chamfer_distance(a, a) == 0.0


def test_fscore_hand_made_sets():
    gt = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    pred = np.array([[0.0, 0.005, 0], [1.0, 0.02, 0], [2.0, 0, 0.009]])
    # precision: pred within 1 cm of gt: 2 of 3; recall: gt within 1 cm of pred: 2 of 4
    f = fscore(gt, pred, threshold=0.01)
    assert isinstance(f, FScore)
    assert f.precision == pytest.approx(2 / 3) and f.recall == pytest.approx(0.5)
    assert f.fscore == pytest.approx(2 * (2 / 3) * 0.5 / (2 / 3 + 0.5))
    assert fscore(gt, gt + 1.0).fscore == 0.0
    assert fscore(gt, gt).fscore == 1.0
    # strict threshold: a distance of exactly the threshold does not count
    assert fscore(np.zeros((1, 3)), np.array([[0.0, 0.0, 0.5]]), threshold=0.5).fscore == 0.0
    with pytest.raises(ValueError):
        fscore(gt, np.array([[np.nan, 0, 0]]))
    with pytest.raises(ValueError):
        fscore(gt, pred, threshold=0)


# --- sampling -------------------------------------------------------------------------------------

def test_sample_surface_is_seeded_area_weighted_and_on_the_surface():
    box = trimesh.creation.box([0.1, 0.2, 0.4])
    p = sample_surface(box, n=40000, seed=3)
    assert p.shape == (40000, 3)
    np.testing.assert_array_equal(p, sample_surface(box, n=40000, seed=3))
    assert not np.array_equal(p, sample_surface(box, n=40000, seed=4))
    half = np.array([0.05, 0.1, 0.2])
    on_face = np.isclose(np.abs(p), half, atol=1e-12)
    assert np.all(on_face.any(axis=1))
    # area weighting: share of points on the two x faces = 2 * 0.2 * 0.4 / total area
    total = 2 * (0.1 * 0.2 + 0.1 * 0.4 + 0.2 * 0.4)
    assert on_face[:, 0].mean() == pytest.approx(2 * 0.2 * 0.4 / total, abs=0.01)
    # (V, F) arrays work the same
    np.testing.assert_array_equal(sample_surface((box.vertices, box.faces), n=10, seed=0), sample_surface(box, n=10, seed=0))


def test_sample_surface_rejects_bad_meshes():
    with pytest.raises(ValueError):
        sample_surface((np.zeros((3, 3)), np.array([[0, 1, 2]])))  # zero area
    with pytest.raises(ValueError):
        sample_surface((np.zeros((3, 3)), np.array([[0, 1, 5]])))
    with pytest.raises(ValueError):
        sample_surface(trimesh.creation.box([1, 1, 1]), n=0)


def test_shape_index_reuses_one_tree_and_matches_direct_metrics():
    box = trimesh.creation.box([0.1, 0.2, 0.1])
    index = ShapeIndex.from_mesh(box, n=5000, seed=0)
    assert len(index) == 5000
    pred = sample_surface(box, n=3000, seed=1) * 1.02
    assert index.fscore(pred, 0.005) == fscore(index.points, pred, 0.005)
    assert index.chamfer_distance(pred) == pytest.approx(chamfer_distance(index.points, pred), abs=1e-15)


def test_degenerate_configurations_in_random_frames_are_exact():
    """5000 pairs on a grid: coplanar, touching, contained, disjoint and zero-volume boxes, the second
    box turned by one of the 24 rotations that keep faces parallel, all in a random common frame.
    Truth: the axis-aligned overlap in that frame."""
    import itertools

    rng = np.random.default_rng(0)
    perms = []
    for p in itertools.permutations(range(3)):
        for s in itertools.product([1, -1], repeat=3):
            M = np.zeros((3, 3))
            M[range(3), p] = s
            if np.linalg.det(M) > 0:
                perms.append(M)
    n = 5000
    G = Rotation.random(n, random_state=3).as_matrix()
    ea, eb = rng.integers(1, 5, (n, 3)) * 0.05, rng.integers(0, 5, (n, 3)) * 0.05
    P = np.array(perms)[rng.integers(0, 24, n)]
    ta, tb = rng.integers(-4, 5, (n, 3)) * 0.025, rng.integers(-4, 5, (n, 3)) * 0.025
    Ta, Tb = np.tile(np.eye(4), (n, 1, 1)), np.tile(np.eye(4), (n, 1, 1))
    Ta[:, :3, :3], Ta[:, :3, 3] = G, np.einsum("nij,nj->ni", G, ta)
    Tb[:, :3, :3], Tb[:, :3, 3] = G @ P, np.einsum("nij,nj->ni", G, tb)
    half_b = np.abs(np.einsum("nij,nj->ni", P, eb)) / 2
    lo, hi = np.maximum(ta - ea / 2, tb - half_b), np.minimum(ta + ea / 2, tb + half_b)
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    va, vb = np.prod(ea, 1), np.prod(eb, 1)
    union = va + vb - inter
    expected = np.where((va > 0) & (vb > 0), inter / np.where(union > 0, union, 1), 0.0)
    assert np.sum(expected > 0) > 500 and np.sum((expected == 0) & np.all(hi - lo >= 0, axis=1)) > 500  # overlaps, contacts
    np.testing.assert_allclose(box_iou_batch(ea, Ta, eb, Tb), expected, atol=1e-13, rtol=0)


def test_shape_index_hits_shortcut_is_exactly_the_distance_test():
    # surface samples (where the grid-cell shortcut decides most points) and points placed exactly on
    # cell boundaries and at distances just below and above the threshold
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    index = ShapeIndex.from_mesh(mesh, n=3000, seed=0)
    rng = np.random.default_rng(1)
    threshold = 0.01
    cell = threshold * sampling._CELL
    near = index.points[:200] + rng.normal(size=(200, 3)) * 0.003
    on_grid = np.round(index.points[200:400] / cell) * cell
    direction = rng.normal(size=(100, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    shell = index.points[:100] * 1.5 + direction * 1e-3  # far from the sphere
    # dense prediction with a hole: few gt points undecided, checked against only the predicted points near them
    dense = sample_surface(mesh, 20000, seed=3)
    holed = dense[dense[:, 2] < 0.045]
    far_and_many = rng.normal(size=(90000, 3)) * 0.01 + [0.2, 0, 0]  # no predicted point near any gt point
    misaligned = index.points @ Rotation.from_rotvec([0.02, 0.05, -0.03]).as_matrix().T + [0.005, -0.004, 0.01]
    for pred in (sample_surface(mesh, 2500, seed=2) * 1.03, near, on_grid, shell, holed, far_and_many, misaligned):
        d_gt, d_pred = index.distances(pred)
        hit_gt, hit_pred = index.hits(pred, threshold)
        np.testing.assert_array_equal(hit_gt, d_gt < threshold)
        np.testing.assert_array_equal(hit_pred, d_pred < threshold)
        assert index.fscore(pred, threshold) == fscore(index.points, pred, threshold)


@pytest.mark.parametrize("cell", [0.01 / 3.8, 0.01 / 2.5, 0.004])
def test_grid_reach_certifies_only_pairs_closer_than_the_radius(cell):
    """Brute force over point pairs: every pair whose cells differ by an offset in reach is closer
    than the radius, and the reach holds every offset whose cells' farthest corners are."""
    radius = 0.01
    offsets = hit_grid.reach(cell, radius)
    rng = np.random.default_rng(0)
    # points on and off cell boundaries and corners, in a region a few reaches wide
    points = np.concatenate([rng.uniform(-0.015, 0.015, (1500, 3)),
                             np.round(rng.uniform(-0.015, 0.015, (500, 3)) / cell) * cell])
    cells = np.floor(points * (1 / cell)).astype(np.int64)
    diff = cells[:, None, :] - cells[None, :, :]
    in_reach = np.zeros(diff.shape[:2], bool)
    for o in offsets:
        in_reach |= np.all(diff == o, axis=2)
    distance = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    assert in_reach.sum() > 10000
    assert distance[in_reach].max() < radius
    r = int(np.ceil(radius / cell)) + 1
    grid = np.stack(np.meshgrid(*[np.arange(-r, r + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    corners = np.linalg.norm((np.abs(grid) + 1) * cell, axis=1)
    expected = {tuple(o) for o in grid[corners < radius * (1 - 1e-9)]}
    assert {tuple(o) for o in offsets} == expected


def test_shape_index_hits_without_grid_far_from_the_origin_or_spread_out():
    """Ground truth 5 km from the origin (cell indices beyond MAX_INDEX) or spread over 50 m (more than
    MAX_CELLS cells): no grid, KD-trees alone, the same hits as the distance test."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    surface = sample_surface(mesh, 2000, seed=0)
    rng = np.random.default_rng(2)
    for gt in (surface + [5000.0, 0.0, 0.0], np.concatenate([surface, surface + [50.0, 0.0, 0.0]])):
        index = ShapeIndex(gt)
        pred = gt[::2] * 1.0 + rng.normal(size=(len(gt) // 2, 3)) * 0.004
        hit_gt, hit_pred = index.hits(pred, 0.01)
        assert not index.prepare(0.01).built
        d_gt, d_pred = index.distances(pred)
        assert 0 < hit_pred.sum() < len(pred)
        np.testing.assert_array_equal(hit_gt, d_gt < 0.01)
        np.testing.assert_array_equal(hit_pred, d_pred < 0.01)


def test_shape_index_hits_at_the_threshold_exactly():
    """Predicted points at 1 - 1e-12 and 1 + 1e-12 thresholds from a gt point along random directions,
    and far outside the gt box: the grid never decides against the distance test."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    index = ShapeIndex.from_mesh(mesh, n=3000, seed=0)
    rng = np.random.default_rng(4)
    threshold = 0.01
    direction = rng.normal(size=(3000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    for scale in (1 - 1e-12, 1 + 1e-12):
        pred = np.concatenate([index.points + direction * threshold * scale, rng.uniform(-1, 1, (500, 3))])
        hit_gt, hit_pred = index.hits(pred, threshold)
        d_gt, d_pred = index.distances(pred)
        np.testing.assert_array_equal(hit_gt, d_gt < threshold)
        np.testing.assert_array_equal(hit_pred, d_pred < threshold)
