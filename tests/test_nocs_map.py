"""NOCS-style mAP (evaluate.metrics.nocs_map): hand-computed cases that follow the reference definitions
(hughw19/NOCS_CVPR2019 utils.py: compute_3d_matches, compute_match_from_degree_cm with
use_matches_for_pose, compute_ap_from_matches_scores), the symmetric handling, an independent loop
implementation of the reference's matching and AP on random scenes, where the reference's IoU differs
from the exact one, bad input, and the evaluate outputs."""

from __future__ import annotations

import csv
import json
import math
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluate.metrics.box_iou import axis_aligned_iou, box_iou, symmetric_box_iou
from evaluate.metrics.nocs_map import (
    NocsMapConfig,
    average_precision,
    candidate_pairs,
    nocs_map,
    nocs_symmetric,
    pair_errors,
)

CUBE = np.array([0.2, 0.2, 0.2])


def pose(t=(0.0, 0.0, 1.0), rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()
    T[:3, 3] = t
    return T


def about_x(degrees: float) -> tuple[float, float, float]:
    return (math.radians(degrees), 0.0, 0.0)


def about_y(degrees: float) -> tuple[float, float, float]:
    return (0.0, math.radians(degrees), 0.0)


def run(gt, dets, config=NocsMapConfig(), symmetric=None):
    """gt: [(image, category, T, extents)], dets: [(image, category, score, T, extents)]."""
    symmetric = np.zeros(len(gt), bool) if symmetric is None else np.asarray(symmetric)
    return nocs_map(
        [g[0] for g in gt], [g[1] for g in gt], np.array([g[2] for g in gt]).reshape(-1, 4, 4), np.array([g[3] for g in gt]).reshape(-1, 3), symmetric,
        [d[0] for d in dets], [d[1] for d in dets], [d[2] for d in dets], np.array([d[3] for d in dets]).reshape(-1, 4, 4), np.array([d[4] for d in dets]).reshape(-1, 3),
        config,
    )


# --- hand-computed cases --------------------------------------------------------------------------

def test_iou_ap_hand_computed():
    """3 ground-truth cubes (side 0.2 m), 4 detections.  Cubes shifted by s along x: IoU = (0.2 - s) / (0.2 + s).

    image A: a1 at x = 0, a2 at x = 1;  image B: b1 at x = 0.
    d1 (0.9) A, x = 0.05: IoU(a1) = 0.6      d2 (0.8) A, x = 0: IoU(a1) = 1
    d3 (0.7) B, x = 0.1:  IoU(b1) = 1/3      d4 (0.6) A, x = 1.02: IoU(a2) = 0.18 / 0.22
    IoU > 0.25: d1 takes a1; d2 finds a1 taken and a2 at IoU 0: FP; d3, d4 TP.  TP FP TP TP:
      precision 1, 1/2, 2/3, 3/4, recall 1/3, 1/3, 2/3, 1; envelope 1, 3/4, 3/4, 3/4: AP = 1/3 + 1/3 (3/4) + 1/3 (3/4) = 5/6.
    IoU > 0.5: d3 fails too.  TP FP FP TP: envelope 1, 1/2, 1/2, 1/2 at recalls 1/3, 1/3, 1/3, 2/3: AP = 1/3 + 1/6 = 1/2.
    IoU > 0.75: d1 fails (0.6), so d2 takes a1.  FP TP FP TP: precision 0, 1/2, 1/3, 1/2; envelope 1/2: AP = 2/3 (1/2) = 1/3.
    """
    gt = [("A", "camera", pose((0, 0, 1)), CUBE), ("A", "camera", pose((1, 0, 1)), CUBE), ("B", "camera", pose((0, 0, 1)), CUBE)]
    dets = [("A", "camera", 0.9, pose((0.05, 0, 1)), CUBE), ("A", "camera", 0.8, pose((0, 0, 1)), CUBE),
            ("B", "camera", 0.7, pose((0.1, 0, 1)), CUBE), ("A", "camera", 0.6, pose((1.02, 0, 1)), CUBE)]
    result = run(gt, dets)
    assert result.categories == ["camera"]
    assert result.iou_ap[0] == pytest.approx([5 / 6, 1 / 2, 1 / 3], abs=1e-12)
    # the order of the input does not matter, only the scores
    result = run(gt[::-1], dets[::-1])
    assert result.iou_ap[0] == pytest.approx([5 / 6, 1 / 2, 1 / 3], abs=1e-12)
    # the curve: at IoU 0 every pair with overlap matches, at 1 none does
    grid, ap = result.curves["iou"]
    assert grid[[0, 25, 50, 75, 100]] == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    assert ap[0, [25, 50, 75, 100]] == pytest.approx([5 / 6, 1 / 2, 1 / 3, 0.0], abs=1e-12)


def test_iou_equal_to_the_threshold_does_not_match():
    """The reference matches only when IoU > threshold: cubes shifted by 0.2 / 3 have IoU exactly 1/2."""
    s = 0.2 / 3
    iou = box_iou(CUBE, pose((0, 0, 1)), CUBE, pose((s, 0, 1)))
    config = NocsMapConfig(iou_thresholds=(iou, np.nextafter(iou, 0)))
    result = run([("A", "camera", pose((0, 0, 1)), CUBE)], [("A", "camera", 1.0, pose((s, 0, 1)), CUBE)], config)
    assert result.iou_ap[0].tolist() == [0.0, 1.0]


def pose_scene():
    """Four images with one cube each (category camera); detections with known rotation (about x) and
    translation errors, all with IoU > 0.1, and a second, lower-scored one in image 0."""
    gt = [(f"i{k}", "camera", pose((0, 0, 1)), CUBE) for k in range(4)]
    dets = [
        ("i0", "camera", 0.95, pose((0.01, 0, 1), about_x(3)), CUBE),  # 3 deg, 1 cm
        ("i1", "camera", 0.90, pose((0.01, 0, 1), about_x(7)), CUBE),  # 7 deg, 1 cm
        ("i2", "camera", 0.85, pose((0.04, 0, 1), about_x(3)), CUBE),  # 3 deg, 4 cm
        ("i3", "camera", 0.80, pose((0.03, 0, 1), about_x(12)), CUBE),  # 12 deg, 3 cm
        ("i0", "camera", 0.70, pose((0.005, 0, 1), about_x(1)), CUBE),  # 1 deg, 0.5 cm; i0's cube is taken at IoU 0.1
    ]
    return gt, dets


def test_pose_ap_hand_computed():
    """Pose AP over the pairs matched at IoU > 0.1 (the last detection is not one: i0's cube went to the first).

    5 deg 2 cm: T F F F -> AP 1/4.   5 deg 5 cm: T F T F -> precision 1, 1/2, 2/3, 1/2, envelope 1, 2/3, 2/3, 1/2
    at recalls 1/4, 1/4, 1/2, 1/2: AP = 1/4 + 1/4 (2/3) = 5/12.   10 deg 2 cm: T T F F -> 1/2.   10 deg 5 cm: T T T F -> 3/4.
    """
    gt, dets = pose_scene()
    result = run(gt, dets)
    assert result.pose_thresholds.tolist() == [[5, 0.02], [5, 0.05], [10, 0.02], [10, 0.05]]
    assert result.pose_ap[0] == pytest.approx([1 / 4, 5 / 12, 1 / 2, 3 / 4], abs=1e-12)
    # the curves: rotation alone (translation <= 1 m) and translation alone (rotation <= 360 deg)
    degrees, ap = result.curves["degrees"]
    # at 2 deg none; at 4: T F T F -> 5/12; at 8: T T T F -> 3/4; from 13: all
    assert degrees[[2, 4, 8, 13, 60]].tolist() == [2, 4, 8, 13, 60]
    assert ap[0, [2, 4, 8, 13, 60]] == pytest.approx([0, 5 / 12, 3 / 4, 1, 1], abs=1e-12)
    position, ap = result.curves["position"]
    assert position[[1, 3, 7, 9]] == pytest.approx([0.005, 0.015, 0.035, 0.045])
    # at 0.5 cm none; at 1.5 cm: T T F F (i2 4 cm, i3 3 cm) -> 1/2; at 3.5 cm: T T F T -> 1/4 + 1/4 + 1/4 (3/4) = 11/16; at 4.5 cm: all
    assert ap[0, [1, 3, 7, 9]] == pytest.approx([0, 1 / 2, 11 / 16, 1], abs=1e-12)


def test_pose_gate_and_its_absence():
    """A detection at the exact pose but a tenth of the size (IoU 0.001 < 0.1) with the top score, in i2:
    with NOCS's gate it takes no part in pose AP (and i2's cube still goes to its other detection);
    without a gate (use_matches_for_pose=False) it takes i2's cube: at 5 deg 2 cm T T F F F F -> AP 1/2."""
    gt, dets = pose_scene()
    dets = dets + [("i2", "camera", 0.99, pose((0, 0, 1)), CUBE / 10)]
    gated = run(gt, dets)
    assert gated.pose_ap[0] == pytest.approx([1 / 4, 5 / 12, 1 / 2, 3 / 4], abs=1e-12)
    open_ = run(gt, dets, NocsMapConfig(pose_iou_gate=None))
    # 5/2: T(tiny, i2) T(i0) F F(i2 taken) F F -> 1/2;  5/5: T T F F F F -> 1/2;  10/2: T T T F F F -> 3/4;  10/5: T T T F F F -> 3/4
    assert open_.pose_ap[0] == pytest.approx([1 / 2, 1 / 2, 3 / 4, 3 / 4], abs=1e-12)


def test_pose_matching_takes_the_smallest_degrees_plus_cm():
    """Two cubes in one image, 3 cm apart; one detection between them, 1 cm + 10 deg from the first and
    2 cm + 0 deg from the second (sums 11 and 2): at 10 deg 5 cm both qualify, and it takes the second,
    leaving the first to a lower-scored detection that only fits the first."""
    gt = [("A", "camera", pose((0, 0, 1), about_x(10)), CUBE), ("A", "camera", pose((0.03, 0, 1)), CUBE)]
    dets = [("A", "camera", 0.9, pose((0.01, 0, 1)), CUBE), ("A", "camera", 0.5, pose((0, 0, 1), about_x(9)), CUBE)]
    result = run(gt, dets, NocsMapConfig(pose_thresholds=((10.5, 0.05),)))
    assert result.pose_ap[0] == pytest.approx([1.0], abs=1e-12)


def test_mean_is_over_the_categories_and_other_categories_are_ignored():
    """Two categories: camera AP 1, laptop AP 0 (its one detection in the wrong place): mean 1/2.  A detection
    of a category without ground truth changes nothing and is counted as ignored."""
    gt = [("A", "camera", pose(), CUBE), ("A", "laptop", pose((1, 0, 1)), CUBE)]
    dets = [("A", "camera", 0.5, pose(), CUBE), ("A", "laptop", 0.9, pose((0.5, 0, 1)), CUBE), ("A", "mug", 0.7, pose(), CUBE)]
    result = run(gt, dets)
    assert result.categories == ["camera", "laptop"]
    assert result.iou_ap.tolist() == [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]
    assert result.mean(result.iou_ap).tolist() == [0.5, 0.5, 0.5]
    assert (result.detections, result.ground_truth, result.ignored) == (2, 2, 1)
    # a detection of the right category in an image without that category's truth is a false positive
    more = run(gt, dets + [("B", "camera", 0.8, pose(), CUBE)])
    assert more.iou_ap[0].tolist() == [0.5, 0.5, 0.5]  # FP (0.8) then TP (0.5): precision 0, 1/2 at recall 0, 1


def test_no_detections_and_no_truth():
    gt = [("A", "camera", pose(), CUBE)]
    empty = np.zeros((0, 4, 4)), np.zeros((0, 3))
    result = nocs_map(["A"], ["camera"], [pose()], [CUBE], [False], [], [], [], *empty)
    assert result.iou_ap.tolist() == [[0.0, 0.0, 0.0]] and result.pose_ap.tolist() == [[0.0] * 4]
    result = nocs_map([], [], *empty, [], ["A"], ["camera"], [1.0], [pose()], [CUBE])
    assert result.categories == [] and result.ignored == 1 and np.isnan(result.mean(result.iou_ap)).all()
    assert run(gt, [("A", "camera", 1.0, pose(), CUBE)]).iou_ap.tolist() == [[1.0, 1.0, 1.0]]


# --- ties -------------------------------------------------------------------------------------------

def test_tied_scores_are_one_operating_point():
    """All scores equal: one point, precision TP / detections at recall TP / truth, whatever the order:
    AP = recall x precision.  Distinct scores would give 1/2 x 1 = 1/2 for TP first, 1/2 x 1/2 = 1/4 for FP first."""
    tp = np.array([[True, False], [False, True]])
    assert average_precision(tp, [1.0, 1.0], 2).tolist() == [0.25, 0.25]
    assert average_precision(tp, [1.0, 0.5], 2).tolist() == [0.5, 0.25]
    rng = np.random.default_rng(3)
    hits = rng.random(40) < 0.6
    scores = rng.integers(0, 4, 40).astype(float)  # many ties
    perm = rng.permutation(40)
    assert average_precision(hits, scores, 30)[0] == pytest.approx(average_precision(hits[perm], scores[perm], 30)[0], abs=1e-15)
    assert average_precision(hits, np.ones(40), 30)[0] == pytest.approx((hits.sum() / 30) * (hits.sum() / 40), abs=1e-15)


# --- symmetric handling -----------------------------------------------------------------------------

BOX = np.array([0.2, 0.3, 0.1])  # x != z: a quarter turn about y changes the box


@pytest.mark.parametrize("turn", [90.0, 9.0, 33.0])
def test_symmetric_truth_ignores_the_turn_about_y(turn):
    """A bottle (and a mug whose handle is hidden) turned about y matches at IoU 1 and 0 degrees; a mug
    whose handle is visible does not: at a quarter turn the boxes overlap in 0.1 x 0.3 x 0.1 of 0.2 x 0.3 x 0.1
    each, IoU 1/3, and the rotation error is 90 degrees."""
    gt_pose, det_pose = pose((0, 0, 1), about_y(20)), pose((0, 0, 1), about_y(20 + turn))
    for category, visible, symmetric in (("bottle", None, True), ("mug", False, True), ("mug", True, False), ("mug", None, False)):
        flags = nocs_symmetric([category], ["y" if category == "bottle" else "none"], [visible])
        assert flags.tolist() == [symmetric]
        pairs = pair_errors(candidate_pairs(["A"], [category], ["A"], [category]), [gt_pose], [BOX], flags, [det_pose], [BOX])
        result = run([("A", category, gt_pose, BOX)], [("A", category, 1.0, det_pose, BOX)], symmetric=flags)
        if symmetric:
            assert pairs.iou[0] == pytest.approx(1.0, abs=1e-9) and pairs.degrees[0] == pytest.approx(0.0, abs=1e-6)
            assert result.iou_ap[0].tolist() == [1.0, 1.0, 1.0] and result.pose_ap[0].tolist() == [1.0] * 4
        else:
            assert pairs.degrees[0] == pytest.approx(turn, abs=1e-9)
            assert result.pose_ap[0].tolist() == ([0.0] * 4 if turn > 10 else [0.0, 0.0, 1.0, 1.0])
            if turn == 90.0:
                assert pairs.iou[0] == pytest.approx(1 / 3, abs=1e-12)
                assert result.iou_ap[0].tolist() == [1.0, 0.0, 0.0]


def test_symmetric_truth_still_counts_the_tilt_of_y():
    """Symmetric: the rotation error is the angle between the y axes, so a tilt about x counts in full."""
    flags = nocs_symmetric(["can"])
    pairs = pair_errors(candidate_pairs(["A"], ["can"], ["A"], ["can"]), [pose()], [BOX], flags, [pose(rotvec=about_x(7))], [BOX])
    assert flags.tolist() == [True] and pairs.degrees[0] == pytest.approx(7.0, abs=1e-9)


def test_symmetric_categories_come_from_the_one_definition():
    from sequences.annotation import SYMMETRIC_CATEGORIES

    categories = list(SYMMETRIC_CATEGORIES) + ["mug", "camera", "laptop"]
    assert nocs_symmetric(categories).tolist() == [True] * len(SYMMETRIC_CATEGORIES) + [False] * 3
    # a label wins over the category: a square bowl labelled "none" is not symmetric, and a mug's handle
    # only matters when it is known to be hidden
    assert nocs_symmetric(["bowl", "camera"], ["none", "y"]).tolist() == [False, True]
    assert nocs_symmetric(["mug", "mug", "mug", "camera"], None, [False, True, None, False]).tolist() == [True, False, False, False]


# --- the reference's IoU, and where ours differs ---------------------------------------------------

def published_iou(extents_1, T_1, extents_2, T_2, axis: int = 0) -> float:
    """The asymmetric IoU of the reference's compute_3d_iou_new, restated: the 8 corners of each box in the
    camera frame as a (3, 8) array, its max and min along ``axis`` (the published code: 0, i.e. per corner over
    x, y, z; copies that fixed it: 1, per coordinate over the corners), the product of the overlaps."""
    signs = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=float) * 2 - 1
    c1 = T_1[:3, :3] @ (signs * np.asarray(extents_1) / 2).T + T_1[:3, 3:4]
    c2 = T_2[:3, :3] @ (signs * np.asarray(extents_2) / 2).T + T_2[:3, 3:4]
    hi1, lo1, hi2, lo2 = c1.max(axis), c1.min(axis), c2.max(axis), c2.min(axis)
    overlap = np.minimum(hi1, hi2) - np.maximum(lo1, lo2)
    inter = 0.0 if overlap.min() < 0 else float(np.prod(overlap))
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(inter / (np.prod(hi1 - lo1) + np.prod(hi2 - lo2) - inter))


def test_where_the_reference_iou_differs_from_the_exact_one():
    """1. Nested axis-aligned cubes (side 1 and 0.5, both at (1, 1, 1); github.com/hughw19/NOCS_CVPR2019 issue 47):
    exact 1/8; the published code gives NaN (each corner's max - min over x, y, z is 0 for the
    corners on the diagonal, so the union is 0), the fixed axis gives 1/8.
    2. Identical cubes (side 0.2) turned 45 deg about y, 5 cm apart along camera x: exact
    (0.2 - 0.05 / sqrt 2)^2 / (2 (0.2)^2 - (0.2 - 0.05 / sqrt 2)^2) = 0.5125; the fixed axis gives the IoU of the
    camera-axis-aligned boxes, (0.2 sqrt 2 - 0.05) / (0.2 sqrt 2 + 0.05) = 0.6996; the published code 0.830."""
    T = np.eye(4)
    T[:3, 3] = 1.0
    assert math.isnan(published_iou(np.ones(3), T, np.full(3, 0.5), T))
    assert published_iou(np.ones(3), T, np.full(3, 0.5), T, axis=1) == pytest.approx(1 / 8)
    assert box_iou(np.ones(3), T, np.full(3, 0.5), T) == pytest.approx(1 / 8, abs=1e-12)

    A, B = pose((0, 0, 1), about_y(45)), pose((0.05, 0, 1), about_y(45))
    side = 0.2 - 0.05 / math.sqrt(2)
    exact = side**2 / (2 * 0.2**2 - side**2)
    aabb = (0.2 * math.sqrt(2) - 0.05) / (0.2 * math.sqrt(2) + 0.05)
    assert box_iou(CUBE, A, CUBE, B) == pytest.approx(exact, abs=1e-12)
    assert published_iou(CUBE, A, CUBE, B, axis=1) == pytest.approx(aabb, abs=1e-12)
    assert axis_aligned_iou(CUBE, A, CUBE, B) == pytest.approx(aabb, abs=1e-12)
    assert published_iou(CUBE, A, CUBE, B) == pytest.approx(0.8298, abs=1e-4)
    # 3. Symmetric: the reference tries 20 turns of the detection, 18 deg apart; a bottle turned by 9 deg lies
    # between them.  Exact: 1.  The best of the 20 (with the exact IoU per turn) stays below.
    gt, det = pose((0, 0, 1)), pose((0, 0, 1), about_y(9))
    assert symmetric_box_iou(BOX, gt, BOX, det) == pytest.approx(1.0, abs=1e-9)
    turns = [box_iou(BOX, gt, BOX, det @ pose((0, 0, 0), about_y(18 * i))) for i in range(20)]
    assert max(turns) == pytest.approx(0.8397, abs=1e-4)


# --- an independent implementation of the reference on random scenes -------------------------------

def reference_ap(matched: list[bool], scores: list[float], n_gt: int) -> float:
    """compute_ap_from_matches_scores, restated with loops (distinct scores)."""
    order = sorted(range(len(scores)), key=lambda i: -scores[i])
    tp = 0
    precisions, recalls = [0.0], [0.0]
    for k, i in enumerate(order):
        tp += matched[i]
        precisions.append(tp / (k + 1))
        recalls.append(tp / n_gt)
    precisions.append(0.0)
    recalls.append(1.0)
    for k in range(len(precisions) - 2, -1, -1):
        precisions[k] = max(precisions[k], precisions[k + 1])
    return sum((recalls[k] - recalls[k - 1]) * precisions[k] for k in range(1, len(recalls)) if recalls[k] != recalls[k - 1])


def reference_map(gt, dets, iou, degrees, cm, iou_thresholds, pose_thresholds, gate):
    """compute_degree_cm_mAP with compute_3d_matches and compute_match_from_degree_cm, restated with loops over
    the overlaps (iou, degrees, cm: dicts {(det, gt): value} of the pairs in one image and category)."""
    categories = sorted({g[1] for g in gt})
    images = sorted({g[0] for g in gt} | {d[0] for d in dets})
    out_iou, out_pose = [], []
    for c in categories:
        iou_hits = [[] for _ in iou_thresholds]  # per threshold (a list: thresholds may repeat)
        pose_hits = [[] for _ in pose_thresholds]
        iou_scores, pose_scores, n_pose_gt = [], [], 0
        for image in images:
            G = [j for j, g in enumerate(gt) if g[0] == image and g[1] == c]
            D = sorted((i for i, d in enumerate(dets) if d[0] == image and d[1] == c), key=lambda i: -dets[i][2])

            def match_iou(threshold):
                taken, hit = set(), {}
                for i in D:
                    hit[i] = False
                    for j in sorted(G, key=lambda j: -iou[i, j]):
                        if j in taken:
                            continue
                        if iou[i, j] < threshold:
                            break
                        if iou[i, j] > threshold:
                            taken.add(j)
                            hit[i] = True
                            break
                return hit, taken

            for k, t in enumerate(iou_thresholds):
                hit = match_iou(t)[0]
                iou_hits[k] += [hit[i] for i in D]
            iou_scores += [dets[i][2] for i in D]
            if gate is None:
                D_in, G_in = D, G
            else:
                hit, taken = match_iou(gate)
                D_in, G_in = [i for i in D if hit[i]], [j for j in G if j in taken]
            n_pose_gt += len(G_in)
            pose_scores += [dets[i][2] for i in D_in]
            for k, t in enumerate(pose_thresholds):
                taken = set()
                for i in D_in:
                    found = False
                    for j in sorted(G_in, key=lambda j: degrees[i, j] + cm[i, j]):
                        if j in taken or degrees[i, j] > t[0] or cm[i, j] > t[1] * 100:
                            continue
                        taken.add(j)
                        found = True
                        break
                    pose_hits[k].append(found)
        n_gt = sum(1 for g in gt if g[1] == c)
        out_iou.append([reference_ap(hits, iou_scores, n_gt) for hits in iou_hits])
        out_pose.append([reference_ap(hits, pose_scores, n_pose_gt) if n_pose_gt else 0.0 for hits in pose_hits])
    return np.array(out_iou), np.array(out_pose)


def random_scene(rng, images=6):
    """Cameras (asymmetric) and bottles (symmetric) crowded in a few images, detections near them and a few
    stray ones; distinct scores."""
    gt, dets = [], []
    for k in range(images):
        for c in ("camera", "bottle"):
            for _ in range(rng.integers(0, 4)):
                T = pose(rng.uniform(-0.08, 0.08, 3) + [0, 0, 1], Rotation.random(random_state=rng).as_rotvec())
                e = rng.uniform(0.08, 0.2, 3)
                gt.append((f"im{k}", c, T, e))
                for _ in range(rng.integers(0, 3)):
                    noise = pose(rng.normal(0, 0.02, 3), rng.normal(0, math.radians(8), 3))
                    dets.append((f"im{k}", c, None, T @ noise, e * rng.uniform(0.8, 1.25, 3)))
            if rng.random() < 0.3:
                dets.append((f"im{k}", c, None, pose(rng.uniform(-0.1, 0.1, 3) + [0, 0, 1]), rng.uniform(0.08, 0.2, 3)))
    scores = rng.permutation(len(dets)) / len(dets) + 0.01
    return gt, [(d[0], d[1], float(s), d[3], d[4]) for d, s in zip(dets, scores)]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("gate", [0.1, None])
def test_agrees_with_a_loop_implementation_of_the_reference(seed, gate):
    rng = np.random.default_rng(seed)
    gt, dets = random_scene(rng)
    symmetric = nocs_symmetric([g[1] for g in gt])
    config = NocsMapConfig(pose_iou_gate=gate)
    result = run(gt, dets, config, symmetric)
    pairs = candidate_pairs([g[0] for g in gt], [g[1] for g in gt], [d[0] for d in dets], [d[1] for d in dets])
    pairs = pair_errors(pairs, [g[2] for g in gt], [g[3] for g in gt], symmetric, [d[3] for d in dets], [d[4] for d in dets])
    iou = {(i, j): v for i, j, v in zip(pairs.det, pairs.gt, pairs.iou)}
    degrees = {(i, j): v for i, j, v in zip(pairs.det, pairs.gt, pairs.degrees)}
    cm = {(i, j): 100 * v for i, j, v in zip(pairs.det, pairs.gt, pairs.position)}
    assert len(pairs.det) > 10 and 0 < np.mean(pairs.iou > 0.5) < 1  # crowded enough to make matching matter
    iou_thresholds = list(config.iou_thresholds) + list(config.iou_curve[::10])
    pose_thresholds = list(config.pose_thresholds) + [(d, 1.0) for d in (1, 8, 20)] + [(360, p) for p in (0.005, 0.03)]
    ref_iou, ref_pose = reference_map(gt, dets, iou, degrees, cm, iou_thresholds, pose_thresholds, gate)
    assert result.iou_ap == pytest.approx(ref_iou[:, :3], abs=1e-12)
    assert result.curves["iou"][1][:, ::10] == pytest.approx(ref_iou[:, 3:], abs=1e-12)
    assert result.pose_ap == pytest.approx(ref_pose[:, :4], abs=1e-12)
    assert result.curves["degrees"][1][:, [1, 8, 20]] == pytest.approx(ref_pose[:, 4:7], abs=1e-12)
    assert result.curves["position"][1][:, [1, 6]] == pytest.approx(ref_pose[:, 7:], abs=1e-12)


def test_average_precision_agrees_with_the_loop_version():
    rng = np.random.default_rng(11)
    for _ in range(200):
        m = int(rng.integers(0, 30))
        hits = rng.random(m) < rng.random()
        n_gt = int(hits.sum() + rng.integers(0 if hits.sum() else 1, 5))
        scores = rng.permutation(m) + rng.random(m) * 0.5
        assert average_precision(hits, scores, n_gt)[0] == pytest.approx(reference_ap(list(hits), list(scores), n_gt), abs=1e-12)


# --- bad input --------------------------------------------------------------------------------------

def test_bad_input_is_a_value_error():
    ok = dict(gt_image=["A"], gt_category=["camera"], gt_pose=[pose()], gt_extents=[CUBE], gt_symmetric=[False],
              det_image=["A"], det_category=["camera"], det_score=[1.0], det_pose=[pose()], det_extents=[CUBE])
    assert nocs_map(**ok).iou_ap.tolist() == [[1.0, 1.0, 1.0]]
    cases = {
        "det_score": ([float("nan")], "det_score"),
        "det_pose": ([pose() * 2], "det_pose"),
        "gt_extents": ([-CUBE], "negative"),
        "det_image": (["A", "B"], "one entry per box"),
        "gt_pose": ([np.full((4, 4), np.nan)], "NaN"),
    }
    for key, (value, message) in cases.items():
        with pytest.raises(ValueError, match=message):
            nocs_map(**{**ok, key: value})
    from evaluate.metrics.nocs_map import Pairs, nocs_map_from_pairs

    labels = (["A", "B"], ["camera", "camera"], ["A"], ["camera"], [1.0])
    with pytest.raises(ValueError, match="same image and category"):
        nocs_map_from_pairs(Pairs(np.array([0]), np.array([1]), np.ones(1), np.zeros(1), np.zeros(1)), *labels)
    with pytest.raises(ValueError, match="no errors"):
        nocs_map_from_pairs(Pairs(np.array([0]), np.array([0])), *labels)
    with pytest.raises(ValueError, match="finite IoU"):
        nocs_map_from_pairs(Pairs(np.array([0]), np.array([0]), np.full(1, np.nan), np.zeros(1), np.zeros(1)), *labels)
    with pytest.raises(ValueError, match="IoU thresholds"):
        NocsMapConfig(iou_thresholds=(1.5,))
    with pytest.raises(ValueError, match="pose_iou_gate"):
        NocsMapConfig(pose_iou_gate=-0.1)
    with pytest.raises(ValueError, match="finite"):
        average_precision([True], [float("inf")], 1)
    with pytest.raises(ValueError, match="symmetry"):
        nocs_symmetric(["bottle"], ["z"])


# --- evaluate: predictions with scores and categories, results.json, tables, plots ------------------

def _redwood_predictions(redwood75_dir: Path, path: Path) -> dict:
    """Exact predictions for every REDWOOD75 sample (75: 25 bottles, 25 bowls, 25 mugs), except: the mugs of
    the first mug sequence are called bowls (score 0.5), and one bottle frame's prediction is NaN (failed)."""
    from evaluate.datasets.redwood75 import Redwood75Dataset

    data = Redwood75Dataset(redwood75_dir)
    first_mug = next(s.sequence for s in data if s.category == "mug")
    first_bottle = next(s for s in data if s.category == "bottle")
    lines = []
    for s in data:
        entry = {"sequence": s.sequence, "frame": s.frame, "position": s.position.tolist(), "orientation": s.orientation.tolist(), "extents": s.extents.tolist()}
        if s.sequence == first_mug:
            entry.update(category="bowl", score=0.5)
        if s is first_bottle:
            entry["position"] = [float("nan")] * 3
        lines.append(json.dumps(entry).replace("NaN", '"NaN"') if s is first_bottle else json.dumps(entry))
    path.write_text("\n".join(lines) + "\n")
    return {"data": data, "first_mug": first_mug}


def test_evaluate_reports_nocs_map(redwood75_dir, tmp_path):
    """Bottle: 24 exact detections of 25 (one failed): AP = 24/25.  Bowl: 25 exact (score 1) then 5 false
    (the mugs called bowls, 0.5): AP 1.  Mug: 20 of 25 found, all exact: AP 20/25.  The same at every IoU
    threshold (exact poses), so mean = (0.96 + 1 + 0.8) / 3 = 0.92.  Pose AP counts only the pairs matched
    at IoU > 0.1 (NOCS's use_matches_for_pose): the missed boxes and the false bowls drop out, AP 1."""
    from evaluate.cli import main

    predictions = tmp_path / "p.jsonl"
    _redwood_predictions(redwood75_dir, predictions)
    out = tmp_path / "out"
    assert main(["--dataset", str(redwood75_dir), "--method", f"mine={predictions}", "--method", "oracle", "--out", str(out), "--quiet", "--surface-samples", "500"]) == 0
    results = json.loads((out / "results.json").read_text())["methods"]
    nocs = results["mine"]["nocs_map"]
    assert nocs["pose_iou_gate"] == 0.1 and nocs["detections"] == 74 and nocs["ground_truth"] == 75
    assert [e["iou"] for e in nocs["iou"]] == [0.25, 0.5, 0.75]
    assert [(e["degrees"], e["position"]) for e in nocs["pose"]] == [(5.0, 0.02), (5.0, 0.05), (10.0, 0.02), (10.0, 0.05)]
    for entry in nocs["iou"]:
        assert entry["per_category"] == pytest.approx({"bottle": 24 / 25, "bowl": 1.0, "mug": 20 / 25}, abs=1e-12)
        assert entry["mean"] == pytest.approx(0.92, abs=1e-12)
    for entry in nocs["pose"]:
        assert entry["per_category"] == {"bottle": 1.0, "bowl": 1.0, "mug": 1.0} and entry["mean"] == 1.0
    oracle = results["oracle"]["nocs_map"]
    assert all(e["mean"] == 1.0 for e in oracle["iou"] + oracle["pose"])
    # the precision table is unchanged by the detected category (precision compares poses only)
    assert results["mine"]["precision"][0]["per_category"]["mug"] == 1.0

    markdown = (out / "table.md").read_text()
    assert "## NOCS-style mAP (%)" in markdown
    assert "| Method | IoU25 | IoU50 | IoU75 | 5° 2 cm | 5° 5 cm | 10° 2 cm | 10° 5 cm | Detections |" in markdown
    assert "| mine | 92.0 | 92.0 | 92.0 | 100.0 | 100.0 | 100.0 | 100.0 | 74 / 75 |" in markdown
    assert "| mug | mine | 80.0 | 80.0 | 80.0 | 100.0 | 100.0 | 100.0 | 100.0 |" in markdown
    rows = list(csv.DictReader((out / "nocs_map.csv").open()))
    assert len(rows) == 2 * 7 * 4
    mine = {(r["category"], r["label"]): float(r["ap"]) for r in rows if r["method"] == "mine"}
    assert mine[("mean", "IoU50")] == pytest.approx(0.92) and mine[("bottle", "IoU75")] == pytest.approx(0.96) and mine[("bottle", "10° 5 cm")] == 1.0
    curves = json.loads((out / "curves.json").read_text())["nocs_map"]["mine"]
    assert set(curves) == {"iou", "degrees", "position"}
    assert len(curves["iou"]["thresholds"]) == 101 and curves["iou"]["mean"][50] == pytest.approx(0.92)
    assert curves["iou"]["mean"][100] == 0.0  # IoU > 1: nothing
    assert curves["iou"]["per_category"]["mug"][5] == pytest.approx(0.8) and curves["degrees"]["per_category"]["mug"][5] == 1.0
    from PIL import Image

    with Image.open(out / "nocs_map_curves.png") as image:
        assert image.format == "PNG" and image.size[1] > image.size[0] / 2  # two rows of three panels

    # the runner's reuse of each sample's own errors gives what the metric computes from scratch
    from evaluate.runner import nocs_ground_truth

    data = _redwood_predictions(redwood75_dir, tmp_path / "again.jsonl")["data"]
    truth = nocs_ground_truth(data)
    lines = [json.loads(line) for line in predictions.read_text().splitlines()]
    keep = [i for i, e in enumerate(lines) if not isinstance(e["position"][0], str)]
    det_pose = np.array([pose(lines[i]["position"]) for i in keep])
    det_pose[:, :3, :3] = Rotation.from_quat([lines[i]["orientation"] for i in keep]).as_matrix()
    direct = nocs_map(truth["image"], truth["category"], truth["pose"], truth["extents"], truth["symmetric"],
                      truth["image"][keep], [lines[i].get("category", data.samples[i].category) for i in keep],
                      [lines[i].get("score", 1.0) for i in keep], det_pose, [lines[i]["extents"] for i in keep])
    assert direct.iou_ap.mean(axis=0).tolist() == pytest.approx([nocs["iou"][k]["mean"] for k in range(3)], abs=1e-12)


def test_predictions_score_and_category_are_checked(redwood75_dir, tmp_path):
    """A malformed score or category fails that sample, with the reason; old files without them still load."""
    from evaluate.datasets.redwood75 import Redwood75Dataset
    from evaluate.methods import PredictionFailure
    from evaluate.methods.predictions import PredictionsFile

    s = Redwood75Dataset(redwood75_dir).samples[0]
    base = {"sequence": s.sequence, "frame": s.frame, "position": s.position.tolist(), "orientation": s.orientation.tolist(), "extents": s.extents.tolist()}
    for extra, message in (({"score": "high"}, "score must be a finite number"), ({"score": True}, "score must be"),
                           ({"score": 1e400}, "score must be"), ({"category": ""}, "category must be"), ({"category": 3}, "category must be")):
        path = tmp_path / "p.jsonl"
        path.write_text(json.dumps({**base, **extra}).replace("Infinity", "1e400") + "\n")
        with pytest.raises(PredictionFailure, match=message):
            PredictionsFile("p", path).predict(s)
    path.write_text(json.dumps(base) + "\n")
    p = PredictionsFile("p", path).predict(s)
    assert (p.score, p.category) == (1.0, None)
    path.write_text(json.dumps({**base, "score": 0.25, "category": "bowl"}) + "\n")
    p = PredictionsFile("p", path).predict(s)
    assert (p.score, p.category) == (0.25, "bowl")


def test_nocs_reader_takes_the_handle_visibility(nocs_dir, tmp_path):
    """gt_handle_visibility of a results pickle (when present) reaches the mug's sample, and a hidden handle
    makes NOCS's symmetric flag; a malformed one is a one-line error naming the pickle."""
    from evaluate.datasets.nocs import NocsDataset
    from evaluate.runner import nocs_ground_truth
    from sequences.errors import InputError

    root = tmp_path / "nocs"
    shutil.copytree(nocs_dir, root)
    before = NocsDataset(root)
    assert all(s.handle_visible is None for s in before)
    gts = sorted((root / "gts").glob("*/*.pkl"))
    mug_frames = {s.sequence.split("/")[0] + "_" + s.sequence.split("/")[1] + "_" + s.frame for s in before if s.category == "mug"}
    target = next(p for p in gts if any(p.stem.endswith(f) for f in mug_frames))
    data = pickle.loads(target.read_bytes())
    n = len(data["gt_RTs"])
    data["gt_handle_visibility"] = np.zeros(n, dtype=np.int64)
    target.write_bytes(pickle.dumps(data))
    after = NocsDataset(root)
    frame = [s for s in after if target.stem.endswith(s.sequence.replace("/", "_") + "_" + s.frame)]
    assert len(frame) == n and all(s.handle_visible is False for s in frame)
    truth = nocs_ground_truth(after)
    for s, flag in zip(after, truth["symmetric"]):
        assert flag == (s.symmetry == "y" or (s.category == "mug" and s.handle_visible is False))
    assert any(s.category == "mug" and s.handle_visible is False for s in after)
    data["gt_handle_visibility"] = np.zeros(n + 1)
    target.write_bytes(pickle.dumps(data))
    with pytest.raises(InputError, match="gt_handle_visibility") as error:
        NocsDataset(root)
    assert target.name in str(error.value) and "\n" not in str(error.value)


def test_several_objects_per_image_on_the_nocs_sample(nocs_dir, tmp_path):
    """The NOCS sample has several objects per frame: the exact oracle gets AP 1 everywhere."""
    from evaluate.cli import main

    out = tmp_path / "out"
    assert main(["--dataset", str(nocs_dir), "--method", "oracle", "--out", str(out), "--quiet", "--surface-samples", "300"]) == 0
    nocs = json.loads((out / "results.json").read_text())["methods"]["oracle"]["nocs_map"]
    assert all(e["mean"] == 1.0 for e in nocs["iou"] + nocs["pose"])
    assert nocs["detections"] == nocs["ground_truth"] == 5
