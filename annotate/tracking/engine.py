"""The tracking engine: from a few hand-placed boxes to a pose in every frame (and one-frame refinement).

``track_sequence``:
1. anchors: the frames whose box a person placed, refined or accepted (in the chosen range; annotate.engines.anchor_frames);
2. chains: from every anchor forward and backward to the neighbouring anchors (or the ends),
   each frame registered to the chain's growing model (propagate.py);
3. reconcile: between two anchors, the two chains are blended, or joined at the frame where they
   meet when one of them lost the object (reconcile.py);
4. refine: every frame, anchors included, re-registered to the model of all frames (refine.py), first once
   against a twice coarser model, where the copies of a detail that stretches between manual frames left
   side by side merge (refine.coarse_round);
   where the two chains disagreed, the frame is re-registered from each chain's pose: when no
   start finds a rival pose fitting as well and the pose is smooth with its neighbours, the
   disagreement is re-measured against the final pose (refine.recheck_disagreements); the
   models of all frames leave out voxels that other frames see through (a hand before a
   regrasp, freespace.py);
4a. flips: a frame the refinement left turned over from the frame before it (a bottle upside down: its ends fit
   each other's place) is registered again from that frame's pose (refine.repair_flips), before the smoothing
   would average it with its neighbours;
4b. smooth: where a frame's registration leaves a direction weak (a mug's spin with its handle
   hidden), the pose is taken from its neighbours by an information-weighted least-squares
   smoothing (smooth.py); a frame it turned 3-45 deg keeps its refined pose where that fits the trusted frames
   clearly better (refine.undo_smoothing_bends: a long run without evidence is bent by the smoothing alone). Then the frames still suspect (their chains disagreed and no restart
   cleared them) are registered once more to the model of the trusted final poses, which holds none
   of their own points (refine.reregister_suspects);
4c. slide: where the registration leaves one direction of translation free (a laptop seen on its
   faces slides along its hinge), the frame is moved along it where the fitness on a wider crop
   clearly rises (slide.py), unless that takes it off the path of its neighbours (then it is
   flagged: slide.against_the_motion);
5. common frame: the consistent poses are moved by the one correction that best fits all the
   placed boxes (their errors average out; a manual frame whose shape leaves the spin free does not
   set it); for symmetry y, the box is snapped upright on the
   axis estimated from the model (annotate/symmetry_axis.py), unless the fit leaves the axis direction
   undetermined (a shallow bowl: nearly a sphere), where the box's y is turned onto the model's normals within 5 deg
   of it instead (its foot and inner bottom face along the axis; faces.tilt_onto_axis), its centre moved across y
   onto the axis the model's normal lines meet along that y (symmetry_axis.fit_axis_point), and then each frame onto
   the normals of its own points near y, the median over +-6 frames, the suspect frames measuring none (tilt.py);
   a near-round body without symmetry whose wall is a surface of revolution (a mug: _revolves) has its box's y
   turned onto the body's axis the same way, about
   the box centre (which the handle keeps off the axis), and each frame then turned onto its own normals near y as a
   bowl's (tilt.py; by at most
   half the cone of normals it reads: a curved patch seen from one side walks the cone's mean to its edge);
   a box-like body (a camera) onto its faces (faces.py); a hinged one (a laptop) its y onto its base's faces and
   its x square to its lid's (faces.hinge_rotation), each frame then turned onto its own base's and lid's faces,
   the median over +-6 frames (tilt.py: the frames that see the base from above and those that see it from below
   share no face, and kept their manual frames' rotations);
6. quality: figures and flags per frame (quality.py), with the final poses checked against the
   chains they came from and for jumps between frames (consistency.py), and, for objects without
   symmetry, the frames whose geometry leaves the spin about the axis free found (free_spin.py: a mug with
   its handle hidden, carried by both chains alike on the motion; done before the common frame, after the joint
   refinement and the smoothing); where the spin is free somewhere, the suspect and free-spin frames take the mean
   spin about the axis of the frames within +-2 (spin_window.py: they were registered one at a time, and jitter
   about the axis);
   frames in a long run of such free-spin frames, or beyond the last frame that fixes the spin, are
   flagged: only the motion carries their spin (consistency.free_spin_runs).

With ``config.registration.facing`` (the default; registration.py), the chains and the refinement pair
only model surfaces that face the camera; the chains of an object without symmetry whose placed frames'
model is nearly round (a mug) do not, where it measured worse, but its refinement does (its model of all
frames holds both sides of the mug's bottom).

Every frame before the first or after the last manual frame is also checked against the one chain that
reached it, and a frame or two left unflagged between flagged frames is flagged with them
(consistency.flagged_gaps).

Open3D runs on ``config.threads`` threads meanwhile (1 by default: reproducible figures), and the independent
work (the chains, every frame's registration in a refinement round and the first round's restarts of suspect
frames, the rechecks, the slides, a model's crops, the smoothing's information matrices and
the document's in-box shares) on ``config.workers`` forked processes (workers.py): the same poses for any count
(ranges under ``MIN_FRAMES_FOR_WORKERS`` frames, and the refinement of one frame, run on one process). After the
chains, a large object's frames (a laptop's) are each cropped once, a little wider, and their later crops cut from
that (FrameStore.hold; ``LARGE_BODY_AREA_M2``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, NamedTuple

import numpy as np

from annotate.depth_agreement import AGREEMENT_TOLERANCE, agreement_figures
from annotate.engines import anchor_correction, anchor_frames, anchored_pose, kept_by_a_person
from annotate.estimator.model import is_revolution
from sequences.annotation import Annotation, FramePose
from sequences.reader import Sequence
from sequences.timing import at_colour_time, at_depth_time

from .config import TrackingConfig, scaled_to
from .consistency import chain_departures, flagged_gaps, flags_grown, free_spin_runs, rotation_jumps
from .frames import FrameStore
from .freespace import free_space_votes
from .propagate import run_chain
from .quality import CHAIN_WORDS, document_figures, in_box_share, rotation_angle_deg
from .registration import open3d_threads
from .reconcile import blend_chains, chain_frame_offsets, common_correction
from .free_spin import FreeSpinCheck
from .faces import box_like, face_rotation, hinge_rotation, tilt_onto_axis
from .model import ObjectModel
from .refine import build_model, coarse_round, min_hits_for, recheck_disagreements, recheck_single_chains, refine_all, repair_flips, reregister_suspects, smooth_refined, suspect, trusted_model, undo_smoothing_bends
from .slide import against_the_motion, shifted, slide_corrections
from .spin_window import windowed_spins
from annotate.symmetry_axis import fit_axis_point, fit_symmetry_axis, snap_upright
from .tilt import each_frame_untilted
from .tracker import FrameResult, Tracker
from annotate.workers import ordered_map

Progress = Callable[[int, int], None]


#: Shorter ranges track on one process: forking and gathering cost about 30 ms per parallel step, which a short
#: range does not win back.
MIN_FRAMES_FOR_WORKERS = 40

#: A large body: the box's two largest sides span at least this (m^2; a laptop, 0.35 x 0.34 m). After the chains, its
#: frames' crops are cut from one wider crop per frame (FrameStore.hold): a crop's cost grows with the pixels the box
#: covers (a laptop's ~1.9 ms for 13,000 pixels; a mug's ~0.5 ms); smaller objects gain nothing from it, and a mug's
#: spin moves with its crops.
LARGE_BODY_AREA_M2 = 0.05


class _Steps:
    """Counts work units and reports (done, total) to an optional callback."""

    def __init__(self, total: int, progress: Progress | None) -> None:
        self.total, self.done, self.progress = total, 0, progress
        self._phase_end = 0  # where the current phase's units end (:meth:`phase`)

    def __call__(self) -> None:
        self.done += 1
        if self.progress is not None:
            self.progress(self.done, self.total)

    def phase(self, units: int) -> Progress:
        """A (done, total) callback for a phase worth ``units`` of the total: it advances this count in proportion,
        and the phase's units are counted in full once the next phase begins (or :meth:`finish_phase`)."""
        self.finish_phase()
        start = self.done
        self._phase_end = start + units

        def advance(done: int, total: int) -> None:
            target = start + (units * done) // max(total, 1)
            while self.done < min(target, self._phase_end):
                self()

        return advance

    def finish_phase(self) -> None:
        """Count the rest of the current phase's units (a phase whose work turned out smaller or empty)."""
        while self.done < self._phase_end:
            self()


def _run_chains(tracker: Tracker, jobs: list[tuple[list[str], np.ndarray]], workers: int, steps: _Steps) -> list[dict[str, FrameResult]]:
    """``run_chain`` for each (frames, start pose) of ``jobs``, on up to ``workers`` processes; progress per chain."""

    def done(job, _result) -> None:
        for _ in job[0][1:]:
            steps()

    return ordered_map(lambda job: run_chain(tracker, job[0], job[1]), jobs, workers, done)


def _ordered_range(sequence: Sequence, frames: list[str] | None) -> list[str]:
    ids = sequence.ids
    if frames is None:
        return ids
    wanted = {str(f) for f in frames}
    unknown = wanted - set(ids)
    if unknown:
        raise ValueError(f"frames not in the sequence: {sorted(unknown)[:5]}")
    return [f for f in ids if f in wanted]


def _anchors(annotation: Annotation, ids: list[str]) -> list[str]:
    """The boxes a person placed, refined or accepted (annotate.engines.anchor_frames), else every posed frame."""
    kept = anchor_frames(annotation, ids)
    if kept:
        return kept
    return [f for f in ids if f in annotation.frames]


class _AxisFit(NamedTuple):
    """The symmetry axis fitted to a model: unit direction and point (object frame, m) and how ill-conditioned
    the fit of its direction is (symmetry_axis.fit_symmetry_axis)."""

    axis: np.ndarray
    point: np.ndarray
    conditioning: float


def _fit_axis(tracker: Tracker, model: ObjectModel) -> _AxisFit | None:
    """The axis fitted to ``model``'s points, or None where too few points or the fit fails."""
    points, _ = model.points(min_hits_for(model, tracker.config))
    try:
        axis, point, _, conditioning = fit_symmetry_axis(points, normal_radius=4 * tracker.config.voxel_size)
    except ValueError:
        return None
    return _AxisFit(axis, point, float(conditioning))


def _nearly_sphere(fit: _AxisFit | None, config: TrackingConfig) -> bool:
    """Whether the shape itself leaves its axis undetermined (a shallow bowl: the fit is ill-conditioned); not a
    fit that failed or went wrong for other reasons (too few points, a hand), which keeps the placed boxes' tilt."""
    return fit is not None and fit.conditioning > config.max_axis_conditioning


def _usable_axis(fit: _AxisFit | None, config: TrackingConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """(direction, point) of ``fit``, or None where it is unreliable: too ill-conditioned, or more than 10 deg off
    the box's y."""
    if fit is None or _nearly_sphere(fit, config):
        # the shape does not pin the axis down (a shallow bowl, an ill-conditioned mug body): the placed boxes' mean
        # tilt is better
        return None
    if not _near_box_y(fit):
        return None
    return fit.axis, fit.point


def _near_box_y(fit: _AxisFit) -> bool:
    """Whether the fitted axis lies within 10 deg of the box's y: a larger turn means the fit went wrong (a hand, a
    partial view), not that the placed boxes are 10 deg off."""
    return bool(np.degrees(np.arccos(np.clip(fit.axis[1], -1, 1))) <= 10.0)


def _snap_symmetric(tracker: Tracker, fit: _AxisFit | None) -> np.ndarray | None:
    """Correction (4x4) putting the box's y on the symmetry axis of ``fit``, or None if unreliable."""
    fitted = _usable_axis(fit, tracker.config)
    if fitted is None or np.linalg.norm(fitted[1]) > 0.25 * np.max(tracker.extents):
        return None
    return snap_upright(np.eye(4), *fitted)


def _flat_axis_shift(tracker: Tracker, model: ObjectModel, flat: np.ndarray) -> np.ndarray | None:
    """Correction (4x4, a translation across y) moving the box centre onto the symmetry axis along the box's y once
    ``flat`` (4x4, a rotation about the centre: _snap_flat) turned ``model`` (object frame before it), or None where
    the fit fails, moves it further than ``config.max_axis_shift_m`` (then the fit is not the object's), or the model is
    no surface of revolution about that axis (estimator.model.is_revolution: a square bowl)."""
    config = tracker.config
    target = model.target(min_hits_for(model, config))
    turn = flat[:3, :3]
    points = (target.points - flat[:3, 3]) @ turn  # the object frame after the snap: turn^T (p - t)
    normals = np.asarray(target.cloud.normals) @ turn
    point = _axis_of_revolution(points, normals, config.voxel_size)
    if point is None or np.linalg.norm(point) > config.max_axis_shift_m:
        return None  # a square bowl's normal lines meet nowhere in particular: its box centre is the placed boxes'
    shift = np.eye(4)
    shift[:3, 3] = point  # its y is 0: the axis point nearest the centre
    return shift


def _rotation_snap(rotation: np.ndarray, config: TrackingConfig) -> np.ndarray | None:
    """The correction (4x4, about the box centre) for a model whose normals ``rotation`` (3x3) turns onto the
    object axes, or None where that turn exceeds ``max_face_snap_deg`` (a larger one means the faces are not the
    frame's)."""
    if rotation_angle_deg(np.eye(3), rotation) > config.max_face_snap_deg:
        return None
    snap = np.eye(4)
    snap[:3, :3] = rotation.T  # the normals n turn to rotation @ n: the object frame turns by its inverse
    return snap


def _snap_flat(tracker: Tracker, model: ObjectModel) -> np.ndarray | None:
    """Correction (4x4, a rotation about the box centre) turning the box's y onto the normals of the model's faces
    across the axis (a bowl's foot; faces.tilt_onto_axis), or None where too few normals lie near y or the turn
    exceeds ``max_face_snap_deg``."""
    config = tracker.config
    normals = np.asarray(model.target(min_hits_for(model, config)).cloud.normals)
    rotation, count = tilt_onto_axis(normals, config.flat_cone_deg)
    if rotation is None or count < config.min_flat_share * len(normals):
        return None
    return _rotation_snap(rotation, config)


def _snap_body_axis(tracker: Tracker, model: ObjectModel) -> np.ndarray | None:
    """Correction (4x4) turning the box's y onto the axis of a near-round body fitted to ``model`` (a mug's body: its
    handle an outlier to the fit), about the box centre; None where the fit is not reliable."""
    fitted = _usable_axis(_fit_axis(tracker, model), tracker.config)
    if fitted is None:
        return None
    snap = snap_upright(np.eye(4), *fitted)
    snap[:3, 3] = 0.0  # the box centre is off the body's axis (the handle): it stays where it is
    return snap


def _axis_of_revolution(points: np.ndarray, normals: np.ndarray, voxel: float) -> np.ndarray | None:
    """The point (3,; its y 0) of the axis along y where the normal lines of ``points`` (N, 3, object frame) meet
    (symmetry_axis.fit_axis_point), where the wall is a surface of revolution about it (estimator.model.is_revolution);
    None where the fit fails or the wall is not (a square bowl, a box, a banana)."""
    try:
        point, _ = fit_axis_point(points, normals, np.array([0.0, 1.0, 0.0]))
    except ValueError:
        return None
    return point if is_revolution(points, normals, voxel, np.array([0.0, 0.0, point[0], point[2]])) else None


def _revolves(tracker: Tracker, model: ObjectModel) -> bool:
    """Whether ``model``'s wall is a surface of revolution about the box's y (:func:`_axis_of_revolution`)."""
    target = model.target(min_hits_for(model, tracker.config))
    return _axis_of_revolution(target.points, np.asarray(target.cloud.normals), tracker.config.voxel_size) is not None


def _snap_faces(tracker: Tracker, model: ObjectModel) -> np.ndarray | None:
    """Correction (4x4, a rotation about the box centre) turning the box onto the faces of ``model`` (faces.py), or
    None where the model is not box-like or the turn exceeds ``max_face_snap_deg``."""
    config = tracker.config
    normals = np.asarray(model.target(min_hits_for(model, config)).cloud.normals)
    rotation, counts = face_rotation(normals)
    if rotation is None or not box_like(counts, len(normals), config.min_face_share, config.min_faces_total):
        return None
    return _rotation_snap(rotation, config)


def _snap_hinge(tracker: Tracker, model: ObjectModel) -> np.ndarray | None:
    """Correction (4x4, a rotation about the box centre) turning the box onto a hinged body's faces (a laptop's base
    onto y, its lid's and edges' normals into the y-z plane; faces.hinge_rotation), or None where the model's normals
    are not laid out so or the turn exceeds ``max_face_snap_deg``."""
    config = tracker.config
    normals = np.asarray(model.target(min_hits_for(model, config)).cloud.normals)
    rotation, shares = hinge_rotation(normals, config.hinge_cone_deg, config.hinge_plane_deg)
    if rotation is None or shares[1] < config.min_hinge_plane_share:
        return None
    return _rotation_snap(rotation, config)


def _nearly_round(tracker: Tracker, placed: dict[str, np.ndarray]) -> bool:
    """Whether the model of the placed frames, spun by 10 deg about its fitted axis, still fits itself
    (free_spin.FreeSpinCheck.round: a mug's body; not a laptop or a camera)."""
    points, _ = build_model(tracker, placed, len(placed), free_space=False).points(1)
    if len(points) < 30:
        return False
    try:
        return FreeSpinCheck(tracker, points).round()
    except ValueError:
        return False


def free_spin_frames(tracker: Tracker, results: dict[str, FrameResult], model: ObjectModel) -> tuple[set[str], tuple[np.ndarray, np.ndarray] | None]:
    """The frames whose geometry leaves the spin about the axis of ``model`` (of the trusted frames, object frame)
    free (free_spin.py), and that axis (unit direction, point; object frame), None where none could be fitted."""
    points, _ = model.points(min_hits_for(model, tracker.config))
    try:
        check = FreeSpinCheck(tracker, points)
    except ValueError:
        return set(), None
    return set(check.free_frames({f: r.pose for f, r in results.items() if r.ok})), (check.axis, check.point)


def track_sequence(
    sequence: Sequence,
    annotation: Annotation,
    frames: list[str] | None = None,
    config: TrackingConfig | None = None,
    progress: Progress | None = None,
) -> Annotation:
    """A new document with a pose for every frame of ``frames`` (default: all), from its manual frames.

    The anchors (boxes a person placed, refined or accepted) keep their source; each takes its estimated pose where
    that lies within ``max_manual_correction_deg`` / ``_m`` of the person's box, which stays in the document as the
    anchor of later runs (engines.anchored_pose), else keeps the box and is flagged. The others get ``source:
    tracked`` with quality figures as extra keys, and ``flagged: true`` plus ``flag_reason`` where a figure is beyond
    the configured thresholds. Raises ValueError when the range holds no posed frame.
    """
    config = scaled_to(config or TrackingConfig(), annotation.extents, annotation.symmetry == "y")
    with open3d_threads(config.threads):
        return _track(sequence, annotation, frames, config, progress)


def _suspects(results: dict[str, FrameResult], ids: list[str], config: TrackingConfig) -> frozenset[str]:
    """The frames of ``ids`` whose registration failed or whose chains disagree (refine.suspect)."""
    return frozenset(f for f in ids if suspect(results[f], config))


def _track(sequence: Sequence, annotation: Annotation, frames: list[str] | None, config: TrackingConfig, progress: Progress | None) -> Annotation:
    ids = _ordered_range(sequence, frames)
    anchors = _anchors(annotation, ids)
    if not anchors:
        raise ValueError("no frame in the range has a box: place a box in at least one frame first")
    if len(ids) < MIN_FRAMES_FOR_WORKERS:
        config = replace(config, workers=1)
    symmetric = annotation.symmetry == "y"
    tracker = Tracker(FrameStore(sequence, config.stride, colors=config.backend == "colored"), annotation.extents, symmetric, config)
    placed = {m: annotation.frames[m].placed_matrix for m in anchors}  # the person's boxes, where a run moved them
    chaining = tracker  # the chains' tracker; the joint refinement and all after it use ``tracker`` (see step 4)
    nearly_round = not symmetric and _nearly_round(tracker, placed)
    if config.registration.facing and nearly_round:
        # pairing only same-facing surfaces lets a mug's chains lose its spin where the handle is hidden, while it
        # helps every other shape; and so does following frames below min_fitness (propagate.follows), while it keeps
        # the other shapes' chains on the object
        chaining = Tracker(tracker.store, annotation.extents, symmetric, replace(config, registration=replace(config.registration, facing=False),
                                                                                 chain_follow_fitness=config.min_fitness))
        # its refinement's fitness counts all pairs, as its chains' does: counted on the facing pairs alone, a mug
        # held in the hand falls below min_fitness in frames that then leave the carving, and the hand space only
        # they see free stays in the mesh
        tracker = Tracker(tracker.store, annotation.extents, symmetric, replace(config, registration=replace(config.registration, facing_figures=False)))
    position = {f: i for i, f in enumerate(ids)}
    a_idx = [position[m] for m in anchors]
    chain_frames = (a_idx[0]) + (len(ids) - 1 - a_idx[-1]) + sum(2 * (b - a) for a, b in zip(a_idx, a_idx[1:]))
    large = float(np.prod(np.sort(tracker.box)[1:])) >= LARGE_BODY_AREA_M2
    rounds = config.global_rounds + (1 if config.coarse_voxel() is not None else 0)
    # the checks after the joint refinement (the recheck of the frames whose chains disagreed, the slides) count a
    # frame's worth each: a laptop spent a third of its run in them with the bar already full
    steps = _Steps(chain_frames + rounds * len(ids) + 2 * len(ids), progress)

    # 2-3: chains from every anchor, brought into anchor 0's object frame, and reconciled
    results: dict[str, FrameResult] = {}
    chain_poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # both chains' poses, anchor 0's object frame
    workers = config.worker_count()
    if workers > 1:
        # every frame read here once, before the first fork: the workers inherit the images (and any read error)
        # instead of each reading them again
        tracker.store.preload(ids, workers)
    # the chains are independent of each other: each on its own process where there are several cores
    segments = [ids[a : b + 1] for a, b in zip(a_idx, a_idx[1:])]
    chains = _run_chains(chaining, [job for s in segments for job in ((s, placed[s[0]]), (s[::-1], placed[s[-1]]))], workers, steps)
    forwards, backwards = chains[0::2], chains[1::2]
    frames_of = chain_frame_offsets(anchors, placed, forwards, backwards, symmetric, (config.manual_rotation_sigma_deg, config.manual_translation_sigma))
    for k, m in enumerate(anchors):
        results[m] = FrameResult(placed[m] @ frames_of[k], True, {})
    for k, (a, b) in enumerate(zip(a_idx, a_idx[1:])):
        forward = {f: FrameResult(r.pose @ frames_of[k], r.ok, r.figures) for f, r in forwards[k].items()}
        backward = {f: FrameResult(r.pose @ frames_of[k + 1], r.ok, r.figures) for f, r in backwards[k].items()}
        blended = blend_chains(ids[a : b + 1], forward, backward, symmetric, config.max_chain_disagreement_deg, config.max_chain_disagreement_m,
                               anchors=(results[ids[a]].pose, results[ids[b]].pose))
        results.update(blended)
        for f in ids[a + 1 : b]:
            if forward[f].ok and backward[f].ok:
                # both chains witness the frame, also where the blend switched to one of them: the switch
                # may have picked the lost chain, and with it as the only witness no rival is found and the frames
                # lose their flag
                chain_poses[f] = (forward[f].pose, backward[f].pose)
    outer = []  # before the first and after the last manual frame
    if a_idx[0] > 0:
        outer.append((ids[a_idx[0] :: -1], results[anchors[0]].pose))
    if a_idx[-1] < len(ids) - 1:
        outer.append((ids[a_idx[-1] :], results[anchors[-1]].pose))
    for chain in _run_chains(chaining, outer, workers, steps):
        results.update(chain)
    results = {f: results[f] for f in ids}

    # 4: joint refinement against the model of all frames, pairing only facing surfaces even where the chains
    # did not: the model of all frames holds both sides of a thin wall, and a mug seen from above paired its inner
    # bottom with the outer one and slid along its axis by the bottom's thickness
    chained = {f: r.pose for f, r in results.items()}
    if large:
        # from here on a frame is cropped at poses a few millimetres apart, many times: each once, a little wider,
        # and then cut from that (FrameStore.hold)
        for voxel in [v for v in (config.voxel_size, config.coarse_voxel()) if v is not None]:
            tracker.store.hold([(f, chained[f]) for f in ids], tracker.box, voxel, workers)
    results = coarse_round(tracker, results, anchors, steps)
    results = refine_all(tracker, results, config.global_rounds, anchors, steps, (config.settled_deg, config.settled_m), origin=chained)
    # a frame the refinement left turned over (a bottle upside down) is brought back before the smoothing averages it in
    results = repair_flips(tracker, results, anchors)
    # flags follow the final pose: where the chains disagreed, does the whole model pin the frame down?
    results = recheck_disagreements(tracker, results, chain_poses, anchors, steps.phase(len(ids)))
    if config.smoothing:
        smoothed = smooth_refined(tracker, results, anchors, placed if config.manual_rotation_sigma_deg > 0 and config.manual_translation_sigma > 0 else None, chained)
        # a long run of frames without evidence is bent by the smoothing alone: where the refined pose fits clearly
        # better, it stays (refine.undo_smoothing_bends)
        results = undo_smoothing_bends(tracker, results, smoothed, anchors)
    # before the first and after the last manual frame only one chain ran: a second one, on the whole model
    ends = []
    if a_idx[0] > 0 and a_idx[0] + 1 < len(ids):
        ends.append(ids[a_idx[0] + 1 :: -1])
    if a_idx[-1] < len(ids) - 1 and a_idx[-1] > 0:
        ends.append(ids[a_idx[-1] - 1 :])
    check_spin = not symmetric  # a symmetric object's spin is no error
    # one model of the trusted frames judges the second chains, the suspect frames, the slides and the free spins
    trusted = trusted_model(tracker, results, anchors) if ends or check_spin or config.slide_check else None
    results = recheck_single_chains(tracker, results, ends, anchors, trusted)
    # the frames whose chains disagreed, against the model that holds none of their own points (refine.reregister_suspects)
    results = reregister_suspects(tracker, results, trusted, set(placed)) if trusted is not None else results
    # a flat object slides along its faces unseen by the ICP: the fitness on a wider crop sees it (slide.py)
    sliding = steps.phase(len(ids))
    slides = slide_corrections(tracker, results, trusted.target(min_hits_for(trusted, config)), set(anchors), sliding) if trusted is not None else {}
    steps.finish_phase()
    # ... unless the slide takes the frame off the path of its neighbours: it is then flagged for review instead
    lone = against_the_motion(results, slides, config.slide_path_tolerance, _suspects(results, ids, config))
    results = dict(results)
    for frame_id, shift in slides.items():
        r, metres = results[frame_id], float(np.linalg.norm(shift))
        if frame_id in lone:
            results[frame_id] = FrameResult(r.pose, r.ok, {**r.figures, "slide_rejected_m": metres})
        else:
            results[frame_id] = FrameResult(shifted(r.pose, shift), r.ok, {**r.figures, "slide_m": metres})
    # a spin the geometry leaves free (a mug's handle hidden) is carried by both chains alike, on the motion alone
    free, spin_axis = free_spin_frames(tracker, results, trusted) if check_spin and trusted is not None else (set(), None)
    if free and spin_axis is not None and config.spin_window > 0:
        # where the shape leaves the spin free somewhere (a mug whose handle hides), each suspect or free-spin frame took
        # its spin from its own registration, one frame at a time: consecutive frames jitter about the axis, which
        # the hand turns smoothly (spin_window.py)
        chosen = [f not in placed and (f in free or suspect(results[f], config)) for f in ids]
        # about the body's axis, fitted to the model of the trusted frames
        steadied = windowed_spins([results[f].pose for f in ids], chosen, config.spin_window, *spin_axis, [results[f].ok for f in ids])
        results = {f: FrameResult(p, results[f].ok, results[f].figures) for f, p in zip(ids, steadied)}
    # where the spin is free and so is that of its neighbours, only the motion carries it: how long such a run is
    runs = free_spin_runs(ids, free, set(anchors))
    # the final pose must stay near one of the chains it came from (both in anchor 0's object frame)
    # (before the first and after the last manual frame, one chain ran: its pose is the only witness)
    single = {f: (chained[f],) for f in ids if f not in chain_poses and f not in placed}
    departures = chain_departures({f: r.pose for f, r in results.items()}, {**chain_poses, **single}, symmetric)

    # 5: one object frame for all, fitted to the placed boxes
    poses = {f: r.pose for f, r in results.items()}
    correction = common_correction({m: poses[m] for m in anchors}, placed, symmetric, {m for m in anchors if m in free})
    poses = {f: p @ correction for f, p in poses.items()}
    if symmetric and config.symmetry_snap:
        model = build_model(tracker, poses, config.max_global_frames, anchors)
        fit = _fit_axis(tracker, model)
        snap = _snap_symmetric(tracker, fit)
        flat = None
        if snap is None and _nearly_sphere(fit, config) and config.flat_snap:
            # the shape leaves its axis undetermined (a shallow bowl: nearly a sphere), but its foot and inner bottom
            # face along it, which the placed boxes' mean tilt does not (faces.tilt_onto_axis); a fit refused for
            # other reasons (a hand, too few points) keeps that tilt: a can's ends measured worse than its side
            snap = flat = _snap_flat(tracker, model)
        if snap is not None:
            poses = {f: p @ snap for f, p in poses.items()}
        if flat is not None and config.flat_axis_centring:
            # ... and its centre onto the axis along that y: a sphere's normal lines all meet at its centre, so the
            # direction they leave free, not the axis's place (symmetry_axis.fit_axis_point)
            shift = _flat_axis_shift(tracker, model, flat)
            if shift is not None:
                poses = {f: p @ shift for f, p in poses.items()}
        if flat is not None and config.frame_tilt:
            # ... and each frame's own tilt, which its registration leaves to the curved wall (tilt.py); not measured
            # on the suspect frames (see the round body's below)
            poses = each_frame_untilted(tracker, ids, poses, skip=_suspects(results, ids, config))
    elif not symmetric and (config.face_snap or config.hinge_snap or (nearly_round and config.body_axis_snap)):
        model = build_model(tracker, poses, config.max_global_frames, anchors)
        # a round body's axis and foot say its tilt only where its wall is a surface of revolution (a mug's: its handle
        # an outlier at the median); a box or a banana that passed the roundness test has neither
        round_body = nearly_round and _revolves(tracker, model)
        # a box-like body (a camera): its faces fix the rotation better than the placed boxes' mean tilt (faces.py;
        # cameras pass the roundness test too, so the faces are asked first)
        snap = _snap_faces(tracker, model) if config.face_snap else None
        faced = snap is not None
        hinged = False
        if snap is None and config.hinge_snap and not nearly_round:
            snap = _snap_hinge(tracker, model)
            hinged = snap is not None
        if snap is None and round_body and config.body_axis_snap:
            # the placed boxes' mean tilt is off by their errors' mean; the body's axis, fitted to the model, is not
            # (refused where the fit is ill-conditioned)
            snap = _snap_body_axis(tracker, model)
        if snap is not None:
            poses = {f: p @ snap for f, p in poses.items()}
        if round_body and not hinged and not faced and config.frame_tilt:
            # ... and each frame's own tilt from its foot and inner bottom, as a bowl's (tilt.py): the snap turns all
            # frames alike, and is refused where the body's fit is ill-conditioned
            # (not measured on the suspect frames: a frame centimetres off measures a tilt that is not the object's,
            # and the window's median would carry it to its trusted neighbours)
            poses = each_frame_untilted(tracker, ids, poses, skip=_suspects(results, ids, config))
        if hinged and config.frame_hinge_tilt:
            # ... and each frame's own rotation from its base's and lid's faces: the snap turns all frames alike, but
            # the frames that see the base from above and those that see it from below share no face, and their
            # rotations differ by what their manual frames brought (tilt.py)
            poses = each_frame_untilted(tracker, ids, poses, hinged=True, every=config.hinge_tilt_every)

    # 6: the document, its poses at the colour instants (the registrations' are at the depth ones: sequences.timing)
    at_colour = at_colour_time(sequence, {f: poses[f] for f in ids})
    # an anchor whose box lies within the placement's tolerance of its estimate takes the estimate: the object frame
    # is one, fitted to all the placed boxes (and snapped onto the shape), and each box is off by its own error
    corrections = {f: anchor_correction(placed[f], at_colour[f], symmetric) for f in placed}
    follows = {f: results[f].ok and deg <= config.max_manual_correction_deg and metres <= config.max_manual_correction_m
               for f, (deg, metres) in corrections.items()}
    kept = [placed[f] if f in placed and not follows[f] else at_colour[f] for f in ids]
    jumps = dict(zip(ids, rotation_jumps(kept, symmetric)))
    out = annotation.copy()
    # each frame's share of points in its final box, on the workers (a crop each)
    seen = [f for f in ids if results[f].ok]
    in_box = dict(zip(seen, ordered_map(lambda f: in_box_share(tracker.crop(f, poses[f])[0], poses[f], tracker.box), seen, workers)))
    for frame_id in ids:
        result = results[frame_id]
        figures = dict(result.figures)
        if frame_id in departures:
            figures["chain_departure_deg"], figures["chain_departure_m"] = departures[frame_id]
        figures["rotation_jump_deg"] = float(jumps[frame_id])
        if frame_id in runs:
            figures["free_spin_run"], figures["free_spin_end"] = runs[frame_id]
        if result.ok:
            figures["in_box"] = in_box[frame_id]
        if frame_id in placed:
            figures["manual_correction_deg"], figures["manual_correction_m"] = corrections[frame_id]
        figures = document_figures(figures, config)
        if frame_id in placed and kept_by_a_person(annotation.frames[frame_id]):
            old = annotation.frames[frame_id]
            extra = {k: v for k, v in old.extra.items() if k not in ("flagged", "flag_reason", "flag_spin_only")}
            extra.update(figures)
            out.frames[frame_id] = anchored_pose(old, at_colour[frame_id], extra, follows[frame_id])
        else:
            out.frames[frame_id] = FramePose.from_matrix(at_colour[frame_id], "tracked", figures)
    flagged = {f for f in ids if out.frames[f].extra.get("flagged")}
    tracked = {f for f in ids if out.frames[f].source == "tracked"}
    if config.flag_hysteresis > 0:
        limits = {"chain_disagreement_deg": config.max_chain_disagreement_deg, "chain_disagreement_m": config.max_chain_disagreement_m,
                  "chain_departure_deg": config.max_chain_departure_deg}
        grown = flags_grown(ids, flagged, tracked, {f: out.frames[f].extra for f in ids}, limits, config.flag_hysteresis, config.max_flag_gap)
        for frame_id, (beside, key, value, limit) in grown.items():
            extra = out.frames[frame_id].extra
            extra["flagged"] = True
            extra["flag_reason"] = f"beside flagged frame {beside}, {CHAIN_WORDS[key](value)}, {value / limit:.0%} of the limit"
        flagged |= set(grown)
    for frame_id, (before, after) in flagged_gaps(ids, flagged, tracked, config.max_flag_gap).items():
        extra = out.frames[frame_id].extra
        extra["flagged"] = True
        extra["flag_reason"] = f"between flagged frames {before} and {after}: its pose leans on theirs"
        if out.frames[before].extra.get("flag_spin_only") and out.frames[after].extra.get("flag_spin_only"):
            extra["flag_spin_only"] = True
    return out


def refine_frame(sequence: Sequence, annotation: Annotation, frame_id: str, config: TrackingConfig | None = None) -> FramePose:
    """Refine one frame's box against its points and the model built from the other posed frames.

    Starts from the frame's own pose, or from the nearest posed frame's when it has none. Returns a
    FramePose with ``source: refined`` and quality figures (and a flag) in ``extra``. Raises
    ValueError when the document has no pose to start from.
    """
    config = scaled_to(config or TrackingConfig(), annotation.extents, annotation.symmetry == "y")
    with open3d_threads(config.threads):
        return _refine_one(sequence, annotation, str(frame_id), config)


def _refine_one(sequence: Sequence, annotation: Annotation, frame_id: str, config: TrackingConfig) -> FramePose:
    ids = sequence.ids
    if frame_id not in ids:
        raise ValueError(f"frame {frame_id!r} is not in the sequence")
    others = [f for f in ids if f in annotation.frames and f != frame_id]
    if frame_id in annotation.frames:
        start = annotation.frames[frame_id].matrix
    elif others:
        here = ids.index(frame_id)
        start = annotation.frames[min(others, key=lambda f: abs(ids.index(f) - here))].matrix
    else:
        raise ValueError("no posed frame to start from: place a box first")
    symmetric = annotation.symmetry == "y"
    config = replace(config, workers=1)  # one frame, its model's crops included, on this process: forking would not pay
    tracker = Tracker(FrameStore(sequence, config.stride, colors=config.backend == "colored"), annotation.extents, symmetric, config)
    # the document's poses are at the colour instants; the depth is posed at its own (sequences.timing)
    at_depth = at_depth_time(sequence, {**{f: annotation.frames[f].matrix for f in others}, frame_id: start})
    if others:
        here = ids.index(frame_id)
        # the nearest posed frames in time see most of what this one sees
        nearest = sorted(others, key=lambda f: abs(ids.index(f) - here))[: config.max_global_frames // 2]
        model = build_model(tracker, {f: at_depth[f] for f in sorted(nearest, key=ids.index)}, config.max_global_frames)
        hits = min_hits_for(model, config)
    else:
        model = tracker.new_model()
        tracker.add_to_model(model, frame_id, at_depth[frame_id])  # alone: a self-consistency check of the placed box
        hits = 1
    result = tracker.register(frame_id, at_depth[frame_id], model, hits)
    figures = dict(result.figures)
    if others:  # whether the frame's depth confirms the model of the other frames where the result puts it
        through, seen = free_space_votes(model.points(hits)[0], {frame_id: result.pose}, tracker.store, AGREEMENT_TOLERANCE)
        figures.update(agreement_figures(seen.sum(), through.sum()))
    figures = document_figures(figures, config)
    to_colour = np.linalg.inv(at_depth[frame_id]) @ start  # the motion from the depth instant to the colour one
    return FramePose.from_matrix(result.pose @ to_colour, "refined", figures)
