"""Frames whose geometry leaves the spin about a near-round body's axis free.

A mug whose handle is hidden (behind its body, or in the hand) is a surface of revolution in that frame: every spin
about its axis fits the points equally well, and the registration carries the spin it started from. Such frames are
found here from the geometry alone: the frame's points, at its pose and spun by +-``FREE_SPIN_DEG`` about the axis of
the model (symmetry_axis.fit_symmetry_axis, the handle an outlier to it), fit the model within ``SPIN_FIT_MARGIN`` of
each other. The engine takes their spin from their neighbours' (spin_window.py) and flags long runs of them
(consistency.free_spin_runs): only the motion carries it there.

The model must be round first (``round``): spun by FREE_SPIN_DEG, it still fits itself with ``MIN_ROUND_SHARE`` of
its points (a mug's body); a camera or a laptop has no free spin, and none of its frames is checked.

The spin is not read from the colours: a mug's print fixes it only where the print is not itself symmetric, and a
colour model built from the tracked frames carries their errors (a colour check tuned on the generator's label
turned the spins of real scanned mugs 30-45 deg off).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from annotate.symmetry_axis import fit_symmetry_axis
from evaluate.geometry import untransform

from .sampling import every_kth

#: a spin whose geometric fitness is within this of the pose's own is one the geometry cannot tell apart
SPIN_FIT_MARGIN = 0.03
#: the spin that geometry leaves free must be at least this wide (degrees each side)
FREE_SPIN_DEG = 10.0
#: voxel points per frame used for the geometric fitness (every k-th beyond): the check's time stays bounded
MAX_CHECK_POINTS = 600
#: the model spun by FREE_SPIN_DEG must still fit itself with this share of its points (a mug: its body),
#: else no spin is free anywhere (a camera, a laptop) and no frame is checked
MIN_ROUND_SHARE = 0.6
#: model points used to fit the axis and test the roundness (every k-th beyond)
MAX_AXIS_POINTS = 1500


def spin_matrix(axis: np.ndarray, point: np.ndarray, degrees: float) -> np.ndarray:
    """The 4x4 object-frame rotation S by ``degrees`` about the line ``axis`` through ``point`` (pose @ S spins the pose)."""
    S = np.eye(4)
    S[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, dtype=np.float64)).as_matrix()
    S[:3, 3] = point - S[:3, :3] @ point
    return S


class FreeSpinCheck:
    """Which frames leave the spin about one model's axis free (object frame, metres). Raises ValueError where no
    axis can be fitted to the model's points."""

    def __init__(self, tracker, model_points: np.ndarray) -> None:
        self.tracker = tracker
        self.points = np.asarray(model_points, dtype=np.float64)
        self.tree = cKDTree(self.points)
        # the axis and the roundness from every k-th model point (a spread sample) bound their time
        self._sample = every_kth(self.points, MAX_AXIS_POINTS)
        self.axis, self.point, _, _ = fit_symmetry_axis(self._sample, normal_radius=4 * tracker.config.voxel_size)
        # spun(q, deg) = (q - point) @ R(deg) + point
        self._R = {d: spin_matrix(self.axis, self.point, d)[:3, :3] for d in (-FREE_SPIN_DEG, FREE_SPIN_DEG)}

    def _spun(self, local: np.ndarray, degrees: float) -> np.ndarray:
        """Object-frame points (N, 3) as seen at the pose spun by ``degrees`` (pose @ S sees ``local`` at S^-1 local)."""
        return (local - self.point) @ self._R[degrees] + self.point

    def round(self) -> bool:
        """Whether the model spun by FREE_SPIN_DEG about its axis still fits itself (MIN_ROUND_SHARE): a spin can be free."""
        return self._fitness(self._spun(self._sample, FREE_SPIN_DEG)) >= MIN_ROUND_SHARE

    def free_frames(self, poses: dict[str, np.ndarray]) -> list[str]:
        """The frames of ``poses`` (frame -> 4x4 pose in the model's object frame) that leave the spin free, in their
        order; none where the model is not round."""
        if not self.round():
            return []
        return [f for f, pose in poses.items() if self.spin_free_at(f, pose)]

    def spin_free_at(self, frame_id: str, pose: np.ndarray) -> bool:
        """Whether the frame at ``pose`` has enough voxel points to judge (a quarter of ``min_points``) and spinning it
        by +-FREE_SPIN_DEG keeps its geometric fitness."""
        local = self._local(frame_id, pose)
        if len(local) < self.tracker.config.min_points // 4:
            return False
        own = self._fitness(local)
        return all(self._fitness(self._spun(local, d)) >= own - SPIN_FIT_MARGIN for d in (FREE_SPIN_DEG, -FREE_SPIN_DEG))

    def _local(self, frame_id: str, pose: np.ndarray) -> np.ndarray:
        """A frame's voxel points at ``pose``, object frame (N, 3) (every k-th beyond MAX_CHECK_POINTS)."""
        points, _ = self.tracker.crop(frame_id, pose, margin=0.0)
        return untransform(pose, every_kth(points, MAX_CHECK_POINTS))

    def _fitness(self, local: np.ndarray) -> float:
        """The share of ``local`` within the registration's quality distance of the model."""
        d, _ = self.tree.query(local, distance_upper_bound=self.tracker.config.registration.quality_distance)
        return float(np.mean(np.isfinite(d))) if len(d) else 0.0
