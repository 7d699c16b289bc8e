"""Thresholds, precision tables and curves, and compute_sample_errors (failed predictions, posed F-score)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from evaluate.metrics import (
    DEFAULT_THRESHOLDS,
    DEGREE_CURVE,
    FSCORE_CURVE,
    POSITION_CURVE,
    SampleErrors,
    ShapeIndex,
    Threshold,
    compute_sample_errors,
    correct,
    precision,
    precision_curves,
    precision_table,
    sample_surface,
    symmetric_box_iou,
)


def errors(**kw):
    n = len(next(iter(kw.values())))
    base = dict(position_error=np.zeros(n), rotation_error=np.zeros(n), iou=np.ones(n), fscore=np.ones(n))
    base.update(kw)
    return SampleErrors(**base)


def test_default_thresholds_are_the_papers_table_2():
    assert [t.as_dict() for t in DEFAULT_THRESHOLDS] == [
        {"position": 0.02, "degrees": 10, "iou": None, "fscore": None},
        {"position": 0.01, "degrees": 5, "iou": None, "fscore": None},
        {"position": 0.02, "degrees": 10, "iou": None, "fscore": 0.6},
        {"position": 0.01, "degrees": 5, "iou": None, "fscore": 0.8},
    ]
    assert DEFAULT_THRESHOLDS[2].label() == "10° 2 cm F≥0.6"
    np.testing.assert_allclose(POSITION_CURVE, np.linspace(0, 0.05, 11))
    np.testing.assert_array_equal(DEGREE_CURVE, np.arange(21))
    np.testing.assert_allclose(FSCORE_CURVE, np.linspace(0, 1, 21))
    with pytest.raises(ValueError):
        Threshold(position=-0.01)
    with pytest.raises(ValueError):
        Threshold(degrees=float("nan"))


def test_threshold_comparisons_are_inclusive_like_cpas():
    e = errors(position_error=np.array([0.02, 0.0201, 0.0]), rotation_error=np.array([10.0, 0, 10.01]),
               iou=np.array([0.5, 0.49, 0.5]), fscore=np.array([0.6, 0.6, 0.59]))
    np.testing.assert_array_equal(correct(e, [Threshold(position=0.02)])[0], [True, False, True])
    np.testing.assert_array_equal(correct(e, [Threshold(degrees=10)])[0], [True, True, False])
    np.testing.assert_array_equal(correct(e, [Threshold(iou=0.5)])[0], [True, False, True])
    np.testing.assert_array_equal(correct(e, [Threshold(fscore=0.6)])[0], [True, True, False])
    assert precision(e, Threshold(position=0.02, degrees=10)) == pytest.approx(1 / 3)


def test_failed_and_nan_samples_are_never_correct():
    e = errors(position_error=np.array([0.0, np.nan, 0.0, 0.0]), fscore=np.array([1.0, 1.0, np.nan, 1.0]))
    e.failed[3] = True
    np.testing.assert_array_equal(correct(e, [Threshold(position=1.0)])[0], [True, False, True, False])
    np.testing.assert_array_equal(correct(e, [Threshold(fscore=0.0)])[0], [True, True, False, False])
    np.testing.assert_array_equal(correct(e, [Threshold()])[0], [True, True, True, False])


def test_precision_table_overall_and_per_category():
    e = errors(position_error=np.array([0.005, 0.015, 0.03, 0.005]), rotation_error=np.array([1.0, 1.0, 1.0, 7.0]),
               fscore=np.array([0.9, 0.7, 0.9, 0.9]))
    rows = precision_table(e, DEFAULT_THRESHOLDS, categories=["mug", "mug", "bowl", "bowl"])
    assert [r["overall"] for r in rows] == [0.75, 0.25, 0.75, 0.25]
    assert rows[0]["per_category"] == {"bowl": 0.5, "mug": 1.0}
    assert rows[1]["per_category"] == {"bowl": 0.0, "mug": 0.5}
    assert rows[3] == {"position": 0.01, "degrees": 5, "iou": None, "fscore": 0.8, "overall": 0.25,
                             "per_category": {"bowl": 0.0, "mug": 0.5}}
    with pytest.raises(ValueError):
        precision_table(e, DEFAULT_THRESHOLDS, categories=["mug"])
    empty = precision_table(SampleErrors.concatenate([]), DEFAULT_THRESHOLDS)
    assert all(np.isnan(r["overall"]) for r in empty)


def test_precision_curves_are_monotone_step_functions_of_the_errors():
    rng = np.random.default_rng(0)
    n = 500
    e = errors(position_error=rng.uniform(0, 0.06, n), rotation_error=rng.uniform(0, 25, n), iou=rng.uniform(0, 1, n),
               fscore=rng.uniform(0, 1, n))
    curves = precision_curves(e, categories=rng.choice(["a", "b"], n))
    assert set(curves) == {"position", "degrees", "fscore", "iou"}
    pos = curves["position"]
    np.testing.assert_allclose(pos["overall"], [(e.position_error <= t).mean() for t in POSITION_CURVE])
    np.testing.assert_allclose(curves["fscore"]["overall"], [(e.fscore >= t).mean() for t in FSCORE_CURVE])
    assert np.all(np.diff(curves["degrees"]["overall"]) >= 0)
    assert np.all(np.diff(curves["iou"]["overall"]) <= 0)
    assert set(pos["per_category"]) == {"a", "b"}
    assert "iou" not in precision_curves(e, iou=None)


def test_compute_sample_errors_known_errors_and_failures():
    box = trimesh.creation.box([0.1, 0.2, 0.1])
    index = ShapeIndex.from_mesh(box, n=4000, seed=0)
    q_gt = Rotation.from_euler("x", 30, degrees=True).as_quat()
    q_pred = (Rotation.from_euler("x", 30, degrees=True) * Rotation.from_euler("z", 4, degrees=True)).as_quat()
    ext = [0.1, 0.2, 0.1]
    pts = sample_surface(box, 3000, seed=1)
    gt = dict(gt_position=np.tile([0.0, 0.0, 0.6], (6, 1)), gt_orientation=np.tile(q_gt, (6, 1)), gt_extents=np.tile(ext, (6, 1)),
              gt_symmetry=["none", "y", "none", "none", "none", "none"], gt_shape=[index] * 6)
    pred = dict(
        pred_position=[[0.003, 0.004, 0.6], [0.0, 0.0, 0.6], [0, 0, 0.6], [0, 0, 0.6], [0, 0, 0.6], None],
        pred_orientation=[q_pred, q_pred, q_pred * 2, q_pred, [0, 0, 0, 1, 0], q_pred],
        pred_extents=[ext, ext, ext, [0.1, -0.2, 0.1], ext, ext],
        pred_points=[pts, None, pts, pts, pts, pts],
    )
    e = compute_sample_errors(**gt, **pred)
    assert e.position_error[0] == pytest.approx(0.005)
    assert e.rotation_error[0] == pytest.approx(4.0, abs=1e-6)
    assert e.rotation_error[1] == pytest.approx(4.0, abs=1e-6)  # rotation about z tilts the y axis by 4 deg
    assert 0.5 < e.fscore[0] < 1.0
    assert np.isnan(e.fscore[1]) and not e.failed[1]  # no reconstruction: F-score unavailable, pose fine
    # symmetric IoU for the symmetric sample
    assert e.iou[1] == pytest.approx(symmetric_box_iou(np.array(ext), _pose(q_gt, [0, 0, 0.6]), np.array(ext), _pose(q_pred, [0, 0, 0.6])))
    np.testing.assert_array_equal(e.failed, [False, False, True, True, True, True])
    assert "unit quaternion" in e.failure[2] and "negative" in e.failure[3] and "shape" in e.failure[4]
    assert "missing position" in e.failure[5]
    assert np.all(np.isnan(e.position_error[2:])) and np.all(np.isnan(e.iou[2:]))
    # single-sample form gives the same numbers
    one = compute_sample_errors([0, 0, 0.6], q_gt, ext, "none", index, [0.003, 0.004, 0.6], q_pred, ext, pts)
    assert one.fscore[0] == e.fscore[0] and one.iou[0] == e.iou[0]


def test_compute_sample_errors_fscore_is_on_posed_shapes():
    # a perfect shape in a wrong pose loses F-score; the same shape in the true pose has F = 1
    box = trimesh.creation.box([0.1, 0.2, 0.1])
    index = ShapeIndex.from_mesh(box, n=4000, seed=0)
    pts = index.points.copy()
    q = Rotation.random(random_state=1).as_quat()
    right = compute_sample_errors([0, 0, 0.6], q, [0.1, 0.2, 0.1], "none", index, [0, 0, 0.6], q, None, pts)
    moved = compute_sample_errors([0, 0, 0.6], q, [0.1, 0.2, 0.1], "none", index, [0.03, 0, 0.6], q, None, pts)
    assert right.fscore[0] == 1.0 and moved.fscore[0] < 0.5
    assert np.isnan(right.iou[0])  # no predicted extents: no IoU
    with_chamfer = compute_sample_errors([0, 0, 0.6], q, [0.1, 0.2, 0.1], "none", index, [0.03, 0, 0.6], q, None, pts,
                                         compute_chamfer=True)
    assert 0.005 < with_chamfer.chamfer[0] < 0.03


def test_compute_sample_errors_rejects_bad_ground_truth():
    with pytest.raises(ValueError):
        compute_sample_errors([0, 0, np.nan], [0, 0, 0, 1], [1, 1, 1], "none", None, [0, 0, 0], [0, 0, 0, 1], [1, 1, 1])
    with pytest.raises(ValueError):
        compute_sample_errors([0, 0, 0], [0, 0, 0, 2], [1, 1, 1], "none", None, [0, 0, 0], [0, 0, 0, 1], [1, 1, 1])
    with pytest.raises(ValueError):
        compute_sample_errors([0, 0, 0], [0, 0, 0, 1], [1, 1, 1], "x", None, [0, 0, 0], [0, 0, 0, 1], [1, 1, 1])


def _pose(q, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = t
    return T
