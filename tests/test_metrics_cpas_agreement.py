"""Agreement with cpas_toolbox 1.0.0 (metrics.py) wherever it is right, and one test per difference.

Agreement: exact box IoU within 1e-9 of cpas's ``iou_3d`` (Qhull half-space intersection, exact up to
Qhull's rounding, ~1e-12 here); chamfer distance and F-score bit for bit on the same points; rotation
errors to rounding; and the correct/incorrect decision of ``correct_thresh`` over the whole REDWOOD75
threshold grid on random samples.  cpas's ``iou_3d_sampling`` (10000 uniform points, global random
state) is only a Monte-Carlo estimate, compared at its statistical precision.

Differences, each shown below with cpas's wrong answer and ours:
* symmetric rotation error: unclamped arccos gives NaN for upside-down predictions of symmetric objects
  and NaN > threshold is False, so many of them count as correct at 5 degrees (ours: 180 degrees);
* symmetric IoU threshold: ``Rotation.from_rotvec`` gets a scalar and raises ValueError (ours: exact max);
* touching or zero-volume boxes: QhullError (ours: IoU 0);
* ``iou_3d`` draws from NumPy's global random state (ours: no randomness);
* a NaN prediction passes a position threshold (ours: failed, never correct).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluate.metrics import (
    SampleErrors,
    ShapeIndex,
    Threshold,
    box_iou,
    box_iou_batch,
    chamfer_distance,
    compute_sample_errors,
    correct,
    fscore,
    rotation_error,
    symmetric_box_iou,
)

cpas = pytest.importorskip("cpas_toolbox.metrics")


def pose(rotation: Rotation, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation.as_matrix()
    T[:3, 3] = t
    return T


def random_pairs(n: int, seed: int):
    rng = np.random.default_rng(seed)
    for i in range(n):
        yield (rng.normal(size=3) * 0.03, Rotation.random(random_state=seed * 1000 + i), rng.uniform(0.03, 0.25, 3),
               rng.normal(size=3) * 0.03, Rotation.random(random_state=seed * 1000 + 500 + i), rng.uniform(0.03, 0.25, 3))


def test_box_iou_equals_cpas_iou_3d_within_1e_9():
    np.random.seed(0)  # cpas's inside-point search draws from the global state
    diffs, nonzero = [], 0
    for p1, r1, e1, p2, r2, e2 in random_pairs(150, seed=1):
        theirs = cpas.iou_3d(p1, r1, e1, p2, r2, e2)
        ours = box_iou(e1, pose(r1, p1), e2, pose(r2, p2))
        diffs.append(abs(theirs - ours))
        nonzero += theirs > 0
    assert nonzero > 100  # the inputs mostly overlap: the comparison is not about zeros
    assert max(diffs) < 1e-9


def test_box_iou_batch_equals_cpas_iou_3d():
    np.random.seed(0)
    pairs = list(random_pairs(60, seed=2))
    theirs = np.array([cpas.iou_3d(*p) for p in pairs])
    ours = box_iou_batch(np.array([p[2] for p in pairs]), np.stack([pose(p[1], p[0]) for p in pairs]),
                         np.array([p[5] for p in pairs]), np.stack([pose(p[4], p[3]) for p in pairs]))
    np.testing.assert_allclose(ours, theirs, atol=1e-9, rtol=0)


def test_cpas_sampled_iou_is_a_monte_carlo_estimate_of_ours():
    np.random.seed(0)
    for p1, r1, e1, p2, r2, e2 in random_pairs(10, seed=3):
        sampled = cpas.iou_3d_sampling(p1, r1, e1, p2, r2, e2, num_points=10000)
        # 10000 points: the intersection fraction has standard error <= 0.005; IoU error is smaller
        assert box_iou(e1, pose(r1, p1), e2, pose(r2, p2)) == pytest.approx(sampled, abs=0.03)


def test_chamfer_and_fscore_equal_cpas_bit_for_bit():
    rng = np.random.default_rng(4)
    for n_gt, n_pred, noise in [(1000, 800, 0.003), (5000, 5000, 0.01), (300, 2000, 0.02)]:
        gt = rng.normal(size=(n_gt, 3)) * 0.05
        pred = gt[rng.integers(0, n_gt, n_pred)] + rng.normal(size=(n_pred, 3)) * noise
        assert chamfer_distance(gt, pred) == cpas.symmetric_chamfer(gt, pred)
        for threshold in (0.005, 0.01, 0.02):
            ours = fscore(gt, pred, threshold)
            assert ours.fscore == cpas.reconstruction_fscore(gt, pred, threshold)
            assert ours.precision == cpas.accuracy_thresh(gt, pred, threshold)
            assert ours.recall == cpas.completeness_thresh(gt, pred, threshold)
        index = ShapeIndex(gt)
        assert index.fscore(pred, 0.01).fscore == cpas.reconstruction_fscore(gt, pred, 0.01)
        assert index.chamfer_distance(pred) == cpas.symmetric_chamfer(gt, pred)


def test_rotation_error_equals_cpas_where_cpas_is_finite():
    a, b = Rotation.random(300, random_state=5), Rotation.random(300, random_state=6)
    theirs = np.degrees((a * b.inv()).magnitude())
    np.testing.assert_allclose(rotation_error(a.as_matrix(), b.as_matrix()), theirs, atol=1e-9)
    # symmetric: cpas's arccos(y_gt · y_pred) where finite; arccos is ill-conditioned near 0 and 180
    dots = np.einsum("ni,ni->n", a.apply([0, 1, 0]), b.apply([0, 1, 0]))
    np.testing.assert_allclose(rotation_error(a.as_matrix(), b.as_matrix(), "y"), np.degrees(np.arccos(dots)), atol=1e-6)


def _redwood75_grid():
    """The REDWOOD75 config's metric grid (cpas_toolbox config/redwood75.yaml), as (p, d, i, f) tuples."""
    pos = [0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03, 0.035, 0.04, 0.045, 0.05]
    deg = list(range(21))
    f = [0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0]
    grid = [(p, None, None, None) for p in pos] + [(None, d, None, None) for d in deg] + [(None, None, None, x) for x in f]
    return grid + [(0.02, 10, None, None), (0.01, 5, None, None), (0.02, 10, None, 0.6), (0.01, 5, None, 0.8)]


def test_correct_thresh_decisions_match_over_the_redwood75_grid():
    rng = np.random.default_rng(7)
    gt_points = rng.normal(size=(2000, 3)) * np.array([0.04, 0.08, 0.04])
    index = ShapeIndex(gt_points)
    grid = _redwood75_grid()
    thresholds = [Threshold(position=p, degrees=d, iou=i, fscore=f) for p, d, i, f in grid]
    for k in range(12):
        r_gt = Rotation.random(random_state=100 + k)
        r_pred = r_gt * Rotation.from_rotvec(rng.normal(size=3) * rng.uniform(0.01, 0.2))
        p_gt = np.array([0.0, 0.0, 0.8]) + rng.normal(size=3) * 0.05
        p_pred = p_gt + rng.normal(size=3) * rng.uniform(0.002, 0.03)
        pred_points = gt_points[rng.integers(0, 2000, 1500)] * rng.uniform(0.95, 1.05) + rng.normal(size=(1500, 3)) * 0.003
        ours = compute_sample_errors(p_gt, r_gt.as_quat(), [0.1, 0.2, 0.1], "none", index, p_pred, r_pred.as_quat(),
                                     [0.1, 0.2, 0.1], pred_points, compute_iou=False)
        ours_correct = correct(ours, thresholds)[:, 0]
        posed_gt = r_gt.apply(gt_points) + p_gt
        posed_pred = r_pred.apply(pred_points) + p_pred
        theirs = [cpas.correct_thresh(p_gt, p_pred, r_gt, r_pred, points_gt=posed_gt, points_prediction=posed_pred,
                                      position_threshold=p, degree_threshold=d, iou_3d_threshold=i, fscore_threshold=f)
                  for p, d, i, f in grid]
        np.testing.assert_array_equal(ours_correct, np.array(theirs, dtype=bool))


# --- documented differences ----------------------------------------------------------------------

def test_difference_upside_down_symmetric_prediction_nan_counted_correct():
    rng = np.random.default_rng(8)
    n, passed = 300, 0
    ours = []
    for i in range(n):
        gt = Rotation.random(random_state=200 + i)
        pred = gt * Rotation.from_euler("x", 180, degrees=True) * Rotation.from_euler("y", rng.uniform(0, 360), degrees=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # cpas: "invalid value encountered in arccos"
            passed += cpas.correct_thresh(np.zeros(3), np.zeros(3), gt, pred, degree_threshold=5, rotational_symmetry_axis=1)
        ours.append(rotation_error(gt.as_matrix(), pred.as_matrix(), symmetry="y"))
    assert passed / n > 0.2  # cpas: a large share of 180°-wrong predictions "within 5 degrees"
    np.testing.assert_allclose(ours, 180.0, atol=1e-9)  # ours: 180 degrees, never correct
    errors = SampleErrors(np.zeros(n), np.array(ours), np.full(n, np.nan), np.full(n, np.nan))
    assert not correct(errors, [Threshold(degrees=5)]).any()


def test_difference_symmetric_iou_threshold_raises_in_cpas():
    r = Rotation.from_euler("xyz", [0.3, 0.3, 0.5])
    with pytest.raises(ValueError):
        cpas.correct_thresh(np.zeros(3), np.zeros(3), r, r, np.ones(3), np.ones(3), iou_3d_threshold=0.5,
                            rotational_symmetry_axis=1)
    turned = r * Rotation.from_euler("y", 40, degrees=True)
    e = np.array([0.5, 1.0, 0.3])
    assert symmetric_box_iou(e, pose(r, np.zeros(3)), e, pose(turned, np.zeros(3))) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("case", ["touching", "touching_rotated", "zero_volume", "zero_volume_one"])
def test_difference_touching_and_zero_volume_boxes_raise_qhull_error_in_cpas(case):
    from scipy.spatial import QhullError

    ident = Rotation.identity()
    args = {
        "touching": (np.zeros(3), ident, np.ones(3), np.array([1.0, 0, 0]), ident, np.ones(3)),
        "touching_rotated": (np.zeros(3), ident, np.ones(3), np.array([0, 0, 1.0]), Rotation.from_euler("z", 30, degrees=True), np.ones(3)),
        "zero_volume": (np.zeros(3), ident, np.array([0, 1, 1.0]), np.zeros(3), ident, np.array([0, 1, 1.0])),
        "zero_volume_one": (np.zeros(3), ident, np.array([0, 1, 1.0]), np.zeros(3), ident, np.ones(3)),
    }[case]
    np.random.seed(0)
    with pytest.raises(QhullError):
        cpas.iou_3d(*args)
    p1, r1, e1, p2, r2, e2 = args
    assert box_iou(e1, pose(r1, p1), e2, pose(r2, p2)) == pytest.approx(0.0, abs=1e-12)


def test_difference_cpas_iou_consumes_global_random_state():
    ident = Rotation.identity()
    np.random.seed(123)
    before = np.random.get_state()[1].copy(), np.random.get_state()[2]
    box_iou(np.ones(3), pose(ident, np.zeros(3)), np.ones(3), pose(ident, [0.1, 0, 0]))
    after = np.random.get_state()[1], np.random.get_state()[2]
    assert np.array_equal(before[0], after[0]) and before[1] == after[1]  # ours: untouched
    cpas.iou_3d(np.zeros(3), ident, np.ones(3), np.array([0.1, 0, 0]), ident, np.ones(3))
    changed = np.random.get_state()
    assert not (np.array_equal(before[0], changed[1]) and before[1] == changed[2])  # cpas: consumed


def test_difference_nan_prediction_passes_cpas_position_threshold():
    ident = Rotation.identity()
    assert cpas.correct_thresh(np.zeros(3), np.array([np.nan, 0, 0]), ident, ident, position_threshold=0.01) == 1
    ours = compute_sample_errors([0, 0, 0.5], [0, 0, 0, 1], [0.1, 0.1, 0.1], "none", None, [np.nan, 0, 0.5], [0, 0, 0, 1], [0.1, 0.1, 0.1])
    assert ours.failed[0] and "NaN" in ours.failure[0]
    assert not correct(ours, [Threshold(position=0.01)]).any()
