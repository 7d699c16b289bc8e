"""Pose errors: translation error (metres) and rotation error (degrees), batched over leading axes.

Both raise ValueError on NaN or inf input: a NaN error compares False against any threshold, which is
how cpas_toolbox ends up counting broken predictions as correct.  Evaluation code screens predictions
first (see :mod:`evaluate.metrics.sample_errors`) and records malformed ones as failed.
"""

from __future__ import annotations

import numpy as np

from evaluate.metrics import _validate


def translation_error(position_gt, position_pred) -> float | np.ndarray:
    """Euclidean distance (m) between positions (..., 3); a float for single positions."""
    a = _validate.finite_array(position_gt, "position_gt", (3,))
    b = _validate.finite_array(position_pred, "position_pred", (3,))
    d = np.linalg.norm(a - b, axis=-1)
    return float(d) if d.ndim == 0 else d


def rotation_error(R_gt, R_pred, symmetry: str | None = "none") -> float | np.ndarray:
    """Rotation error in degrees between object-to-camera rotations (..., 3, 3).

    ``symmetry="none"``: the angle of the relative rotation R_gt^T R_pred, in [0, 180].
    ``symmetry="y"`` (objects rotationally symmetric about their y axis: bottle, bowl, can): the angle
    between the two rotated y axes, in [0, 180]; an upside-down prediction is 180 degrees wrong.

    The angles are computed as atan2(|sin|, cos), which equals the clamped arccos(clip(cos, -1, 1)) of
    the textbook formulas but stays accurate near 0 and 180 degrees, where arccos loses half the digits.
    Raises ValueError for NaN/inf or matrices that are not rotations.
    """
    mode = _validate.symmetry(symmetry)
    A = _validate.rotations(R_gt, "R_gt")
    B = _validate.rotations(R_pred, "R_pred")
    if mode == "y":
        a, b = A[..., :, 1], B[..., :, 1]
        angle = np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...i,...i->...", a, b))
    else:
        M = np.einsum("...ji,...jk->...ik", A, B)  # R_gt^T R_pred
        cos2 = M[..., 0, 0] + M[..., 1, 1] + M[..., 2, 2] - 1.0  # 2 cos(angle)
        axis2 = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], axis=-1)
        angle = np.arctan2(np.linalg.norm(axis2, axis=-1), cos2)  # |2 sin(angle)|, 2 cos(angle)
    degrees = np.degrees(angle)
    return float(degrees) if degrees.ndim == 0 else degrees
