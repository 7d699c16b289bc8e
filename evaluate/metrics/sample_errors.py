"""All errors of one or N samples at once: ground truth and prediction in, :class:`SampleErrors` out.

Ground truth (must be well formed; ValueError otherwise): position (3,) m in the camera frame,
orientation (4,) quaternion x y z w (object to camera, ShapeNet object axes), extents (3,) full box
side lengths m, symmetry "none" or "y", and optionally a :class:`ShapeIndex` of its mesh (object frame).

Prediction, per sample, same conventions; any part may be missing (None).  A prediction with a missing
pose, NaN/inf, a wrong shape, negative extents, a quaternion whose norm is off 1 by more than
``QUATERNION_TOLERANCE``, or malformed reconstruction points is *failed*: all its errors are NaN, it is
never correct, and the reason is recorded in ``SampleErrors.failure``.  A prediction without extents
has IoU NaN; without reconstruction points, F-score (and chamfer) NaN.

F-score and chamfer compare the POSED shapes, as cpas_toolbox's evaluation does (its correctness
metrics call ``_get_points(..., posed=True)``): the prediction's points are mapped by its pose and the
ground-truth points by the true pose.  Distances are rigid-invariant, so we map the predicted points
into the ground-truth object frame instead and reuse the object's KD-tree.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from evaluate.metrics import _validate
from evaluate.metrics.box_iou import box_iou_batch, symmetric_box_iou_batch
from evaluate.metrics.pose_errors import rotation_error
from evaluate.metrics.precision import DEFAULT_FSCORE_DISTANCE, SampleErrors
from evaluate.metrics.sampling import ShapeIndex
from evaluate.metrics.shape_metrics import chamfer_from_distances, fscore_from_distances, fscore_from_hits

#: A predicted quaternion whose norm differs from 1 by more than this is malformed.
QUATERNION_TOLERANCE = 1e-3


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions x y z w to (N, 3, 3) rotation matrices."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def _per_sample(value, n: int, single: bool) -> list:
    """A per-sample list from a single value (single sample) or a sequence/array of N values."""
    if single:
        return [value]
    if value is None:
        return [None] * n
    items = list(value)
    if len(items) != n:
        raise ValueError(f"expected {n} per-sample values, got {len(items)}")
    return items


def _check_vector(value, size: int, what: str) -> tuple[np.ndarray | None, str | None]:
    if value is None:
        return None, f"missing {what}"
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None, f"{what} is not numeric"
    if a.shape != (size,):
        return None, f"{what} has shape {a.shape}, expected ({size},)"
    if not np.all(np.isfinite(a)):
        return None, f"{what} contains NaN or inf"
    return a, None


def _check_points(value) -> tuple[np.ndarray | None, str | None]:
    if value is None:
        return None, None
    try:
        p = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None, "reconstruction points are not numeric"
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        return None, f"reconstruction points have shape {p.shape}, expected (M, 3) with M >= 1"
    if not np.all(np.isfinite(p)):
        return None, "reconstruction points contain NaN or inf"
    return p, None


def compute_sample_errors(
    gt_position,
    gt_orientation,
    gt_extents,
    gt_symmetry="none",
    gt_shape: ShapeIndex | Sequence[ShapeIndex | None] | None = None,
    pred_position=None,
    pred_orientation=None,
    pred_extents=None,
    pred_points=None,
    *,
    fscore_threshold: float = DEFAULT_FSCORE_DISTANCE,
    compute_iou: bool = True,
    compute_chamfer: bool = False,
) -> SampleErrors:
    """Errors of one sample (gt_position (3,)) or N samples (gt_position (N, 3); per-sample sequences).

    Position error m, rotation error degrees (about y for symmetric samples), IoU (exact oriented box;
    the exact symmetric maximum for symmetric samples) and F-score at ``fscore_threshold`` m, plus the
    chamfer distance if ``compute_chamfer``.  See the module docstring for failed predictions.
    """
    gp = _validate.finite_array(gt_position, "gt_position", (3,))
    single = gp.ndim == 1
    gp = gp.reshape(-1, 3)
    n = len(gp)
    gq = _validate.finite_array(gt_orientation, "gt_orientation", (4,)).reshape(-1, 4)
    ge = _validate.extents(gt_extents, "gt_extents").reshape(-1, 3)
    if len(gq) != n or len(ge) != n:
        raise ValueError("ground truth position, orientation and extents must have the same length")
    if np.any(np.abs(np.linalg.norm(gq, axis=1) - 1) > QUATERNION_TOLERANCE):
        raise ValueError("gt_orientation: not a unit quaternion")
    gq = gq / np.linalg.norm(gq, axis=1, keepdims=True)
    sym = [gt_symmetry] * n if isinstance(gt_symmetry, str) or gt_symmetry is None else list(gt_symmetry)
    if len(sym) != n:
        raise ValueError(f"gt_symmetry: expected {n} values")
    sym = np.array([_validate.symmetry(s) == "y" for s in sym])
    shapes = [gt_shape] * n if (gt_shape is None or isinstance(gt_shape, ShapeIndex)) else list(gt_shape)
    if len(shapes) != n:
        raise ValueError(f"gt_shape: expected {n} values")
    if not np.isfinite(fscore_threshold) or fscore_threshold <= 0:
        raise ValueError(f"fscore_threshold must be a positive distance in metres, got {fscore_threshold}")

    positions, orientations, extents, points = (_per_sample(v, n, single) for v in (pred_position, pred_orientation, pred_extents, pred_points))
    failure: list[str | None] = [None] * n
    pp, pq, pe = np.full((n, 3), np.nan), np.full((n, 4), np.nan), np.full((n, 3), np.nan)
    pts: list[np.ndarray | None] = [None] * n
    for i in range(n):  # validation only; the metrics below are vectorised across samples
        problems = []
        p, why = _check_vector(positions[i], 3, "position")
        problems.append(why)
        q, why = _check_vector(orientations[i], 4, "orientation")
        if q is not None and abs(np.linalg.norm(q) - 1) > QUATERNION_TOLERANCE:
            q, why = None, f"orientation is not a unit quaternion (norm {np.linalg.norm(q):.6g})"
        problems.append(why)
        if extents[i] is not None:
            e, why = _check_vector(extents[i], 3, "extents")
            if e is not None and np.any(e < 0):
                e, why = None, "negative extents"
            problems.append(why)
            if e is not None:
                pe[i] = e
        pts[i], why = _check_points(points[i])
        problems.append(why)
        problems = [w for w in problems if w]
        if problems:
            failure[i] = "; ".join(problems)
        else:
            pp[i], pq[i] = p, q / np.linalg.norm(q)
    failed = np.array([f is not None for f in failure])
    pe[failed] = np.nan
    ok = ~failed

    position_error = np.full(n, np.nan)
    rot_error = np.full(n, np.nan)
    iou = np.full(n, np.nan)
    fscore = np.full(n, np.nan)
    chamfer = np.full(n, np.nan)
    Rg = _quat_to_matrix(gq)
    Rp = np.full((n, 3, 3), np.nan)
    if np.any(ok):
        Rp[ok] = _quat_to_matrix(pq[ok])
        position_error[ok] = np.linalg.norm(gp[ok] - pp[ok], axis=1)
        for flag, mode in ((False, "none"), (True, "y")):
            rows = ok & (sym == flag)
            if np.any(rows):
                rot_error[rows] = rotation_error(Rg[rows], Rp[rows], symmetry=mode)

    if compute_iou:
        Tg = np.tile(np.eye(4), (n, 1, 1))
        Tg[:, :3, :3], Tg[:, :3, 3] = Rg, gp
        Tp = np.tile(np.eye(4), (n, 1, 1))
        Tp[ok, :3, :3], Tp[ok, :3, 3] = Rp[ok], pp[ok]
        has_box = ok & np.all(np.isfinite(pe), axis=1)
        for flag in (False, True):
            rows = has_box & (sym == flag)
            if np.any(rows):
                fn = symmetric_box_iou_batch if flag else box_iou_batch
                iou[rows] = fn(ge[rows], Tg[rows], pe[rows], Tp[rows])

    for i in np.nonzero(ok)[0]:  # one KD-tree per predicted shape: inherently per sample
        if pts[i] is None or shapes[i] is None:
            continue
        # predicted object frame -> camera -> ground-truth object frame
        cam = pts[i] @ Rp[i].T + pp[i]
        in_gt = (cam - gp[i]) @ Rg[i]
        if compute_chamfer:  # full distances needed
            d_gt_to_pred, d_pred_to_gt = shapes[i].distances(in_gt)
            fscore[i] = fscore_from_distances(d_gt_to_pred, d_pred_to_gt, fscore_threshold).fscore
            chamfer[i] = chamfer_from_distances(d_gt_to_pred, d_pred_to_gt)
        else:
            fscore[i] = fscore_from_hits(*shapes[i].hits(in_gt, fscore_threshold)).fscore
    return SampleErrors(position_error, rot_error, iou, fscore, failed, chamfer, failure)
