"""Shape metrics on point sets: chamfer distance and F-score (metres; both point sets in one frame).

Definitions (those of cpas_toolbox 1.0.0 ``metrics.py``, which the REDWOOD75 paper's evaluation uses):

* ``chamfer_distance`` (cpas_toolbox: ``symmetric_chamfer``): the MEAN of the two directed mean
  nearest-neighbour distances,  (mean_a min_b |a - b| + mean_b min_a |a - b|) / 2.  Not the sum.
* ``squared_chamfer_distance``: the same with squared distances,
  (mean_a min_b |a - b|^2 + mean_b min_a |a - b|^2) / 2 (m^2).
* ``fscore``: precision = fraction of predicted points whose nearest ground-truth point is closer than
  ``threshold`` (strictly), recall = the same from ground truth to prediction, F = their harmonic mean,
  0 when either is below 1e-7.

Both depend on how many points are sampled from a mesh (see :mod:`evaluate.metrics.sampling`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from evaluate.metrics import _validate


class FScore(NamedTuple):
    """F-score at a distance threshold, with its precision and recall (all in [0, 1])."""

    fscore: float
    precision: float
    recall: float


def points_array(points, name: str) -> np.ndarray:
    """(N, 3) finite float64 points with N >= 1; ValueError otherwise."""
    p = _validate.finite_array(points, name, (3,))
    if p.ndim != 2 or len(p) == 0:
        raise ValueError(f"{name}: expected a non-empty (N, 3) point array, got shape {p.shape}")
    return p


def nearest_distances(points_from: np.ndarray, tree_to: cKDTree, upper_bound: float = np.inf, workers: int = 1) -> np.ndarray:
    """Distance from each of ``points_from`` to its nearest point in ``tree_to`` (inf beyond ``upper_bound``)."""
    d, _ = tree_to.query(points_from, k=1, distance_upper_bound=upper_bound, workers=workers)
    return d


def chamfer_from_distances(d_gt_to_pred: np.ndarray, d_pred_to_gt: np.ndarray, squared: bool = False) -> float:
    """Chamfer distance from the two directed nearest-neighbour distance arrays (see module doc)."""
    if squared:
        return float((np.mean(d_gt_to_pred**2) + np.mean(d_pred_to_gt**2)) / 2)
    # Same operation order as cpas_toolbox (completeness + accuracy) / 2, so results agree bit for bit.
    return float((np.mean(d_gt_to_pred) + np.mean(d_pred_to_gt)) / 2)


def fscore_from_distances(d_gt_to_pred: np.ndarray, d_pred_to_gt: np.ndarray, threshold: float) -> FScore:
    """F-score from the two directed nearest-neighbour distance arrays (strict ``< threshold``)."""
    return fscore_from_hits(d_gt_to_pred < threshold, d_pred_to_gt < threshold)


def fscore_from_hits(gt_hit: np.ndarray, pred_hit: np.ndarray) -> FScore:
    """F-score from booleans: gt points with a predicted point within the threshold, and vice versa."""
    # Same arithmetic as cpas_toolbox (count / n, then 2 / (1/r + 1/p)), so results agree bit for bit.
    recall = np.sum(gt_hit) / gt_hit.shape[0]
    precision = np.sum(pred_hit) / pred_hit.shape[0]
    if recall < 1e-7 or precision < 1e-7:
        return FScore(0.0, float(precision), float(recall))
    return FScore(float(2 / (1 / recall + 1 / precision)), float(precision), float(recall))


def chamfer_distance(points_a, points_b, squared: bool = False) -> float:
    """Symmetric chamfer distance (m), the mean of both directed mean NN distances; m^2 if ``squared``."""
    a, b = points_array(points_a, "points_a"), points_array(points_b, "points_b")
    return chamfer_from_distances(nearest_distances(a, cKDTree(b)), nearest_distances(b, cKDTree(a)), squared)


def squared_chamfer_distance(points_a, points_b) -> float:
    """Symmetric chamfer distance with squared NN distances (m^2): ``chamfer_distance(..., squared=True)``."""
    return chamfer_distance(points_a, points_b, squared=True)


def fscore(points_gt, points_pred, threshold: float = 0.01) -> FScore:
    """F-score (with precision and recall) of predicted points against ground-truth points at ``threshold`` m."""
    if not np.isfinite(threshold) or threshold <= 0:
        raise ValueError(f"fscore: threshold must be a positive distance in metres, got {threshold}")
    from evaluate.metrics.sampling import ShapeIndex  # here: sampling builds on this module

    # Only which distances fall below the threshold matters: ShapeIndex.hits decides most points on a
    # grid and bounds the KD-tree queries of the rest, with exactly the result of the distance test.
    gt, pred = points_array(points_gt, "points_gt"), points_array(points_pred, "points_pred")
    return fscore_from_hits(*ShapeIndex(gt).hits(pred, threshold))
