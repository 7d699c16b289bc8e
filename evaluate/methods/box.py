"""``box``: a weights-free baseline: principal axes and robust extents of the masked depth points.

What it does, in the camera frame (OpenCV, metres):

1. Points: the masked pixels with a depth are back-projected; depth outliers (mask bleeding onto
   the background, flying pixels at the silhouette) are dropped by a median-absolute-deviation
   test on depth (:func:`masked_points`).
2. Axes: principal axes of the points (PCA, variance descending a0, a1, a2), assigned to object
   axes by a per-category rule that follows the category's typical proportions (the built-in
   templates' extents):

   - bottle, can (taller than wide): y = a0.  bowl (wider than tall): y = a2.
   - mug (the handle makes body + handle the longest side): z = a0, y = a1.
   - any other category: y = the principal axis closest to the camera's up direction, z = the
     longer remaining one.

3. Signs: a principal axis has no direction, so the up-axis ambiguity is resolved by shape:
   a bottle narrows towards +y (the neck), a bowl widens towards +y (the rim) -- the width is
   the spread across the silhouette (perpendicular to y and to the view ray) in the top and
   bottom 30% of the points along y. A mug's -z is the side of the longer tail of the points along
   z (the handle is a thin appendage, so the body holds most points). Where shape says nothing
   (can; mug's y; other categories) y points to the camera's up (-y camera): the upright prior.
   x completes a right-handed frame (x = y cross z).
4. Extents: the 2nd-98th percentile range along each object axis, divided by 0.96 (the fraction of
   a uniform spread that range covers). Only the camera-facing surface is seen, so the range
   along the axis closest to the view ray under-estimates the object: that extent is raised to at
   least what the category's proportions predict from the other two (for bottle, bowl and can x
   and z are one diameter, which the silhouette shows in full), and its box centre is moved away
   from the camera to half that extent behind the nearest observed surface.

The reconstruction is the observed points in the predicted object frame (a partial shape).
"""

from __future__ import annotations

import numpy as np

from evaluate.geometry import matrix_to_quat
from sequences.annotation import SYMMETRIC_CATEGORIES  # symmetric about object y: x and z extents are one diameter
from sequences.camera import Camera

from .base import Method, Prediction

#: Typical full extents (x, y, z) per category, metres: the built-in templates' boxes
#: (evaluate.methods.templates); only their ratios are used here.
TYPICAL_EXTENTS = {
    "bottle": np.array([0.066, 0.21, 0.066]),
    "bowl": np.array([0.16, 0.065, 0.16]),
    "can": np.array([0.066, 0.122, 0.066]),
    "mug": np.array([0.082, 0.096, 0.111]),
}
#: Fewer valid points than this is no observation.
MIN_POINTS = 10
#: Percentiles bounding the robust extent, and the fraction of a uniform spread they cover.
LOW_PERCENTILE, HIGH_PERCENTILE = 2.0, 98.0
_PERCENTILE_SPAN = (HIGH_PERCENTILE - LOW_PERCENTILE) / 100.0


def check_inputs(depth: np.ndarray, mask: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes and types of a method's depth (H, W) metres and mask (H, W) bool; ValueError if wrong."""
    depth = np.asarray(depth)
    mask = np.asarray(mask)
    if depth.ndim != 2:
        raise ValueError(f"depth must be a 2D image (H, W) in metres, got shape {depth.shape}")
    if mask.shape != depth.shape:
        raise ValueError(f"mask shape {mask.shape} differs from depth shape {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f"depth must be floating point metres, got {depth.dtype}")
    return depth, mask.astype(bool)


def masked_points(depth: np.ndarray, mask: np.ndarray, camera: Camera, mad_factor: float = 4.0, floor: float = 0.02) -> np.ndarray:
    """Camera-frame points (N, 3) m of the masked pixels with depth, without depth outliers.

    A point is kept when its depth is within ``max(mad_factor * 1.4826 * MAD, lateral, floor)`` of
    the median depth: 1.4826 MAD estimates a standard deviation, but an object's depths are far from
    normal (a front surface plus a tail into an opening), so the tolerance is at least the object's
    width across the view (``lateral``: the larger 2nd-98th percentile spread of camera x and y), as
    deep as an object seen from the side is wide; ``floor`` m keeps small objects whole.
    Raises ValueError when fewer than :data:`MIN_POINTS` valid points remain (an empty mask, a mask
    without depth).
    """
    depth, mask = check_inputs(depth, mask, camera)
    points, _ = camera.backproject(depth, mask)
    if len(points) < MIN_POINTS:
        raise ValueError(f"only {len(points)} masked pixels have a depth (need at least {MIN_POINTS}): empty mask or no depth")
    z = points[:, 2]
    median = np.median(z)
    mad = np.median(np.abs(z - median))
    lo, hi = np.percentile(points[:, :2], [LOW_PERCENTILE, HIGH_PERCENTILE], axis=0)
    lateral = float((hi - lo).max())
    keep = np.abs(z - median) <= max(mad_factor * 1.4826 * mad, lateral, floor)
    points = points[keep]
    if len(points) < MIN_POINTS:
        raise ValueError(f"only {len(points)} masked points remain after removing depth outliers (need {MIN_POINTS})")
    return points


def _spread(values: np.ndarray) -> float:
    lo, hi = np.percentile(values, [LOW_PERCENTILE, HIGH_PERCENTILE])
    return float(hi - lo)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _silhouette_direction(y: np.ndarray, view: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Unit direction perpendicular to y and to the view ray (the silhouette's width), or ``fallback``."""
    lateral = np.cross(y, view)
    return _unit(lateral) if np.linalg.norm(lateral) > 0.2 else fallback


def _orient_y(category: str, y: np.ndarray, points: np.ndarray, centroid: np.ndarray, view: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Resolve the sign of the object's y axis (see the module docstring)."""
    up_prior = y if y @ np.array([0.0, -1.0, 0.0]) >= 0 else -y
    if category not in ("bottle", "bowl"):
        return up_prior
    lateral = _silhouette_direction(y, view, other)
    along = (points - centroid) @ y
    across = (points - centroid) @ lateral
    lo, hi = np.percentile(along, [30.0, 70.0])
    bottom, top = across[along <= lo], across[along >= hi]
    if len(bottom) < 3 or len(top) < 3:
        return up_prior
    narrower_top = _spread(top) < _spread(bottom)
    wants_narrow_top = category == "bottle"
    return y if narrower_top == wants_narrow_top else -y


def principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (3,) and principal axes (3, 3) of points (N, 3), columns ordered by variance, descending."""
    centroid = points.mean(axis=0)
    centred = points - centroid
    eigenvalues, eigenvectors = np.linalg.eigh(centred.T @ centred / len(points))
    return centroid, eigenvectors[:, np.argsort(eigenvalues)[::-1]]


def assign_axes(category: str, points: np.ndarray, centroid: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Object-to-camera rotation (3, 3) (columns = object x, y, z in the camera frame) from principal axes."""
    view = _unit(centroid)
    a0, a1, a2 = axes.T
    if category in ("bottle", "can"):
        y, z = a0, a1
    elif category == "bowl":
        y, z = a2, a0
    elif category == "mug":
        z, y = a0, a1
    else:
        k = int(np.argmax(np.abs(axes.T @ np.array([0.0, -1.0, 0.0]))))
        y = axes[:, k]
        z = axes[:, min(j for j in range(3) if j != k)]
    y = _orient_y(category, y, points, centroid, view, z)
    if category == "mug":
        along = (points - centroid) @ z
        lo, median, hi = np.percentile(along, [LOW_PERCENTILE, 50.0, HIGH_PERCENTILE])
        if hi - median > median - lo:  # the handle's thin tail lies on -z (REDWOOD75/NOCS convention)
            z = -z
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


def fit_box(category: str, points: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Box centre (3,) camera frame and full extents (3,) along the object axes of ``rotation``, from visible points."""
    centroid = points.mean(axis=0)
    view = _unit(centroid)
    local = (points - centroid) @ rotation
    lo, hi = np.percentile(local, [LOW_PERCENTILE, HIGH_PERCENTILE], axis=0)
    extents = (hi - lo) / _PERCENTILE_SPAN
    middle = (lo + hi) / 2
    half_extra = (extents - (hi - lo)) / 2
    lo, hi = lo - half_extra, hi + half_extra
    view_alignment = rotation.T @ view  # cosine of each object axis with the view ray
    depth_axis = int(np.argmax(np.abs(view_alignment)))
    typical = TYPICAL_EXTENTS.get(category)
    others = [j for j in range(3) if j != depth_axis]
    if category in SYMMETRIC_CATEGORIES and depth_axis != 1:
        predicted = extents[2 - depth_axis]  # the silhouette shows the diameter in full
    elif typical is not None:
        predicted = typical[depth_axis] * float(np.median(extents[others] / typical[others]))
    else:
        predicted = float(np.mean(extents[others]))
    if predicted > extents[depth_axis]:
        extents[depth_axis] = predicted
        # Keep the camera-facing end, which was observed; the far end is behind the object.
        if view_alignment[depth_axis] > 0:
            middle[depth_axis] = lo[depth_axis] + predicted / 2
        else:
            middle[depth_axis] = hi[depth_axis] - predicted / 2
    if category in SYMMETRIC_CATEGORIES:
        diameter = max(extents[0], extents[2])
        extents[0] = extents[2] = diameter
    return centroid + rotation @ middle, extents


class BoxMethod(Method):
    """Principal axes and robust percentile extents of the masked points (see the module docstring).

    ``config`` keys (all optional): ``mad_factor`` (4.0) and ``depth_floor`` (0.02 m) of the depth
    outlier test.
    """

    name = "box"

    def __init__(self, config: dict | None = None) -> None:
        config = dict(config or {})
        self.mad_factor = float(config.pop("mad_factor", 4.0))
        self.depth_floor = float(config.pop("depth_floor", 0.02))
        if config:
            raise ValueError(f"unknown box method options {sorted(config)}; known: mad_factor, depth_floor")

    def inference(self, color: np.ndarray, depth: np.ndarray, mask: np.ndarray, category: str, camera: Camera) -> Prediction:
        points = masked_points(depth, mask, camera, self.mad_factor, self.depth_floor)
        centroid, axes = principal_axes(points)
        rotation = assign_axes(category, points, centroid, axes)
        position, extents = fit_box(category, points, rotation)
        return Prediction(position, matrix_to_quat(rotation), extents, (points - position) @ rotation)
