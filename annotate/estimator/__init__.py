"""The tracking estimator: chains from the boxes a person placed, one pose graph over all frames, rounds against
the model of all frames (docs/tracking.md).

Public API: :func:`track_sequence`, :func:`refine_frame`, :class:`EstimatorConfig`.
"""

from .config import EstimatorConfig
from .pipeline import anchor_frames, refine_frame, track_sequence

__all__ = ["EstimatorConfig", "anchor_frames", "refine_frame", "track_sequence"]
