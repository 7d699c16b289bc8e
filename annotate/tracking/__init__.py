"""Tracking: from a few hand-placed boxes to a pose in every frame, with quality flags (issue 5).

Public API (used by ``annotate --track`` and the browser app):
- :func:`track_sequence` (a new document with every frame posed), :func:`refine_frame` (one frame);
- :class:`TrackingConfig` (backend, voxel size, thresholds);
- :func:`estimate_symmetry_axis`, :func:`snap_upright` (symmetric objects).
"""

from .config import TrackingConfig
from .engine import refine_frame, track_sequence
from .registration import BACKENDS, RegistrationParams
from annotate.symmetry_axis import closest_about_y, estimate_axis, estimate_symmetry_axis, snap_upright

__all__ = [
    "BACKENDS",
    "RegistrationParams",
    "TrackingConfig",
    "closest_about_y",
    "estimate_axis",
    "estimate_symmetry_axis",
    "refine_frame",
    "snap_upright",
    "track_sequence",
]
