"""From a few boxes a person placed to a pose in every frame: chains, one pose graph, and rounds against the model.

``track_sequence``:
1. anchors: every frame whose box a person placed, refined or accepted;
2. front end: from each anchor a chain runs forward and backward to the next anchor (or the end); each frame is
   cropped at the pose the chain predicts (constant velocity), and registered to the model of the anchor's and the
   chain's last frames; consecutive registered frames give a chain step (their relative pose, its information);
3. back end: one pose graph of the chain steps, the anchors and the motion prior (graph.py), then the common
   correction that best fits the anchors (the object frame is theirs; the data fix only poses relative to it);
4. rounds: the model of all frames is fused at the solved poses, without what other frames see through (a hand),
   and for symmetry y spun about its own axis where it is a body of revolution; every frame is registered to it, and
   the graph solved again with those registrations; until no frame moves more than ``settled`` or ``rounds`` are
   done;
5. flags from the estimate: the registration's fitness, the graph's marginal standard deviation, and how far the
   graph pulled the frame from its registration, each with its reason in words;
6. the anchors take their solved poses within ``ANCHOR_TOLERANCE_SIGMAS`` of their placed boxes (one rigid object
   frame: each placed box is off by its own error), the boxes kept beside them as the anchors of later runs.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from annotate.depth_agreement import AGREEMENT_TOLERANCE, agreement_figures, agreement_reason
from annotate.engines import anchor_correction, anchor_frames, anchored_pose
from sequences.annotation import Annotation, FramePose
from sequences.reader import Sequence
from sequences.timing import at_depth_time

from annotate.workers import ordered_map, resolve

from .config import EstimatorConfig
from .graph import Factor, Solution, sigmas, solve
from .model import fuse, fused_model, revolution_axis, revolved, seen_through
from .observations import Crop, FrameCrops
from .registration import Model, Registration, register, retract
from .review import flag_weak_runs, frame_figures
from .timing import colour_offsets, shifted, velocities

Progress = Callable[[int, int], None]

#: shorter ranges run on one process: forking and gathering cost about 30 ms a map
MIN_FRAMES_FOR_WORKERS = 40
#: a frame is registered, and cropped again at the result, at most this many times ...
CROP_PASSES = 3
#: ... until the registration moves it less than this (deg, m): the crop then holds the same points
RECROP_DEG, RECROP_M = 0.5, 0.001
#: a round registers the frames of each of this many contiguous blocks to the model of the others
ROUND_BLOCKS = 4
#: for symmetry y, a model's axis fitted further from the object's y than this many anchor sigmas is no axis
AXIS_SIGMAS = 3.0
#: an anchor takes its solved pose where it lies within this many anchor sigmas of the placed box (rotation and centre
#: each), else keeps the box and is flagged: the annotator should look
ANCHOR_TOLERANCE_SIGMAS = 2.0
#: a chain closing within this many anchor sigmas (degrees over their sigma plus millimetres over theirs) is trusted
#: fully: two boxes each off by one sigma, in opposite directions, close at 4
CLOSURE_SIGMAS = 4.0


def _ordered_range(sequence: Sequence, frames: list[str] | None) -> list[str]:
    if frames is None:
        return list(sequence.ids)
    wanted = {str(f) for f in frames}
    return [f for f in sequence.ids if f in wanted]


def _object_part(crop: Crop, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A crop's points and normals in the object frame of ``pose``."""
    return (crop.points - pose[:3, 3]) @ pose[:3, :3], crop.normals @ pose[:3, :3]


class _Setup:
    """What every step reads: the crops, the box grown for cropping, the frame order and the settings."""

    def __init__(self, sequence: Sequence, annotation: Annotation, ids: list[str], config: EstimatorConfig) -> None:
        self.config, self.ids = config, ids
        self.index = {f: k for k, f in enumerate(ids)}
        self.crops = FrameCrops(sequence, config.stride, config.voxel_for(annotation.extents))
        self.half = np.asarray(annotation.extents, dtype=np.float64) / 2 * (1 + config.crop_slack) + config.crop_margin
        self.symmetric = annotation.symmetry == "y"
        self.offsets = colour_offsets(sequence, ids)
        # forked workers read the frames the parent read before the fork: read them all first
        self.workers = 1 if len(ids) < MIN_FRAMES_FOR_WORKERS else resolve(config.workers)
        if self.workers > 1:
            for frame_id in ids:
                self.crops.depth(frame_id)
            # and their scene planes: each map's workers would otherwise find them again
            self.crops.keep_planes(dict(zip(ids, ordered_map(self.crops.planes, ids, self.workers))))
        #: a registration's pull towards the pose it starts from: the motion sigma (the start is a prediction)
        self.motion_prior = np.diag(1.0 / sigmas(config.motion_sigma_deg, config.motion_sigma_m) ** 2)

    def at_depth(self, anchors: dict[int, np.ndarray], poses: np.ndarray) -> dict[int, np.ndarray]:
        """The anchors' boxes (placed on colour frames) moved to their depth frames' times along ``poses``' motion."""
        if not np.any(self.offsets):
            return anchors
        xi = velocities(poses)
        return {k: retract(placed, -xi[k] * self.offsets[k]) for k, placed in anchors.items()}

    def crop(self, frame_id: str, pose: np.ndarray, thin: bool = True) -> Crop:
        return self.crops.crop(frame_id, pose, self.half, self.config.max_points if thin else 0, seed=self.index[frame_id])

    def register(self, frame_id: str, start: np.ndarray, model: Model) -> tuple[Registration, Crop]:
        """The frame registered to ``model`` from ``start``, its crop following the box: cropped again where the
        registration moved it (at most CROP_PASSES times): a crop at a pose degrees off holds what lies beside the
        object there (a hand, the table) and misses part of it, and those points hold the pose back."""
        pose = start
        for passes in range(CROP_PASSES):
            crop = self.crop(frame_id, pose)
            result = register(crop, model, pose, self.config, self.motion_prior, coarse=passes == 0)
            degrees, metres = _moved(pose[None], result.pose[None])
            pose = result.pose
            if degrees < RECROP_DEG and metres < RECROP_M:
                break
        return result, crop


def _chain_model(setup: _Setup, members: list[tuple[str, np.ndarray, Crop]]) -> Model:
    """The model of a chain's ``members`` ((frame id, pose, camera-frame crop) each: its anchor and last frames), as
    the rounds' model: without the voxels those frames see through in more than ``max_free_share`` of the frames that
    see them (a hand that slid along the object, the table it was lifted from)."""
    config = setup.config
    return fused_model(setup.crops, {f: pose for f, pose, _ in members}, {f: (c.points, c.normals) for f, _, c in members},
                       config.free_space_tolerance, config.max_free_share)


def _chain(setup: _Setup, start: str, placed: np.ndarray, order: list[str], anchor_crop: Crop, done: Callable[[], None]) -> tuple[dict[str, np.ndarray], list[Factor]]:
    """Poses along ``order`` from the anchor ``start`` (pose ``placed``, its crop ``anchor_crop``), and the chain steps
    between registered frames.

    The chain's model holds its anchor's points at the placed pose and the chain's last frames (:func:`_chain_model`).
    Not the other anchors' points: each box is off by its own few degrees, so their points, fused at the placed
    poses, disagree with each other, and a frame registered to them lands between them, biasing the step from the
    anchor by the boxes' disagreement, not by the object's motion."""
    config = setup.config
    anchor = (start, placed, anchor_crop)
    recent: deque = deque(maxlen=config.chain_model_frames)  # (frame id, pose, crop) of the chain's last frames
    model = fuse([_object_part(anchor_crop, placed)], setup.crops.voxel)  # the free-space test needs other frames
    poses, steps = {}, []
    last_id, last_pose = start, placed
    previous, before = placed, None
    for frame_id in order:
        predicted = previous if before is None else carried(previous, before)
        result, crop = setup.register(frame_id, predicted, model)
        if result.ok and result.fitness >= config.min_fitness / 2:
            pose = result.pose
            steps.append(Factor(setup.index[last_id], setup.index[frame_id], np.linalg.inv(last_pose) @ pose, result.information))
            last_id, last_pose = frame_id, pose
            recent.append((frame_id, pose, crop))
            model = _chain_model(setup, [anchor, *recent])
        else:
            pose = predicted  # the object lost (hidden, out of view): the motion carries the chain on
        before, previous = previous, pose
        poses[frame_id] = pose
        done()
    return poses, steps


def carried(last: np.ndarray, before: np.ndarray) -> np.ndarray:
    """The pose (4x4) one frame after ``last`` at constant velocity, the motion from ``before`` to ``last`` once more."""
    return (last @ np.linalg.inv(before)) @ last


def _closure(setup: _Setup, start: np.ndarray, poses: dict[str, np.ndarray], order: list[str], target: np.ndarray) -> float:
    """How far a chain from the anchor at ``start`` (its pose), carried one frame on at its last velocity, ends from
    the anchor it runs into (``target``), in anchor sigmas (rotation's and centre's summed; for symmetry y without
    the spin)."""
    last = poses[order[-1]]
    before = poses[order[-2]] if len(order) > 1 else start
    predicted = carried(last, before)
    degrees, metres = anchor_correction(target, predicted, setup.symmetric)
    return degrees / setup.config.anchor_sigma_deg + metres / setup.config.anchor_sigma_m


def _front_end(setup: _Setup, anchors: list[str], placed: dict[str, np.ndarray], done: Callable[[], None]) -> tuple[np.ndarray, list[Factor]]:
    """Initial poses (n, 4, 4) (:func:`initial_poses`) and every chain's steps."""
    ids, index = setup.ids, setup.index
    marks = [index[a] for a in anchors]
    jobs = []  # (anchor, its position, the frames its chain runs through, the anchor it runs into or None)
    for n, (a, mark) in enumerate(zip(anchors, marks)):
        after = ids[mark + 1 : marks[n + 1]] if n + 1 < len(marks) else ids[mark + 1 :]
        before = ids[marks[n - 1] + 1 : mark][::-1] if n > 0 else ids[:mark][::-1]
        into_after = anchors[n + 1] if n + 1 < len(marks) else None
        into_before = anchors[n - 1] if n > 0 else None
        jobs += [(a, mark, order, into) for order, into in ((after, into_after), (before, into_before)) if order]
    chains = ordered_map(lambda job: _chain(setup, job[0], placed[job[0]], job[2], setup.crop(job[0], placed[job[0]], thin=False), lambda: None), jobs, setup.workers,
                         done=lambda job, _: [done() for _ in job[2]])
    steps: list[Factor] = []
    runs = []
    for (a, mark, order, into), (poses, chain_steps) in zip(jobs, chains):
        closure = 0.0 if into is None else _closure(setup, placed[a], poses, order, placed[into])
        trust = chain_trust(closure)
        steps += [replace(f, weight=trust) for f in chain_steps]
        runs.append((mark, {index[f]: pose for f, pose in poses.items()}, closure))
    return initial_poses(len(ids), {index[a]: placed[a] for a in anchors}, runs), steps


def chain_trust(closure: float) -> float:
    """The weight (0-1) of a chain's steps in the graph from its closure (:func:`_closure`, anchor sigmas): full
    while the chain ends within CLOSURE_SIGMAS of the anchor it runs into, then falling with the square of the
    closure. A chain that went astray drifted by small steps that no robust kernel sees one by one; beside the chain
    that closes, it would pull the frames between them halfway to its error."""
    return min(1.0, (CLOSURE_SIGMAS / max(closure, 1e-9)) ** 2)


def initial_poses(count: int, anchors: dict[int, np.ndarray], runs: list[tuple[int, dict[int, np.ndarray], float]]) -> np.ndarray:
    """The graph's start (count, 4, 4): the anchors' boxes, and each other frame from one of the chains that reached it.

    ``runs``: per chain its anchor's position, its poses by frame position and its closure (how far it ends from the
    anchor it runs into, :func:`_closure`; 0 for a chain that runs to the sequence's end). A frame between two anchors
    is reached by two chains, whose errors grow with the distance run; the closure measures that growth, so the
    frame starts from the chain whose closure times the share of its run to the frame is the smaller (where the
    chains close alike, the nearer anchor's). A chain that went astray (a bowl turning 9 deg a frame, its tilt lost
    in a view into its dome) then starts none of the frames the other chain reached better."""
    initial = np.tile(np.eye(4), (count, 1, 1))
    expected = np.full(count, np.inf)
    for k, pose in anchors.items():
        initial[k], expected[k] = pose, 0.0
    for mark, poses, closure in runs:
        run = max(abs(k - mark) for k in poses) + 1 if poses else 1
        for k, pose in poses.items():
            score = (closure + 1e-6) * abs(k - mark) / run
            if score < expected[k]:
                initial[k], expected[k] = pose, score
    return initial


def common_correction(poses: np.ndarray, anchors: dict[int, np.ndarray], offsets: np.ndarray | None = None) -> np.ndarray:
    """``poses`` (n, 4, 4, depth time) moved by the one object-frame transform G that best fits the anchors (colour
    time) at colour time (T_a G ~ P_a): the mean rotation and the mean translation of their corrections T_a^-1 P_a."""
    at_colour = poses if offsets is None else shifted(poses, offsets)
    corrections = np.stack([np.linalg.inv(at_colour[k]) @ placed for k, placed in anchors.items()])
    G = np.eye(4)
    G[:3, :3] = Rotation.from_matrix(corrections[:, :3, :3]).mean().as_matrix()
    G[:3, 3] = corrections[:, :3, 3].mean(axis=0)
    return poses @ G


def _moved(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The largest rotation (deg) and translation (m) between two pose stacks (n, 4, 4)."""
    relative = np.linalg.inv(a) @ b
    degrees = np.degrees(np.linalg.norm(Rotation.from_matrix(relative[:, :3, :3]).as_rotvec(), axis=1))
    return float(degrees.max()), float(np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1).max())


def _round(setup: _Setup, poses: np.ndarray, done: Callable[[], None], axis: np.ndarray | None = None) -> tuple[dict[str, Registration], np.ndarray | None]:
    """Every frame registered to the model fused from the frames of the other ROUND_BLOCKS - 1 blocks of the sequence
    (contiguous), at ``poses``: a frame's own points and its neighbours', posed alike, would confirm its pose whatever
    it is; the other blocks saw the object at poses the chains reached independently. For symmetry y the models are
    spun about one fitted axis (started from ``axis``, the round before's) where they are bodies of revolution.
    Returns the registrations and that axis (None: none fitted)."""
    config, ids = setup.config, setup.ids
    at = {f: poses[setup.index[f]] for f in ids}
    parts = dict(zip(ids, ordered_map(lambda f: setup.crop(f, at[f], thin=False), ids, setup.workers)))
    blocks = np.array_split(np.arange(len(ids)), min(ROUND_BLOCKS, len(ids)))
    models, block_of = [], {}
    for b, block in enumerate(blocks):
        inside = {ids[k] for k in block}
        others = {f: (c.points, c.normals) for f, c in parts.items() if f not in inside} or {f: (c.points, c.normals) for f, c in parts.items()}
        models.append(fused_model(setup.crops, at, others, config.free_space_tolerance, config.max_free_share))
        block_of.update({f: b for f in inside})
    if setup.symmetric:  # one axis for all sides: a bowl's inside and outside, seen by different frames, tilt alike
        points, normals = np.concatenate([m.points for m in models]), np.concatenate([m.normals for m in models])
        axis = revolution_axis(points, normals, setup.crops.voxel, AXIS_SIGMAS * config.anchor_sigma_deg, AXIS_SIGMAS * config.anchor_sigma_m, axis)
        if axis is not None:
            models = [revolved(m, setup.crops.voxel, axis) or m for m in models]
    results = ordered_map(lambda f: setup.register(f, at[f], models[block_of[f]])[0], ids, setup.workers, done=lambda f, _: done())
    return dict(zip(ids, results)), axis


def _solve(setup: _Setup, initial: np.ndarray, registrations: list[Factor], steps: list[Factor], anchors: dict[int, np.ndarray]) -> Solution:
    config = setup.config
    return solve(initial, registrations, steps, anchors, sigmas(config.anchor_sigma_deg, config.anchor_sigma_m),
                 sigmas(config.motion_sigma_deg, config.motion_sigma_m), setup.symmetric, config.robust_k)


def track_sequence(
    sequence: Sequence,
    annotation: Annotation,
    frames: list[str] | None = None,
    config: EstimatorConfig | None = None,
    progress: Progress | None = None,
) -> Annotation:
    """A new document with a pose for every frame of ``frames`` (default: all) from the anchors (see the module notes).

    Anchors keep their source and take the solved pose where it lies within ``ANCHOR_TOLERANCE_SIGMAS`` anchor sigmas
    of the person's box, which stays in the document as the anchor of later runs (engines.anchored_pose); else they
    keep the box and are flagged. The other frames get ``source: tracked``, their figures as extra keys, and
    ``flagged: true`` with ``flag_reason`` where the estimate itself says it is weak. Raises ValueError when the range
    holds no anchor.
    """
    config = (config or EstimatorConfig()).check()
    ids = _ordered_range(sequence, frames)
    anchors = anchor_frames(annotation, ids)
    if not anchors:
        raise ValueError("no frame in the range has a box: place a box in at least one frame first")
    setup = _Setup(sequence, annotation, ids, config)
    placed = {a: annotation.frames[a].placed_matrix for a in anchors}  # the person's boxes, where a run moved them
    anchored = {setup.index[a]: placed[a] for a in anchors}
    total = len(ids) - len(anchors) + config.rounds * len(ids)
    count = [0]

    def done() -> None:
        count[0] += 1
        if progress is not None:
            progress(min(count[0], total), total)

    # 2-3: the chains, one graph of their steps, the anchors' frame
    initial, steps = _front_end(setup, anchors, placed, done)
    poses = common_correction(_solve(setup, initial, [], steps, setup.at_depth(anchored, initial)).poses, anchored, setup.offsets)
    # 4: rounds against the model of all frames
    registrations: dict[str, Registration] = {}
    solution, axis = None, None
    for _ in range(config.rounds):
        registrations, axis = _round(setup, poses, done, axis)
        factors = [Factor(setup.index[f], None, r.pose, r.information) for f, r in registrations.items() if r.ok]
        solution = _solve(setup, poses, factors, steps, setup.at_depth(anchored, poses))
        new = common_correction(solution.poses, anchored, setup.offsets)
        degrees, metres = _moved(poses, new)
        poses = new
        if degrees < config.settled[0] and metres < config.settled[1]:
            break
    if progress is not None:
        progress(total, total)
    # 5: the document, at the colour frames' times
    poses = shifted(poses, setup.offsets)
    out = annotation.copy()
    every = [frame_figures(poses[k], registrations.get(f), None if solution is None else solution.covariances[k], setup.symmetric, config)
             for k, f in enumerate(ids)]
    flag_weak_runs(every, np.array([f in placed for f in ids]))
    limit = (ANCHOR_TOLERANCE_SIGMAS * config.anchor_sigma_deg, ANCHOR_TOLERANCE_SIGMAS * config.anchor_sigma_m)
    for k, (frame_id, figures) in enumerate(zip(ids, every)):
        if frame_id in placed:
            old = annotation.frames[frame_id]
            extra = {key: v for key, v in old.extra.items() if key not in ("flagged", "flag_reason")}
            extra.update({key: v for key, v in figures.items() if key not in ("flagged", "flag_reason")})
            degrees, metres = anchor_correction(placed[frame_id], poses[k], setup.symmetric)
            extra["manual_correction_deg"], extra["manual_correction_m"] = round(degrees, 3), round(metres, 5)
            follows = degrees <= limit[0] and metres <= limit[1]
            if not follows:
                extra["flagged"] = True
                extra["flag_reason"] = (f"the placed box is {degrees:.1f} deg and {1000 * metres:.0f} mm off the pose the other frames "
                                        "agree on: it was kept (check it, or clear it)")
            out.frames[frame_id] = anchored_pose(old, poses[k], extra, follows)
        else:
            out.frames[frame_id] = FramePose.from_matrix(poses[k], "tracked", figures)
    return out


def refine_frame(sequence: Sequence, annotation: Annotation, frame_id: str, config: EstimatorConfig | None = None) -> FramePose:
    """One frame's box registered to the model of the nearest other posed frames (source ``refined``).

    Starts from the frame's pose, or the nearest posed frame's. Where its points do not fit the model (fitness
    below ``min_fitness``) the box is returned where it was, flagged, with the reason and what to do.
    Raises ValueError when no frame is posed.
    """
    config = (config or EstimatorConfig()).check()
    ids = list(sequence.ids)
    frame_id = str(frame_id)
    if frame_id not in ids:
        raise ValueError(f"frame {frame_id!r} is not in the sequence")
    others = sorted((f for f in annotation.frames if f != frame_id and f in ids), key=lambda f: abs(ids.index(f) - ids.index(frame_id)))
    if frame_id in annotation.frames:
        start = annotation.frames[frame_id].matrix
    elif others:
        start = annotation.frames[others[0]].matrix
    else:
        raise ValueError("no posed frame to start from: place a box first")
    setup = _Setup(sequence, annotation, ids, replace(config, workers=1))  # a few frames: forking would not pay
    sources = others[: config.chain_model_frames] or [frame_id]
    # the document's poses are at the colour instants; the depth is posed at its own (sequences.timing)
    at_depth = at_depth_time(sequence, {**{f: annotation.frames[f].matrix for f in others}, frame_id: start})
    at = {f: at_depth[f] for f in sources}
    parts = {f: setup.crop(f, at[f], thin=False) for f in sources}
    model = fused_model(setup.crops, at, {f: (c.points, c.normals) for f, c in parts.items()}, config.free_space_tolerance, config.max_free_share)
    result = register(setup.crop(frame_id, at_depth[frame_id]), model, at_depth[frame_id], config)
    agreement = None
    if result.ok and others:  # whether the frame's depth confirms the model of the other frames where the result puts it
        through, seen = seen_through(model, setup.crops, {frame_id: result.pose}, AGREEMENT_TOLERANCE)
        agreement = agreement_figures(seen.sum(), through.sum())
    figures = frame_figures(result.pose, result, None, setup.symmetric, config, agreement)
    reason = "no depth of the object in the box" if not result.ok else agreement_reason(agreement or {})
    if reason:
        figures["flagged"] = True
        figures["flag_reason"] = f"{reason}: move the box onto the object and refine again"
        return FramePose.from_matrix(start, "refined", figures)
    to_colour = np.linalg.inv(at_depth[frame_id]) @ start  # the motion from the depth instant to the colour one
    return FramePose.from_matrix(result.pose @ to_colour, "refined", figures)
