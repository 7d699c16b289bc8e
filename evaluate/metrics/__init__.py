"""Exact, fast, documented evaluation metrics for categorical pose and shape estimation.

Conventions: metres, degrees; poses map object to camera (p_cam = R p_obj + t, OpenCV camera);
quaternions x, y, z, w; boxes centred on the object origin with full side lengths ``extents``;
symmetric objects (bottle, bowl, can) are symmetric about their object y axis.

Modules: :mod:`.pose_errors` (translation, rotation), :mod:`.box_iou` (exact oriented IoU, symmetric
IoU, NOCS axis-aligned IoU), :mod:`.shape_metrics` (chamfer, F-score), :mod:`.sampling` (mesh
sampling, :class:`ShapeIndex`), :mod:`.precision` (thresholds, precision tables and curves),
:mod:`.sample_errors` (all errors of a sample at once), :mod:`.nocs_map` (NOCS-style mAP of scored
detections, with the exact IoU).  Typical use: build one ShapeIndex per object,
call :func:`compute_sample_errors` once for all samples of a method, then :func:`precision_table` and
:func:`precision_curves` (pure comparisons; no metric is recomputed per threshold).

Where these differ from cpas_toolbox 1.0.0 (each tested in tests/test_metrics_cpas_agreement.py):
* symmetric rotation error: cpas takes arccos of an unclamped dot product; NaN > threshold is False, so
  upside-down predictions of symmetric objects often count as correct.  Ours: 180 degrees.
* symmetric IoU: cpas raises ValueError (``Rotation.from_rotvec`` of a scalar); ours is the exact
  maximum over the rotation about y.
* oriented IoU: cpas (Qhull) raises QhullError for touching or zero-volume boxes and draws from NumPy's
  global random state; ours is exact (agrees with cpas within 1e-9 where cpas works), deterministic,
  and 0 for touching or zero-volume boxes.
* NaN predictions: cpas passes them (NaN comparisons are False); ours marks them failed, never correct.
* Speed: errors are computed once per sample, thresholds are array comparisons.
Chamfer distance and F-score are the same definitions as cpas's and agree bit for bit.

Note: ``evaluate.metrics.box_iou`` is re-exported as the function; import the module's other names
with ``from evaluate.metrics.box_iou import ...``.
"""

from evaluate.metrics.box_iou import (
    axis_aligned_iou,
    box_iou,
    box_iou_batch,
    box_volume,
    symmetric_box_iou,
    symmetric_box_iou_batch,
)
from evaluate.metrics.nocs_map import NocsMapConfig, NocsMapResult, average_precision, nocs_map, nocs_symmetric
from evaluate.metrics.pose_errors import rotation_error, translation_error
from evaluate.metrics.precision import (
    DEFAULT_FSCORE_DISTANCE,
    DEFAULT_THRESHOLDS,
    DEGREE_CURVE,
    FSCORE_CURVE,
    IOU_CURVE,
    POSITION_CURVE,
    SampleErrors,
    Threshold,
    correct,
    precision,
    precision_curves,
    precision_table,
)
from evaluate.metrics.sample_errors import QUATERNION_TOLERANCE, compute_sample_errors
from evaluate.metrics.sampling import DEFAULT_SAMPLES, ShapeIndex, sample_surface
from evaluate.metrics.shape_metrics import FScore, chamfer_distance, fscore, squared_chamfer_distance

__all__ = [
    "DEFAULT_FSCORE_DISTANCE", "DEFAULT_SAMPLES", "DEFAULT_THRESHOLDS", "DEGREE_CURVE", "FSCORE_CURVE", "FScore",
    "IOU_CURVE", "NocsMapConfig", "NocsMapResult", "POSITION_CURVE", "QUATERNION_TOLERANCE", "SampleErrors", "ShapeIndex", "Threshold",
    "average_precision", "axis_aligned_iou", "box_iou", "box_iou_batch", "box_volume", "chamfer_distance", "compute_sample_errors",
    "correct", "fscore", "nocs_map", "nocs_symmetric", "precision", "precision_curves", "precision_table", "rotation_error", "sample_surface",
    "squared_chamfer_distance", "symmetric_box_iou", "symmetric_box_iou_batch", "translation_error",
]
