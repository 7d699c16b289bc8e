"""The estimator's settings: one frozen dataclass, lengths in metres, angles in degrees.

Every field is one knob of the objective in ``docs/tracking.md``; the benchmark varies them with
``dataclasses.replace``. Defaults were chosen on the suite's ``dev`` split and the real frames of YCB-Video.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EstimatorConfig:
    """Settings of :func:`annotate.estimator.track_sequence` (metres, degrees, frames)."""

    stride: int = 2  #: pixel subsampling of the depth images (2: 320 x 240 from VGA)
    voxel_size: float = 0.004  #: frame and model point spacing (m); large objects use max extent / voxels_across instead
    voxels_across: int = 50  #: ... so a large object's point count, and its time, stays bounded
    crop_margin: float = 0.01  #: a frame's points are taken inside the box grown by this (m) on each side ...
    crop_slack: float = 0.08  #: ... and by this share of its extents (placed extents are off by up to ~8 %)
    max_points: int = 800  #: a frame registers at most this many points (a seeded subset beyond)
    icp_distances: tuple[float, float] = (0.02, 0.006)  #: correspondence distance (m): coarse, then fine
    icp_iterations: int = 10  #: Gauss-Newton iterations per stage at most
    facing_cos: float = 0.3  #: a frame point pairs with a model point whose normal is within acos(this) of its own
    point_sigma: float = 0.002  #: per-point noise (m) that scales a registration's information
    independent_points: int = 100  #: a registration counts as at most this many independent points (neighbours' errors correlate)
    chain_model_frames: int = 8  #: a chain registers each frame to its anchor and its last this many frames
    anchor_sigma_deg: float = 3.0  #: how far a placed box's rotation is off, per axis (the annotator's placement sigma)
    anchor_sigma_m: float = 0.005  #: ... and its centre, per axis (m)
    motion_sigma_deg: float = 1.5  #: change of rotational velocity expected between frames (hand-held, 30 fps)
    motion_sigma_m: float = 0.003  #: ... and of the centre's velocity (m per frame)
    robust_k: float = 2.0  #: Cauchy kernel width of the registration, chain-step and constant-velocity factors, in their standard deviations
    rounds: int = 3  #: rounds of fusing the model of all frames and registering every frame to it, at most
    settled: tuple[float, float] = (0.05, 0.0002)  #: ... fewer once a round moved no frame more than this (deg, m)
    free_space_tolerance: float = 0.01  #: a model voxel a frame sees this far (m) beyond counts as free in that frame
    max_free_share: float = 0.25  #: model voxels seen through in more than this share of the frames that see them are dropped (a hand that moved)
    min_fitness: float = 0.5  #: flag a frame whose points pair with the model at a lower share than this
    #: flag a frame whose marginal standard deviation exceeds this (deg, m); the marginals are too confident (the
    #: registrations count 100 points as independent, and the model they register to was fused at poses off alike), so
    #: the rotation's limit is half of the 2 deg meant
    max_uncertainty: tuple[float, float] = (1.0, 0.003)
    max_disagreement: tuple[float, float] = (3.0, 0.006)  #: flag a frame whose registration and solved pose differ more (deg, m)
    workers: int = 0  #: processes for the chains and the rounds' registrations (0: the cores available, at most 4; 1: none); the same poses for any count

    def voxel_for(self, extents: np.ndarray) -> float:
        """Point spacing (m) for an object of these extents (m)."""
        return max(self.voxel_size, float(np.max(extents)) / self.voxels_across)

    def check(self) -> "EstimatorConfig":
        """This config, or ValueError naming the first setting out of range."""
        positive = ("stride", "voxel_size", "voxels_across", "max_points", "icp_iterations", "point_sigma", "independent_points",
                    "anchor_sigma_deg", "anchor_sigma_m", "motion_sigma_deg", "motion_sigma_m", "robust_k", "free_space_tolerance")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"estimator setting {name} must be positive, got {getattr(self, name)}")
        if not 0 < self.icp_distances[1] <= self.icp_distances[0]:
            raise ValueError(f"icp_distances must be positive, coarse first, got {self.icp_distances}")
        if self.workers < 0:
            raise ValueError(f"workers must be 0 (the cores available) or more, got {self.workers}")
        if not 0 <= self.min_fitness <= 1 or not 0 <= self.max_free_share <= 1:
            raise ValueError("min_fitness and max_free_share are shares between 0 and 1")
        return self
