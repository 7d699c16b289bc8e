"""Tracking settings: the registration backend, object-scale distances and the review thresholds."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .registration import BACKENDS, RegistrationParams
from annotate.workers import resolve


@dataclass
class TrackingConfig:
    """All lengths in metres, angles in degrees."""

    backend: str = "point_to_plane"  #: one of registration.BACKENDS (chosen by benchmarks/bench_tracking.py)
    voxel_size: float = 0.004  #: model and frame downsampling (at least; large objects use max extent / voxels_across)
    voxels_across: int = 60  #: a large object gets a coarser voxel so its point count (and time) stays bounded
    shallow_voxel_size: float = 0.003  #: a shallow body of symmetry y (a bowl: height under SHALLOW_RATIO of its width) starts from this voxel instead (its thin rim and foot fix its axis; 0: voxel_size)
    max_points: int = 2500  #: a frame's points registered at most (every k-th beyond; 0: all)
    stride: int = 2  #: pixel subsampling when reading a frame's points
    crop_margin: float = 0.01  #: box grown by this on each side when cropping a frame
    extents_slack: float = 0.08  #: the box is grown by this share too (hand-placed extents are off by up to ~8%)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    chain_follow_fitness: float = 0.2  #: a chain follows a frame below min_fitness down to this fitness (propagate.follows; >= min_fitness: off)
    chain_follow_step_deg: float = 5.0  #: ... where its registration turned it at most this far from where it started
    chain_follow_step_m: float = 0.01  #: ... and moved it at most this far (m)
    model_refresh: int = 3  #: a chain's model target (normals, search grid) is rebuilt every this many frames
    global_rounds: int = 2  #: rounds of registering every frame to the model of all frames
    coarse_voxel_factor: float = 2.0  #: ... after one round against a model this many times coarser (refine.coarse_round; <= 1: none)
    coarse_step_deg: float = 5.0  #: ... in which a frame turns at most this far (deg)
    coarse_step_m: float = 0.01  #: ... and moves at most this far (m)
    max_refine_step_deg: float = 10.0  #: a joint-refinement round turning a frame further keeps its pose (0: no limit)
    max_refine_step_m: float = 0.02  #: ... and so does one moving it further than this (m; 0: no limit)
    refine_step_fitness_gain: float = 0.05  #: ... unless the turned pose fits the same points by this much better
    max_suspect_step_deg: float = 15.0  #: a frame still suspect after the recheck, registered once more to the trusted model, turns at most this far (refine.reregister_suspects)
    max_refine_departure_deg: float = 5.0  #: symmetric objects: rounds that together turn a frame's axis this far from the chains' pose
    max_refine_departure_m: float = 0.01  #: ... or move it this far (m) need that better fit too (0: no limit; refine.far_from_chains)
    settled_deg: float = 0.2  #: ... fewer once a round moved the poses less than this in the median
    settled_m: float = 0.0005  #: ... and less than this (m)
    global_min_hits: int = 3  #: model voxels seen in fewer frames are left out (a moving hand)
    free_space_tolerance: float = 0.01  #: global models drop voxels seen through by more than this (0: off)
    max_through_share: float = 0.5  #: ... in more than this share of the frames that see them (a moved hand)
    max_global_frames: int = 60  #: frames used to build the global model (evenly spaced)
    spin_window: int = 2  #: objects without symmetry whose spin is free somewhere (a mug): a suspect or free-spin frame takes the mean spin about the body's axis of the frames within this many either side (spin_window.py; 0: off)
    smoothing: bool = True  #: smooth the refined poses where registration leaves a direction weak (smooth.py)
    information_sigma: float = 0.002  #: point noise (m) scaling a frame's registration information
    smoothing_undo_deg: float = 3.0  #: a frame the smoothing turned further keeps its refined pose where that fits clearly better (refine.undo_smoothing_bends; 0: off)
    smoothing_undo_gain: float = 0.05  #: ... by at least this fitness against the model of the trusted frames
    smoothing_undo_max_deg: float = 45.0  #: ... and only up to this turn (beyond it a flip, which a round body fits as well)
    rotation_acceleration_deg: float = 0.5  #: expected rotational acceleration, deg per frame squared (hand-held, 30 fps)
    translation_acceleration: float = 0.0005  #: expected acceleration of the centre, m per frame squared
    manual_rotation_sigma_deg: float = 1.0  #: how far a placed box's rotation is off, per axis: weighs the anchors' links (reconcile.chain_frame_offsets) and the smoothing's pull (0: the links alone, no pull)
    manual_translation_sigma: float = 0.002  #: how far a placed box's centre is off, per axis, m (both must be > 0 for the pull)
    symmetry_snap: bool = True  #: for symmetry y: snap the box's y axis to the axis estimated from the model
    body_axis_snap: bool = True  #: near-round objects without symmetry (a mug): turn the box's y onto the body's axis fitted to the model, about the box centre
    max_axis_conditioning: float = 0.15  #: no snap when the axis fit is this ill-conditioned (symmetry_axis.fit_symmetry_axis)
    face_snap: bool = True  #: box-like objects (a camera): turn the box onto the model's faces, about its centre (faces.py)
    min_face_share: float = 0.05  #: ... when each axis holds at least this share of the model's normals (a laptop's thin sides: 0.3-0.6 %)
    min_faces_total: float = 0.5  #: ... and all six faces together at least this share (cameras 0.67-0.75; a mug's round side leaves 0.18-0.32)
    max_face_snap_deg: float = 5.0  #: ... and the turn is at most this (a larger one means the faces are not the frame's)
    hinge_snap: bool = True  #: a hinged body (a laptop): turn the box's y onto its base's normals and its x square to its lid's (faces.hinge_rotation), at most max_face_snap_deg
    hinge_cone_deg: float = 5.0  #: ... the normals within this of +-y (the base's top and bottom) fix the tilt
    hinge_plane_deg: float = 3.0  #: ... the normals within this of the y-z plane (the lid, the base's edges) fix the spin
    min_hinge_plane_share: float = 0.35  #: ... when at least this share of the model's normals lies within hinge_plane_deg of the y-z plane (a mug's caps and side hold about a quarter)
    frame_hinge_tilt: bool = True  #: ... and then every frame turned onto its own base's and lid's normals, the median over tilt_window (tilt.py)
    hinge_tilt_every: int = 2  #: ... measured on every this-many-th frame (a laptop frame's normals cost ~30 ms of CPU; the median keeps 6-7)
    flat_snap: bool = True  #: symmetry y where the axis fit is refused (a shallow bowl): turn the box's y onto the model's normals near it (faces.tilt_onto_axis), at most max_face_snap_deg
    flat_cone_deg: float = 5.0  #: ... those within this of +-y
    min_flat_share: float = 0.03  #: ... when they are at least this share of the model's normals
    flat_axis_centring: bool = True  #: ... and the box centre moved across y onto the symmetry axis along y (symmetry_axis.fit_axis_point)
    max_axis_shift_m: float = 0.01  #: ... by at most this (m; further means the fit is not the object's)
    frame_tilt: bool = True  #: ... and then every frame's tilt measured from its own normals near y (tilt.py)
    min_tilt_normals: int = 20  #: ... where at least this many of a frame's normals lie within flat_cone_deg of y
    #: ... and they turn it at most this far: half the cone. One frame sees a curved patch (a dome, a rounded foot)
    #: from one side, and the cone's mean then walks towards its edge; a face's own tilt lies well inside it
    max_frame_tilt_deg: float = 2.5
    tilt_window: int = 6  #: ... the median of the tilts measured within this many frames either side
    min_tilt_frames: int = 3  #: ... where at least this many frames there measure one
    threads: int = 1  #: Open3D threads while tracking (1: reproducible results; 0: Open3D's default)
    workers: int = 0  #: processes for independent work (workers.py; 0: the cores available, at most 4; 1: none): the same results for any count
    # review thresholds: a frame outside any of them gets flagged: true and a flag_reason
    min_fitness: float = 0.5
    max_inlier_rmse: float = 0.003
    min_in_box: float = 0.6
    max_chain_disagreement_deg: float = 5.0
    max_chain_disagreement_m: float = 0.01
    max_chain_departure_deg: float = 8.0  #: final pose this far from both chains' poses (consistency.py)
    slide_check: bool = True  #: move a frame along the direction its registration leaves free where its fitness clearly rises (slide.py: a laptop along its hinge)
    max_slide_ratio: float = 0.075  #: ... only where that direction's information is under this share of the strongest one
    min_slide_gain: float = 0.02  #: ... and the fitness on a wider crop rises by at least this
    min_slide_m: float = 0.005  #: ... at a shift of at least this (m)
    max_slide_m: float = 0.04  #: ... shifts tried up to this far either way, a best one within 5 mm of that end not taken (m; the crop is widened by 3/4 of it)
    slide_path_tolerance: float = 0.002  #: ... nor one taking the frame this much further (m) from the midpoint of its neighbours (then flagged)
    max_free_spin_run: int = 5  #: flag frames in a run of more frames whose geometry leaves the spin free, and in such a run at either end (consistency.free_spin_runs; 0: off)
    max_frame_rotation_deg: float = 20.0  #: a frame turned this far from a neighbour frame (consistency.py)
    #: flag a tracked frame beside a flagged one (and so on outwards, at most max_flag_gap frames) whose chain
    #: disagreement or departure reaches this share of its limit (consistency.flags_grown; 0: off)
    flag_hysteresis: float = 0.5
    max_flag_gap: int = 2  #: flag tracked frames in a run of at most this many unflagged ones between flagged frames (consistency.flagged_gaps; 0: off)
    #: an anchor takes its estimated pose where that lies within this of the person's box (deg, m), else keeps the box
    #: and is flagged (twice the placement sigma)
    max_manual_correction_deg: float = 6.0
    max_manual_correction_m: float = 0.012
    min_points: int = 100

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown registration backend {self.backend!r}; one of {', '.join(BACKENDS)}")
        if self.workers < 0:
            raise ValueError(f"workers must be 0 (the cores available) or more, got {self.workers}")
        if not self.voxel_size > 0:
            raise ValueError("voxel_size must be positive")
        if not self.shallow_voxel_size >= 0:
            raise ValueError("shallow_voxel_size must be 0 (off) or positive")

    def coarse_voxel(self) -> float | None:
        """The coarse round's voxel (m; refine.coarse_round), or None where there is no coarse round."""
        return self.voxel_size * self.coarse_voxel_factor if self.coarse_voxel_factor > 1 else None

    def worker_count(self) -> int:
        """Processes for independent work: one unless Open3D runs on one thread (a thread pool does not survive a fork)."""
        return resolve(self.workers) if self.threads == 1 else 1


#: A body of symmetry y whose box is less tall than this share of its width is shallow (a bowl, about a third; cans
#: and bottles are taller than wide).
SHALLOW_RATIO = 0.5


def scaled_to(config: TrackingConfig, extents, symmetric: bool = False) -> TrackingConfig:
    """The configuration with its voxel size for an object of box ``extents`` (m; x, y, z): a shallow body of symmetry
    y (``symmetric``) starts from ``shallow_voxel_size``, and a large object's grows to max extent / ``voxels_across``.

    A bowl's thin rim and foot are what fix its axis: on coarser voxels its frames lose it where the hand covers the
    bowl."""
    from dataclasses import replace

    extents = np.asarray(extents, dtype=np.float64).reshape(3)
    voxel = config.voxel_size
    if symmetric and config.shallow_voxel_size > 0 and extents[1] < SHALLOW_RATIO * max(extents[0], extents[2]):
        voxel = config.shallow_voxel_size
    voxel = max(voxel, float(extents.max()) / config.voxels_across)
    return replace(config, voxel_size=voxel) if voxel != config.voxel_size else config
