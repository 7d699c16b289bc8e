"""NOCS-style mean average precision: detections with a category and a score, matched to the ground
truth by 3D IoU, and AP per category at IoU thresholds and at (degrees, cm) pose thresholds.

The definitions follow the reference evaluation, hughw19/NOCS_CVPR2019 ``utils.py``
(``compute_degree_cm_mAP`` with ``compute_3d_matches``, ``compute_RT_degree_cm_symmetry``,
``compute_match_from_degree_cm`` and ``compute_ap_from_matches_scores``), called as its
``detect_eval.py`` calls it (``use_matches_for_pose=True, iou_pose_thres=0.1``):

* Per image and category.  Detections go in decreasing score; each takes, among the ground-truth boxes of
  its image and category not yet taken, the one with the largest IoU, if that IoU is strictly above the
  threshold (the reference skips taken boxes and stops at the first IoU below the threshold; an IoU
  equal to it never matches).  Every IoU threshold is matched separately.
* Pose: only the detections and ground-truth boxes matched at IoU > ``pose_iou_gate`` (0.1) take part
  (``use_matches_for_pose``; None: all).  Each detection, in decreasing score, takes the untaken box of
  its image and category with the smallest ``degrees + centimetres`` whose rotation error is <= the
  degree threshold and translation error <= the cm threshold (non-strict, as the reference).
* Symmetric handling: a ground-truth box is symmetric when its symmetry label is ``y`` (which REDWOOD75
  and our documents default from :data:`sequences.annotation.SYMMETRIC_CATEGORIES`: bottle, bowl, can)
  or it is a mug whose handle is not visible (:func:`nocs_symmetric`).  For symmetric boxes the rotation
  error is the angle between the two y axes, and the IoU is the maximum over rotations of the detection
  about its own y axis.
* AP (``compute_ap_from_matches_scores``): the detections of a category over all images, in decreasing
  score; precision = TP / detections so far, recall = TP / ground truth; padded with (recall 0,
  precision 0) before and (recall 1, precision 0) after; precision replaced by its maximum over all
  later points (VOC's envelope); AP = sum over points of (recall step) x (enveloped precision), i.e.
  the all-point interpolated area.  The mean is over the categories that have ground truth.

Where ours differs from the reference (each on purpose; the tests compare both on hand-computed cases):

* IoU: exact oriented-box IoU (:mod:`evaluate.metrics.box_iou`) and, for symmetric boxes, its exact
  maximum over the rotation about y.  The reference's ``compute_3d_iou_new`` maps the 8 corners into the
  camera frame and takes ``np.amax(bbox_3d, axis=0)`` of the (3, 8) corner array, i.e. per corner the
  largest of its x, y, z coordinates, and multiplies 8 such "extents": not a volume, not even of the
  axis-aligned boxes (copies that fixed the axis, e.g. Wild6D, get the IoU of the camera-axis-aligned
  bounding boxes, :func:`evaluate.metrics.box_iou.axis_aligned_iou`, which still depends on the camera's
  orientation).  For symmetric boxes it tries 20 rotations of the detection, 18 degrees apart.  It stores
  the IoUs as float32.
* Rotation error: ``atan2`` (accurate near 0 and 180 degrees, never NaN); the reference's ``arccos`` of an
  unclamped cosine gives NaN for near-identical rotations, and a NaN error passes every pose threshold
  there (``NaN > threshold`` is False).
* Ties in score: the reference orders equal scores as ``np.argsort(...)[::-1]`` happens to (not a stable
  sort on large arrays, so the AP of tied detections depends on the machine).  Ours counts tied
  detections as one operating point (precision and recall after all of them), so the AP does not depend
  on the order; with distinct scores the two agree exactly.  Within an image, tied detections are matched
  in input order.  Ties in IoU go to the later ground-truth box and ties in degrees + cm to the earlier
  one, as the reference's sorts do on small arrays (insertion sort, stable).
* Recall is float64 (the reference casts it to float32: differences ~1e-8).
* A category without ground truth is left out (the reference's AP is NaN there, and so is its mean);
  detections of such a category are counted in :attr:`NocsMapResult.ignored`.

Units and frames: poses are 4x4 object-to-camera transforms (metres, OpenCV camera), boxes are centred
on the object origin with full side lengths ``extents`` (m); rotation errors in degrees, translation
errors and thresholds in metres (shown in cm, as NOCS does).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from evaluate.metrics import _validate
from evaluate.metrics.box_iou import box_iou_batch, symmetric_box_iou_batch
from evaluate.metrics.pose_errors import rotation_error
from sequences.annotation import SYMMETRIC_CATEGORIES

#: NOCS's one category-specific rule beyond the symmetric categories: a mug whose handle is not visible
#: counts as symmetric about y (reference: ``class_name == 'mug' and handle_visibility == 0``).
HANDLE_CATEGORY = "mug"
#: The "unbounded" other threshold of NOCS's degree and cm curves (it appends 360 degrees and 100 cm).
UNBOUNDED_DEGREES = 360.0
UNBOUNDED_POSITION = 1.0  # m


@dataclass(frozen=True)
class NocsMapConfig:
    """What NOCS-style mAP is reported at; the defaults are the field's tables and NOCS's curves."""

    iou_thresholds: tuple[float, ...] = (0.25, 0.5, 0.75)  # 3D IoU (matched when IoU > threshold)
    pose_thresholds: tuple[tuple[float, float], ...] = ((5.0, 0.02), (5.0, 0.05), (10.0, 0.02), (10.0, 0.05))  # (degrees, m)
    pose_iou_gate: float | None = 0.1  # pose AP over the pairs matched at IoU > this (NOCS detect_eval.py); None: all
    # Curves (NOCS detect_eval.py: np.linspace(0, 1, 101) IoU, range(0, 61) degrees, np.linspace(0, 1, 31) * 15 cm);
    # the degree curve at translation <= 1 m, the translation curve at rotation <= 360 degrees, as NOCS plots them.
    iou_curve: tuple[float, ...] = tuple(np.round(np.linspace(0.0, 1.0, 101), 6).tolist())
    degree_curve: tuple[float, ...] = tuple(float(d) for d in range(0, 61))
    position_curve: tuple[float, ...] = tuple(np.round(np.linspace(0.0, 0.15, 31), 6).tolist())  # m

    def __post_init__(self) -> None:
        for name in ("iou_thresholds", "iou_curve"):
            values = np.asarray(getattr(self, name), dtype=np.float64)
            if values.ndim != 1 or not np.all(np.isfinite(values)) or np.any((values < 0) | (values > 1)):
                raise ValueError(f"NocsMapConfig.{name}: IoU thresholds must be numbers in [0, 1]")
        pose = np.asarray(self.pose_thresholds, dtype=np.float64).reshape(-1, 2) if len(self.pose_thresholds) else np.zeros((0, 2))
        for name, values in (("pose_thresholds", pose.ravel()), ("degree_curve", self.degree_curve), ("position_curve", self.position_curve)):
            values = np.asarray(values, dtype=np.float64)
            if not np.all(np.isfinite(values)) or np.any(values < 0):
                raise ValueError(f"NocsMapConfig.{name}: thresholds must be non-negative numbers")
        if self.pose_iou_gate is not None and not (0 <= self.pose_iou_gate <= 1):
            raise ValueError(f"NocsMapConfig.pose_iou_gate must be in [0, 1] or None, got {self.pose_iou_gate!r}")


@dataclass
class Pairs:
    """Candidate (detection, ground truth) pairs: same image, same category; errors per pair."""

    det: np.ndarray  # (P,) detection index
    gt: np.ndarray  # (P,) ground-truth index
    iou: np.ndarray | None = None  # (P,) 3D IoU (symmetric maximum for symmetric ground truth)
    degrees: np.ndarray | None = None  # (P,) rotation error, degrees (about y ignored when symmetric)
    position: np.ndarray | None = None  # (P,) translation error, m


@dataclass
class NocsMapResult:
    """AP per category (rows, in ``categories`` order) and their mean; NaN where undefined."""

    categories: list[str]
    iou_thresholds: np.ndarray  # (K,)
    iou_ap: np.ndarray  # (C, K)
    pose_thresholds: np.ndarray  # (Q, 2) degrees, m
    pose_ap: np.ndarray  # (C, Q)
    curves: dict[str, tuple[np.ndarray, np.ndarray]]  # "iou" | "degrees" | "position" -> (grid (n,), AP (C, n))
    detections: int  # detections counted (their category has ground truth)
    ground_truth: int
    ignored: int = 0  # detections of categories without ground truth
    config: NocsMapConfig = field(default_factory=NocsMapConfig)

    @staticmethod
    def mean(ap: np.ndarray) -> np.ndarray:
        """Mean over categories (rows) of an AP array; NaN without categories."""
        return ap.mean(axis=0) if len(ap) else np.full(ap.shape[1:], np.nan)


def nocs_symmetric(categories, symmetry=None, handle_visible=None) -> np.ndarray:
    """(N,) bool: which ground-truth boxes NOCS treats as symmetric about y.

    ``symmetry``: per box "y" / "none" labels (None: by category, :data:`SYMMETRIC_CATEGORIES`);
    ``handle_visible``: per box True / False / None (None = unknown, taken as visible, as the reference
    does when a results file lacks ``gt_handle_visibility``).  A mug whose handle is not visible is symmetric.
    """
    categories = np.asarray(categories, dtype=object).reshape(-1)
    n = len(categories)
    if symmetry is None:
        symmetric = np.isin(categories, list(SYMMETRIC_CATEGORIES))
    else:
        labels = [_validate.symmetry(s) for s in symmetry]
        if len(labels) != n:
            raise ValueError(f"symmetry: expected {n} labels, got {len(labels)}")
        symmetric = np.array([s == "y" for s in labels], dtype=bool).reshape(n)
    if handle_visible is not None:
        visible = list(handle_visible)
        if len(visible) != n:
            raise ValueError(f"handle_visible: expected {n} values, got {len(visible)}")
        hidden = np.array([v is not None and not bool(v) for v in visible], dtype=bool).reshape(n)
        symmetric = symmetric | ((categories == HANDLE_CATEGORY) & hidden)
    return symmetric


def _labels(value, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=object)
    if array.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D sequence of labels, got shape {array.shape}")
    return array


def _codes(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Integer codes of two label arrays over their joint set of values."""
    joint = np.concatenate([a, b]).astype(str)
    values, inverse = np.unique(joint, return_inverse=True)
    return inverse[: len(a)], inverse[len(a):], len(values)


def candidate_pairs(gt_image, gt_category, det_image, det_category) -> Pairs:
    """Every (detection, ground truth) pair in the same image with the same category (no errors yet)."""
    gi, di = _labels(gt_image, "gt_image"), _labels(det_image, "det_image")
    gc, dc = _labels(gt_category, "gt_category"), _labels(det_category, "det_category")
    if len(gi) != len(gc) or len(di) != len(dc):
        raise ValueError("image and category labels must have one entry per box")
    g_img, d_img, _ = _codes(gi, di)
    g_cat, d_cat, n_cat = _codes(gc, dc)
    g_key, d_key = g_img * n_cat + g_cat, d_img * n_cat + d_cat
    order = np.argsort(g_key, kind="stable")
    lo = np.searchsorted(g_key[order], d_key, side="left")
    counts = np.searchsorted(g_key[order], d_key, side="right") - lo
    det = np.repeat(np.arange(len(di)), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    gt = order[np.repeat(lo, counts) + offsets]
    return Pairs(det.astype(np.int64), gt.astype(np.int64))


def pair_errors(pairs: Pairs, gt_pose, gt_extents, gt_symmetric, det_pose, det_extents) -> Pairs:
    """Fill in IoU, rotation error (degrees) and translation error (m) of every pair (vectorised).

    Poses (N, 4, 4) / (M, 4, 4) object to camera; extents (N, 3) / (M, 3) full side lengths, m;
    ``gt_symmetric`` (N,) bool (see :func:`nocs_symmetric`).  ValueError on malformed input.
    """
    Tg = _validate.rigid_transforms(gt_pose, "gt_pose").reshape(-1, 4, 4)
    Td = _validate.rigid_transforms(det_pose, "det_pose").reshape(-1, 4, 4)
    eg = _validate.extents(gt_extents, "gt_extents").reshape(-1, 3)
    ed = _validate.extents(det_extents, "det_extents").reshape(-1, 3)
    sym = np.asarray(gt_symmetric, dtype=bool).reshape(-1)
    if len(eg) != len(Tg) or len(sym) != len(Tg) or len(ed) != len(Td):
        raise ValueError("poses, extents and symmetry flags must have one entry per box")
    d, g = pairs.det, pairs.gt
    s = sym[g]
    iou = np.zeros(len(d))
    degrees = np.zeros(len(d))
    for flag, iou_fn, mode in ((False, box_iou_batch, "none"), (True, symmetric_box_iou_batch, "y")):
        rows = s == flag
        if np.any(rows):
            iou[rows] = iou_fn(eg[g[rows]], Tg[g[rows]], ed[d[rows]], Td[d[rows]])
            degrees[rows] = rotation_error(Tg[g[rows], :3, :3], Td[d[rows], :3, :3], symmetry=mode)
    position = np.linalg.norm(Tg[g, :3, 3] - Td[d, :3, 3], axis=1)
    return Pairs(d, g, iou, degrees, position)


def _layout(gt_group_of: np.ndarray, det_group: np.ndarray, det_score: np.ndarray, n_gt: int):
    """Padded per-group tensors: the detections of each (image, category) group in decreasing score
    (ties in input order), its ground truth in input order.  Returns (det_at (G, D), gt_at (G, H),
    det_rank (M,), gt_col (N,)), -1 where padded."""
    m = len(det_group)
    groups = int(det_group.max()) + 1 if m else 0
    order = np.lexsort((np.arange(m), -det_score, det_group))
    first = np.searchsorted(det_group[order], det_group[order], side="left")
    det_rank = np.empty(m, dtype=np.int64)
    det_rank[order] = np.arange(m) - first
    width = int(det_rank.max()) + 1 if m else 0
    det_at = np.full((groups, width), -1, dtype=np.int64)
    det_at[det_group, det_rank] = np.arange(m)
    in_group = gt_group_of >= 0
    g_idx = np.nonzero(in_group)[0]
    g_order = g_idx[np.lexsort((g_idx, gt_group_of[g_idx]))]
    g_first = np.searchsorted(gt_group_of[g_order], gt_group_of[g_order], side="left")
    gt_col = np.full(n_gt, -1, dtype=np.int64)
    gt_col[g_order] = np.arange(len(g_order)) - g_first
    height = int(gt_col.max()) + 1 if len(g_order) else 0
    gt_at = np.full((groups, height), -1, dtype=np.int64)
    gt_at[gt_group_of[g_order], gt_col[g_order]] = g_order
    return det_at, gt_at, det_rank, gt_col


def _greedy(det_at: np.ndarray, gt_at: np.ndarray, key: np.ndarray, allowed, t: int, largest: bool, n_det: int, n_gt: int):
    """NOCS's greedy matching for T thresholds at once.

    key (G, D, H) per pair (NaN: no pair); allowed(k) -> (T, G, H) bool: which pairs of rank-k detections
    meet each threshold.  Rank by rank (decreasing score), each detection takes the untaken allowed box
    with the largest (``largest``) or smallest key.  Returns det_match (T, M) ground-truth index or -1
    and gt_taken (T, N) bool.
    """
    groups, depth = det_at.shape
    height = gt_at.shape[1]
    det_match = np.full((t, n_det), -1, dtype=np.int64)
    taken = np.zeros((t, groups, height), dtype=bool)
    if height == 0 or depth == 0:
        return det_match, np.zeros((t, n_gt), dtype=bool)
    fill = -np.inf if largest else np.inf
    for k in range(depth):  # ranks within a group: as many as the most detections one image has of one category
        ok = allowed(k) & ~taken
        value = np.where(ok, key[None, :, k, :], fill)
        if largest:  # ties to the later box, as the reference's np.argsort(...)[::-1]
            col = height - 1 - np.argmax(value[..., ::-1], axis=-1)
        else:  # ties to the earlier box, as its np.argsort(...)
            col = np.argmin(value, axis=-1)
        has = ok.any(axis=-1) & (det_at[None, :, k] >= 0)
        ti, gi = np.nonzero(has)
        taken[ti, gi, col[ti, gi]] = True
        det_match[ti, det_at[gi, k]] = gt_at[gi, col[ti, gi]]
    gt_taken = np.zeros((t, n_gt), dtype=bool)
    ti, gi, hi = np.nonzero(taken)
    gt_taken[ti, gt_at[gi, hi]] = True
    return det_match, gt_taken


def average_precision(tp, scores, n_gt) -> np.ndarray:
    """NOCS's AP (``compute_ap_from_matches_scores``) of T match rows at once.

    tp (T, M) bool: detection matched under each threshold; scores (M,); n_gt (T,) or scalar ground-truth
    count.  Tied scores form one operating point (see the module docstring).  Returns (T,); NaN where
    there is no ground truth but there are detections (0/0 recall), 0 with neither.
    """
    tp = np.atleast_2d(np.asarray(tp, dtype=bool))
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if tp.shape[1] != len(scores):
        raise ValueError(f"average_precision: {tp.shape[1]} matches but {len(scores)} scores")
    if not np.all(np.isfinite(scores)):
        raise ValueError("average_precision: scores must be finite")
    n_gt = np.broadcast_to(np.asarray(n_gt, dtype=np.float64), (tp.shape[0],))
    order = np.argsort(-scores, kind="stable")
    s = scores[order]
    cum = np.cumsum(tp[:, order], axis=1)
    ends = np.nonzero(np.r_[s[1:] != s[:-1], True])[0] if len(s) else np.zeros(0, dtype=np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = cum[:, ends] / (ends + 1.0)
        recall = cum[:, ends] / n_gt[:, None]
    t = tp.shape[0]
    precision = np.concatenate([np.zeros((t, 1)), precision, np.zeros((t, 1))], axis=1)
    recall = np.concatenate([np.zeros((t, 1)), recall, np.ones((t, 1))], axis=1)
    envelope = np.maximum.accumulate(precision[:, ::-1], axis=1)[:, ::-1]
    ap = np.sum((recall[:, 1:] - recall[:, :-1]) * envelope[:, 1:], axis=1)
    return np.where((n_gt == 0) & (len(s) > 0), np.nan, ap)


def nocs_map_from_pairs(pairs: Pairs, gt_image, gt_category, det_image, det_category, det_score,
                        config: NocsMapConfig = NocsMapConfig()) -> NocsMapResult:
    """NOCS-style AP from candidate pairs with their errors (see :func:`candidate_pairs`, :func:`pair_errors`)."""
    gi, gc = _labels(gt_image, "gt_image"), _labels(gt_category, "gt_category")
    di, dc = _labels(det_image, "det_image"), _labels(det_category, "det_category")
    score = _validate.finite_array(det_score, "det_score", ()).reshape(-1)
    n, m = len(gi), len(di)
    if len(gc) != n or len(dc) != m or len(score) != m:
        raise ValueError("labels and scores must have one entry per box")
    if pairs.iou is None or pairs.degrees is None or pairs.position is None:
        raise ValueError("pairs have no errors: call pair_errors first")
    # groups: the (image, category) of each detection; ground truth outside them is never matched
    g_img, d_img, _ = _codes(gi, di)
    g_cat, d_cat, n_cat = _codes(gc, dc)
    d_key, g_key = d_img * n_cat + d_cat, g_img * n_cat + g_cat
    keys, det_group = np.unique(d_key, return_inverse=True)
    det_group = det_group.reshape(-1)
    gt_group_of = np.full(n, -1, dtype=np.int64)
    if len(keys):
        at = np.minimum(np.searchsorted(keys, g_key), len(keys) - 1)
        gt_group_of = np.where(keys[at] == g_key, at, -1)
    pd, pg = np.asarray(pairs.det, dtype=np.int64).reshape(-1), np.asarray(pairs.gt, dtype=np.int64).reshape(-1)
    errors = [np.asarray(v, dtype=np.float64).reshape(-1) for v in (pairs.iou, pairs.degrees, pairs.position)]
    if len(pg) != len(pd) or any(len(v) != len(pd) or not np.all(np.isfinite(v)) for v in errors):
        raise ValueError("pairs: one finite IoU, rotation and translation error per (detection, ground truth) pair")
    if len(pd) and (pd.min() < 0 or pd.max() >= m or pg.min() < 0 or pg.max() >= n or np.any(gt_group_of[pg] != det_group[pd])):
        raise ValueError("pairs must join a detection and a ground-truth box of the same image and category")
    det_at, gt_at, det_rank, gt_col = _layout(gt_group_of, det_group, score, n)
    shape = det_at.shape + (gt_at.shape[1],)
    iou, deg, pos_err = (np.full(shape, np.nan) for _ in range(3))
    where = (det_group[pd], det_rank[pd], gt_col[pg])
    iou[where], deg[where], pos_err[where] = errors

    # IoU matching at every threshold needed: the table's, the curve's and the pose gate
    gate = [] if config.pose_iou_gate is None else [config.pose_iou_gate]
    iou_thr = np.array(list(config.iou_thresholds) + list(config.iou_curve) + gate, dtype=np.float64)
    iou_match, iou_taken = _greedy(det_at, gt_at, iou, lambda k: iou[None, :, k, :] > iou_thr[:, None, None], len(iou_thr), True, m, n)

    # pose matching among the gated pairs, at the table's thresholds and along both curves
    pose_thr = np.array(
        [tuple(p) for p in config.pose_thresholds]
        + [(d, UNBOUNDED_POSITION) for d in config.degree_curve]
        + [(UNBOUNDED_DEGREES, p) for p in config.position_curve],
        dtype=np.float64,
    ).reshape(-1, 2)
    det_in = iou_match[-1] >= 0 if gate else np.ones(m, bool)
    gt_in = iou_taken[-1] if gate else np.ones(n, bool)
    pair_in = det_in[det_at][:, :, None] & np.where(gt_at >= 0, gt_in[np.maximum(gt_at, 0)], False)[:, None, :] & (det_at >= 0)[:, :, None]
    cost = deg + 100.0 * pos_err  # the reference sorts candidates by degrees + centimetres

    def pose_ok(k: int) -> np.ndarray:
        ok = (deg[None, :, k, :] <= pose_thr[:, 0, None, None]) & (pos_err[None, :, k, :] <= pose_thr[:, 1, None, None])
        return ok & pair_in[None, :, k, :]

    pose_match, _ = _greedy(det_at, gt_at, cost, pose_ok, len(pose_thr), False, m, n)

    categories = sorted({str(c) for c in gc})
    gc_str, dc_str = gc.astype(str), dc.astype(str)
    ap_iou = np.zeros((len(categories), len(iou_thr)))
    ap_pose = np.zeros((len(categories), len(pose_thr)))
    for row, c in enumerate(categories):  # a handful of categories; everything inside is vectorised
        d_c, g_c = dc_str == c, gc_str == c
        ap_iou[row] = average_precision(iou_match[:, d_c] >= 0, score[d_c], g_c.sum())
        sel = d_c & det_in
        ap_pose[row] = average_precision(pose_match[:, sel] >= 0, score[sel], (g_c & gt_in).sum())
    k1, k2 = len(config.iou_thresholds), len(config.iou_thresholds) + len(config.iou_curve)
    q1 = len(config.pose_thresholds)
    q2 = q1 + len(config.degree_curve)
    curves = {
        "iou": (np.asarray(config.iou_curve, dtype=np.float64), ap_iou[:, k1:k2]),
        "degrees": (np.asarray(config.degree_curve, dtype=np.float64), ap_pose[:, q1:q2]),
        "position": (np.asarray(config.position_curve, dtype=np.float64), ap_pose[:, q2:]),
    }
    counted = np.isin(dc_str, categories)
    return NocsMapResult(
        categories=categories,
        iou_thresholds=np.asarray(config.iou_thresholds, dtype=np.float64),
        iou_ap=ap_iou[:, :k1],
        pose_thresholds=pose_thr[:q1],
        pose_ap=ap_pose[:, :q1],
        curves=curves,
        detections=int(counted.sum()),
        ground_truth=n,
        ignored=int((~counted).sum()),
        config=config,
    )


def nocs_map(gt_image, gt_category, gt_pose, gt_extents, gt_symmetric,
             det_image, det_category, det_score, det_pose, det_extents,
             config: NocsMapConfig = NocsMapConfig()) -> NocsMapResult:
    """NOCS-style AP per category and mean, at ``config``'s IoU and pose thresholds, with the curves.

    Ground truth: ``gt_image`` (N,) labels (equal labels = one image), ``gt_category`` (N,), ``gt_pose``
    (N, 4, 4) object to camera, ``gt_extents`` (N, 3) m, ``gt_symmetric`` (N,) bool (:func:`nocs_symmetric`).
    Detections: ``det_image`` (M,), ``det_category`` (M,), ``det_score`` (M,) finite, higher = more
    confident, ``det_pose`` (M, 4, 4), ``det_extents`` (M, 3) m.  See the module docstring for the
    definitions.  ValueError on malformed input.
    """
    pairs = candidate_pairs(gt_image, gt_category, det_image, det_category)
    pairs = pair_errors(pairs, gt_pose, gt_extents, gt_symmetric, det_pose, det_extents)
    return nocs_map_from_pairs(pairs, gt_image, gt_category, det_image, det_category, det_score, config)
