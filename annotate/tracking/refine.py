"""Joint refinement: every frame registered to the model built from all frames, so drift cannot build up.

The model of all frames (at their current poses) averages the views; voxels seen in fewer than
``global_min_hits`` frames (a hand that moved relative to the object) are left out of the target,
and so are voxels that the frames see through more often than they see them (freespace.py: a
hand held still through one grasp is hit in tens of frames, but seen through after a regrasp).
A few rounds alternate between rebuilding the model and re-registering each frame to it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from evaluate.geometry import invert, untransform

from .consistency import rotation_jumps
from .freespace import free_space_votes
from .smooth import registration_information, smooth_poses
from .model import ObjectModel
from .registration import ModelTarget
from .propagate import predict
from .quality import pose_difference
from .reconcile import common_correction, interpolate, pose_log
from annotate.symmetry_axis import closest_about_y
from .tracker import FrameResult, Tracker
from annotate.workers import TaskPool, counting, ordered_map


def build_model(tracker: Tracker, poses: dict[str, np.ndarray], max_frames: int, always: list[str] = (), free_space: bool = True) -> ObjectModel:
    """The model of up to ``max_frames`` evenly spaced posed frames (plus ``always``), object frame; with
    ``free_space`` (and ``config.free_space_tolerance`` > 0), without the voxels the frames see through."""
    ids = list(poses)
    if len(ids) > max_frames:
        picks = np.unique(np.linspace(0, len(ids) - 1, max_frames).round().astype(int))
        ids = [ids[i] for i in picks]
    ids = list(dict.fromkeys(list(ids) + [m for m in always if m in poses]))
    model = tracker.new_model()
    tracker.add_frames_to_model(model, ids, [poses[f] for f in ids])
    config = tracker.config
    if free_space and config.free_space_tolerance > 0 and len(model):
        # a voxel the frames see through more often than they see it is not rigid with the object (a hand)
        points, _ = model.points(1)
        through, seen = free_space_votes(points, {f: poses[f] for f in ids}, tracker.store, config.free_space_tolerance)
        model.keep(through <= config.max_through_share * seen)
    return model


def min_hits_for(model: ObjectModel, config) -> int:
    """The hit threshold for a model of ``model.frames`` frames: a fifth of them, at least 1, at most the configured."""
    return int(max(1, min(config.global_min_hits, model.frames // 5)))


def refine_all(
    tracker: Tracker,
    results: dict[str, FrameResult],
    rounds: int,
    anchors: list[str] = (),
    step: Callable[[], None] | None = None,
    settled: tuple[float, float] | None = None,
    origin: dict[str, np.ndarray] | None = None,
) -> dict[str, FrameResult]:
    """Re-register every frame of ``results`` (in order) to the model of all of them, ``rounds`` times.

    ``origin``: frame -> the chains' pose (4x4) that :func:`far_from_chains` measures the rounds from (default:
    the poses of ``results``; the engine passes the poses from before :func:`coarse_round`, so that the coarse
    round's moves and these rounds' do not add up past the limit).

    With ``settled`` (deg, m), the rounds stop early once a round moved the frames' poses by less
    than both in the median (the model of the next round would be the same model): a laptop's
    first round moves its frames by 0.07 deg / 0.3 mm in the median, a shallow bowl's by 1.1 deg.

    The model is built from the frames that are not suspect (registration failed, or the chains
    disagree), or, when fewer than a quarter are, from the quarter whose chains agree best (a model of all
    frames would hold frames whose chains slid far along a laptop's hinge, and leave the rotations further off).
    A suspect frame also starts from the last refined pose that fits (``config.min_fitness``) and its
    constant-velocity prediction, the best-fitting start kept, so a chain that lost the object is repaired against
    the whole model; in the first round of a call only (later rounds start from the repaired pose: as accurate, with
    fewer registrations; the coarse round, a call of its own, restarts them too).
    A frame whose registration fails keeps its pose and figures (with the failure noted), and so
    does one that a round would turn by more than ``config.max_refine_step_deg`` or move by more
    than ``config.max_refine_step_m`` without fitting the same points clearly better
    (``config.refine_step_fitness_gain``; noted as ``refine_rejected_deg`` / ``_m``); for symmetric
    objects, the same holds for the rounds together against the chains' pose (:func:`far_from_chains`).
    The limits are there because the model of all frames lets frames slide far along what it does not pin
    down, at a high fitness (a mug's bottom, a disc, fits any spin, even from the true pose), while the
    chains' real corrections (a laptop's, of 10-20 deg) fit clearly better.
    """
    config = tracker.config
    origin = {f: r.pose for f, r in results.items()} if origin is None else {f: origin.get(f, r.pose) for f, r in results.items()}
    for done in range(rounds):
        poses = {k: r.pose for k, r in results.items() if not suspect(r, config)}
        if len(poses) < max(3, len(results) // 4):
            poses = best_agreeing(results, max(3, len(results) // 4), config)
        model = build_model(tracker, poses, config.max_global_frames, [a for a in anchors if a in poses])
        hits = min_hits_for(model, config)
        model.prepare(hits)
        # every frame from its own pose: independent registrations, on several processes where there are cores
        own = dict(zip(results, ordered_map(lambda f: tracker.register(f, results[f].pose, model, hits), list(results), config.worker_count(), step and (lambda *_: step()))))
        settle = _Settler(tracker, results, own, origin, model, hits, retry=done == 0)
        updated = settle.all(config.worker_count())
        moved = np.array([pose_difference(results[f].pose, r.pose, tracker.symmetric) for f, r in updated.items() if r.ok])
        results = updated
        if settled is not None and len(moved) and np.median(moved[:, 0]) < settled[0] and np.median(moved[:, 1]) < settled[1]:
            if step is not None:
                for _ in range((rounds - done - 1) * len(results)):
                    step()  # the progress still ends at its total
            break
    return results


class _Settler:
    """One round's outcome for every frame, from its own registration (``own``): the step limits, and in the first
    round the extra starts of a suspect frame from the last refined poses (``retry``).

    A suspect frame's extra starts are its predecessors' outcomes (the last two refined poses that fit), so those
    frames are settled in order. But an outcome that is not a suspect frame's needs nothing of the frames before
    it: once two such frames were kept after a suspect one, the frames after them depend on nothing before. The
    frames are cut there into stretches that each run in order, independently of the others (otherwise a laptop
    with many suspect frames runs hundreds of such registrations one after the other in the parent process).
    Where there are several cores, a suspect frame's starts run on the workers at once (workers.TaskPool): the
    stretches themselves on the workers left one core idle while the longest ran. The outcome is the same as in
    one loop, bit for bit.
    """

    def __init__(self, tracker: Tracker, results: dict[str, FrameResult], own: dict[str, FrameResult], origin: dict[str, np.ndarray],
                 model: ObjectModel, hits: int, retry: bool) -> None:
        self.tracker, self.results, self.own, self.origin, self.model, self.hits, self.retry = tracker, results, own, origin, model, hits, retry
        self.config = tracker.config
        self._plain: dict[str, tuple[FrameResult, np.ndarray | None]] = {}  # outcomes that need no predecessor

    def all(self, workers: int) -> dict[str, FrameResult]:
        """Every frame's outcome (frame order)."""
        ids = list(self.results)
        stretches = self._stretches(ids)
        if workers > 1 and any(s[2] for s in stretches):
            # a suspect frame's starts on the workers at once, frame after frame: the stretches on the workers left
            # a core idle while the longest one ran its frames in order
            register = lambda frame_id, init: self.tracker.register(frame_id, init, self.model, self.hits)  # noqa: E731
            with TaskPool(register, workers) as pool:
                runs = [self._run(s, pool.map) for s in stretches]
        else:
            runs = [self._run(s) for s in stretches]
        return {f: r for run in runs for f, r in run}

    def _stretches(self, ids: list[str]) -> list[tuple[int, int, bool, list[np.ndarray]]]:
        """(start, stop, holds a suspect frame to retry, the last two kept poses before start) that cover ``ids``."""
        starts: list[tuple[int, list[np.ndarray]]] = [(0, [])]
        last: list[np.ndarray] = []
        known = 2  # the outcomes kept since the last suspect frame (2: ``last`` is known)
        retried = []
        for i, frame_id in enumerate(ids):
            if self._retries(frame_id):
                if known >= 2 and retried and retried[-1] >= starts[-1][0]:  # the stretch so far holds a retried frame
                    starts.append((i, list(last)))
                known = 0
                retried.append(i)
                continue
            result, kept = self._outcome(frame_id, last)
            self._plain[frame_id] = (result, kept)
            if kept is not None:
                last = (last + [kept])[-2:]
                known += 1
        bounds = [s for s, _ in starts] + [len(ids)]
        return [(a, b, any(a <= i < b for i in retried), tail) for (a, tail), b in zip(starts, bounds[1:])]

    def _retries(self, frame_id: str) -> bool:
        return self.retry and suspect(self.results[frame_id], self.config)

    def _run(self, stretch: tuple[int, int, bool, list[np.ndarray]], registrations: Callable | None = None) -> list[tuple[str, FrameResult]]:
        """The outcomes of a stretch's frames, in order; ``registrations``: see :meth:`_outcome`."""
        start, stop, _, last = stretch
        out = []
        for frame_id in list(self.results)[start:stop]:
            result, kept = self._plain[frame_id] if frame_id in self._plain else self._outcome(frame_id, last, registrations)
            out.append((frame_id, result))
            if kept is not None:
                last = (last + [kept])[-2:]
        return out

    def _outcome(self, frame_id: str, last: list[np.ndarray], registrations: Callable | None = None) -> tuple[FrameResult, np.ndarray | None]:
        """The frame's outcome, and its pose where it counts as a refined pose that fits (None otherwise).
        ``registrations``: a batch of (frame id, start pose) -> their registrations to the model, in order (a
        TaskPool's map; None: one after the other here)."""
        tracker, config, model, hits = self.tracker, self.config, self.model, self.hits
        previous = self.results[frame_id]
        candidates = [self.own[frame_id]]
        if self._retries(frame_id) and last:
            # the chains' blend may be the lost one: also start from the last refined pose and its
            # constant-velocity prediction, and keep the start that fits the model best
            starts = [last[-1]] + ([predict(last[-1], last[-2])] if len(last) > 1 else [])
            batch = [(frame_id, init) for init in starts]
            if registrations is None:
                registrations = lambda pairs: [tracker.register(f, init, model, hits) for f, init in pairs]  # noqa: E731
            candidates = registrations(batch) + candidates
        result = None
        for candidate in candidates:
            if result is None or (candidate.ok and (not result.ok or candidate.figures.get("fitness", 0.0) > result.figures.get("fitness", 0.0))):
                result = candidate
        if result.ok:
            deg, metres = pose_difference(previous.pose, result.pose, tracker.symmetric)
            if large_step(deg, metres, config) or (tracker.symmetric and far_from_chains(*pose_difference(self.origin[frame_id], result.pose, True), config)):
                before, after = _fitness_pair(tracker, frame_id, previous.pose, result.pose, model.target(hits))
                if after < before + config.refine_step_fitness_gain:
                    # a slide along a direction the model does not pin down (a mug's bottom: a disc fits any
                    # spin, fitness 0.8-1.0 at 50-170 deg off), not a correction of the chains (a laptop's
                    # 10-20 deg corrections fit clearly better): keep the pose
                    result = FrameResult(previous.pose, True, dict(previous.figures, refine_rejected_deg=deg, refine_rejected_m=metres))
        if not result.ok:
            figures = dict(previous.figures)
            figures.setdefault("error", result.figures.get("error", "registration failed"))
            return FrameResult(previous.pose, False, figures), None
        figures = dict(previous.figures)
        figures.update(result.figures)
        figures.pop("error", None)
        if "refine_rejected_deg" not in result.figures:  # a step this round took: an earlier round's rival is gone
            figures.pop("refine_rejected_deg", None)
            figures.pop("refine_rejected_m", None)
        kept = result.pose if result.figures.get("fitness", 0.0) >= config.min_fitness else None
        return FrameResult(result.pose, True, figures), kept


def coarse_round(tracker: Tracker, results: dict[str, FrameResult], anchors: list[str] = (), step: Callable[[], None] | None = None) -> dict[str, FrameResult]:
    """One joint-refinement round against a model ``config.coarse_voxel_factor`` times coarser, before the usual rounds.

    Each stretch of frames between two manual frames carries that manual frame's error, and the 4 mm model of all
    frames holds the stretches' copies of a detail side by side when they lie less than about two voxels apart (a
    mug's handle 2-7 mm apart in two stretches spun 3.5 and 4 deg off): each stretch keeps fitting its own copy. In a
    twice coarser model the copies merge into one detail at their mean, and every frame is pulled towards it; the
    usual rounds then settle the frames on the sharp model. A move in this round beyond ``coarse_step_deg`` /
    ``coarse_step_m`` is turned down whatever the fit (a coarse mug body fits any spin where the handle is hidden:
    without the limit, frames turned tens of degrees off). Poses only: a frame whose registration fails here keeps
    its pose, and the figures are the usual rounds' to measure (the coarse distances are not the thresholds').

    The round lowers the rotation errors and fails fewer goal checks; the centres move little, and a laptop takes
    about a fifth longer. Two coarse rounds, or a model 1.5 times coarser instead of twice, do no better.
    """
    config = tracker.config
    voxel = config.coarse_voxel()
    if voxel is None:
        return results
    reg = config.registration
    # the distances grow with the voxel (the model's points lie up to a coarse voxel apart), and no fit is
    # good enough for a move beyond the step limits
    coarse = replace(
        config,
        voxel_size=voxel,
        registration=replace(reg, fine_distance=reg.fine_distance * 1.5, quality_distance=reg.quality_distance * 1.5, max_distance=max(reg.max_distance, 3 * reg.fine_distance)),
        max_refine_step_deg=config.coarse_step_deg,
        max_refine_step_m=config.coarse_step_m,
        refine_step_fitness_gain=float("inf"),
    )
    moved = refine_all(Tracker(tracker.store, tracker.extents, tracker.symmetric, coarse), results, 1, anchors, step)
    return {f: FrameResult(moved[f].pose if moved[f].ok else r.pose, r.ok, r.figures) for f, r in results.items()}


def best_agreeing(results: dict[str, FrameResult], count: int, config) -> dict[str, np.ndarray]:
    """The poses (4x4, in frame order) of the ``count`` frames whose chains agree best, failed ones left out.

    The chains' disagreement in units of its thresholds (the larger of rotation and centre); a
    frame outside both chains' span has none and counts as agreeing (one chain from a manual frame).
    """
    ok = [f for f, r in results.items() if r.ok]
    score = {f: max(results[f].figures.get("chain_disagreement_deg", 0.0) / config.max_chain_disagreement_deg, results[f].figures.get("chain_disagreement_m", 0.0) / config.max_chain_disagreement_m) for f in ok}
    keep = set(sorted(ok, key=lambda f: score[f])[:count])
    return {f: results[f].pose for f in results if f in keep}


def large_step(deg: float, metres: float, config) -> bool:
    """Whether a joint-refinement round's change of a frame's pose (degrees, metres) is beyond the
    configured steps (``max_refine_step_deg``, ``max_refine_step_m``; 0: no limit) and must fit clearly better.

    Against a model smeared by frames whose chains had slid along a laptop's hinge, a round can move frames that
    were close a further several centimetres along it (the two planes fit any position along the hinge), with a
    fitness no better and the rotation nearly unchanged.
    """
    return (config.max_refine_step_deg > 0 and deg > config.max_refine_step_deg) or (config.max_refine_step_m > 0 and metres > config.max_refine_step_m)


def far_from_chains(deg: float, metres: float, config) -> bool:
    """Whether the rounds so far took a symmetric object's frame (degrees between the axes, metres) beyond
    ``config.max_refine_departure_deg`` / ``_m`` of the chains' pose (0: no limit): it must then fit clearly better.

    Each round's step stays within ``large_step``, but the rounds add up: where the hand hides half of a bowl, a
    few rounds can slide frames from within a few degrees to several times as far off (a near-sphere fits any
    tilt), and the smoothing carries the rest along.
    """
    return (config.max_refine_departure_deg > 0 and deg > config.max_refine_departure_deg) or (config.max_refine_departure_m > 0 and metres > config.max_refine_departure_m)


def _fitness_pair(tracker: Tracker, frame_id: str, pose_a: np.ndarray, pose_b: np.ndarray, target) -> tuple[float, float]:
    """Fitness (share of points within the quality distance of ``target``) of the same points of a frame,
    cropped at ``pose_a``, at ``pose_a`` and at ``pose_b`` (4x4 each)."""
    points, _ = tracker.crop(frame_id, pose_a)
    if len(points) == 0 or len(target) == 0:
        return 0.0, 0.0
    distance = tracker.config.registration.quality_distance
    out = []
    for pose in (pose_a, pose_b):
        local = untransform(pose, points)
        d, _ = target.nearest(local, distance)
        out.append(float(np.mean(np.isfinite(d))))
    return out[0], out[1]


def suspect(result: FrameResult, config) -> bool:
    """Whether a frame's current pose is doubtful: failed, or its two chains disagree beyond the thresholds."""
    figures = result.figures
    return (
        not result.ok
        or figures.get("chain_disagreement_deg", 0.0) > config.max_chain_disagreement_deg
        or figures.get("chain_disagreement_m", 0.0) > config.max_chain_disagreement_m
    )


#: a restart whose fitness is within this of the final pose's is an equally good rival pose
RIVAL_FITNESS_MARGIN = 0.02


def recheck_disagreements(
    tracker: Tracker,
    results: dict[str, FrameResult],
    chain_poses: dict[str, tuple[np.ndarray, np.ndarray]],
    anchors: list[str] = (),
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, FrameResult]:
    """Re-measure the chains' disagreement of the frames it made suspect, against their final poses.

    The chains' disagreement says where a chain lost the object before the joint refinement; it
    says nothing about the refined pose that replaced both. For each such frame, the frame is
    registered to the model of all (well-fitting) final poses starting from the final pose and from
    each chain's pose (``chain_poses[f]``: forward, backward, 4x4). A start that lands on a pose
    fitting the model as well as the final pose (fitness within ``RIVAL_FITNESS_MARGIN``) is a
    rival; one that lands on a clearly worse fit is a local minimum the final pose beats. With no
    rival beyond the disagreement thresholds, the figures become the rivals' largest difference
    from the final pose (the original kept as ``chain_disagreement_before_deg`` / ``_m``);
    otherwise the frame keeps the chains' figures (and its flag), also when no run of cleared frames
    joins it to a frame that was never suspect (:func:`_vouched`). A frame whose final pose jumps
    away from the midpoint of its neighbours' keeps them too (a bowl frame can slide centimetres along
    the model where the hand hides most of it, and no restart finds a better fit).
    """
    config = tracker.config
    todo = [f for f, r in results.items() if f in chain_poses and r.ok and suspect(r, config)]
    if not todo:
        return results
    model = trusted_model(tracker, results, anchors)
    if model is None:
        return results  # too few trusted frames for a model to judge by
    hits = min_hits_for(model, config)
    model.prepare(hits)
    out = dict(results)
    order = list(results)

    def rivals(frame_id: str) -> tuple[float, float] | None:
        """The largest difference (deg, m) of a rival pose from the frame's final pose; None: no verdict."""
        final = results[frame_id]
        if not _smooth_with_neighbours(results, order, frame_id, tracker.symmetric, config):
            return None  # a jump away from both neighbours: the refined pose itself slid off (a model minimum elsewhere)
        own = tracker.register(frame_id, final.pose, model, hits)  # the final pose's fit on this same model
        if not own.ok:
            return None
        worst_deg, worst_m = 0.0, 0.0
        for start in chain_poses[frame_id]:
            restart = tracker.register(frame_id, start, model, hits)
            if not restart.ok:
                return float("inf"), float("inf")
            # a start that settles elsewhere but fits clearly worse is a local minimum, not a rival pose
            if restart.figures["fitness"] < own.figures["fitness"] - RIVAL_FITNESS_MARGIN:
                continue
            deg, metres = pose_difference(own.pose, restart.pose, tracker.symmetric)
            worst_deg, worst_m = max(worst_deg, deg), max(worst_m, metres)
        return worst_deg, worst_m

    counted = counting(progress, len(todo))
    for frame_id, worst in zip(todo, ordered_map(rivals, todo, config.worker_count(), counted)):
        if worst is None:
            continue
        final, (worst_deg, worst_m) = results[frame_id], worst
        if worst_deg <= config.max_chain_disagreement_deg and worst_m <= config.max_chain_disagreement_m:
            figures = dict(final.figures)
            figures["chain_disagreement_before_deg"] = figures.get("chain_disagreement_deg", 0.0)
            figures["chain_disagreement_before_m"] = figures.get("chain_disagreement_m", 0.0)
            figures["chain_disagreement_deg"], figures["chain_disagreement_m"] = worst_deg, worst_m
            out[frame_id] = FrameResult(final.pose, True, figures)
    never_suspect = {f for f, r in results.items() if r.ok and not suspect(r, config)}
    return _vouched(out, results, order, never_suspect)


def reregister_suspects(tracker: Tracker, results: dict[str, FrameResult], model: ObjectModel, skip: set[str] = frozenset()) -> dict[str, FrameResult]:
    """The frames still suspect after the recheck (their chains disagreed, and no restart cleared them), each
    registered once more to ``model`` (of the trusted final poses, object frame) from its current pose.

    The model of the joint refinement was built before the smoothing, which took such a frame's weak directions
    from its neighbours; the model of the trusted final poses holds none of the suspect frames' own points. A move
    beyond ``config.max_suspect_step_deg`` / ``config.max_refine_step_m`` is turned down (a sliding fit, not a
    correction). Poses only: the figures and flags stay the chains' (these frames stay flagged). Frames in ``skip``
    (the manual ones) are left alone.

    It brings back stretches of frames whose chains disagreed by tens of degrees and which the smoothing left
    several degrees off. Its step limit is wider than the rounds' (``max_suspect_step_deg``): such frames can need
    a turn of more than 10 deg.

    Where the spin is free it also moves frames the smoothing had right, turning them several degrees about the
    axis. That is accepted, as frames the smoothing carried off need the same kind of move, and both ways of telling
    them apart that were tried held the needed moves back as well: keeping the move only where the fitness of the
    same points rises (by 0.02; it rises by under 0.01 in both kinds of frames), and keeping the smoothed pose
    along the directions the move's information leaves weak (the spin is weak in both).
    """
    config = tracker.config
    todo = [f for f, r in results.items() if f not in skip and r.ok and suspect(r, config)]
    if not todo or len(model) == 0:
        return results
    hits = min_hits_for(model, config)
    limits = replace(config, max_refine_step_deg=config.max_suspect_step_deg)
    out = dict(results)
    model.prepare(hits)
    for frame_id, again in zip(todo, ordered_map(lambda f: tracker.register(f, results[f].pose, model, hits), todo, config.worker_count())):
        before = results[frame_id]
        if again.ok and not large_step(*pose_difference(before.pose, again.pose, tracker.symmetric), limits):
            out[frame_id] = FrameResult(again.pose, True, before.figures)
    return out


def _vouched(rechecked: dict[str, FrameResult], before: dict[str, FrameResult], order: list[str], never_suspect: set[str]) -> dict[str, FrameResult]:
    """The recheck's clearances that neighbours vouch for: a cleared frame keeps its new figures only when
    a run of cleared frames joins it to a frame in ``never_suspect`` (registered, chains agreeing). Its
    smoothness with neighbours that stay suspect, or failed, says nothing (a frame as far off as its flagged
    neighbours is smooth with them, and every restart can land on the same wrong minimum of the model)."""
    cleared = {f for f in rechecked if rechecked[f] is not before[f]}
    kept: set[str] = set()
    # two sweeps reach every run of cleared frames from either end
    for sweep in (order, order[::-1]):
        trusted = never_suspect | kept
        for previous, frame_id in zip([None] + sweep[:-1], sweep):
            if frame_id in cleared and frame_id not in kept and previous in trusted:
                kept.add(frame_id)
                trusted.add(frame_id)
    return {f: before[f] if f in cleared and f not in kept else r for f, r in rechecked.items()}


def _smooth_with_neighbours(results: dict[str, FrameResult], order: list[str], frame_id: str, symmetric: bool, config) -> bool:
    """Whether a frame's pose lies within the chain-disagreement thresholds of the midpoint of its two
    neighbours' poses (objects move smoothly between frames; an end frame is not judged this way)."""
    i = order.index(frame_id)
    if i == 0 or i == len(order) - 1:
        return False
    before, after = results[order[i - 1]].pose, results[order[i + 1]].pose.copy()
    if symmetric:
        after[:3, :3] = closest_about_y(after[:3, :3], before[:3, :3])
    deg, metres = pose_difference(interpolate(before, after, 0.5), results[frame_id].pose, symmetric)
    return deg <= config.max_chain_disagreement_deg and metres <= config.max_chain_disagreement_m


def smooth_refined(
    tracker: Tracker,
    results: dict[str, FrameResult],
    anchors: list[str] = (),
    placed: dict[str, np.ndarray] | None = None,
    chained: dict[str, np.ndarray] | None = None,
) -> dict[str, FrameResult]:
    """The refined poses (``results`` in frame order) smoothed where their registration is weak (smooth.py).

    With ``placed`` (manual frame -> placed 4x4 pose), each manual frame also pulls its pose toward
    its placed box, brought into the tracked poses' object frame by the common correction, with
    the confidence of a hand placement (``manual_rotation_sigma_deg``, ``manual_translation_sigma``):
    the only evidence on a direction the geometry leaves weak over a whole stretch of frames.

    Each frame's information comes from its points at its pose against the model of the trusted
    frames; a frame whose registration failed, fits poorly or whose chains disagree gives none
    (its pose is interpolated from its neighbours), unless the joint refinement confirmed its
    chains' pose (``chained``: frame -> 4x4 pose before the refinement; see :func:`refinement_confirmed`).
    Figures and flags are kept.
    """
    config = tracker.config
    order = list(results)
    trusted = {f: r.pose for f, r in results.items() if r.ok and not suspect(r, config) and r.figures.get("fitness", 0.0) >= config.min_fitness}
    if len(trusted) < max(3, len(results) // 4):
        return results
    model = build_model(tracker, trusted, config.max_global_frames, [a for a in anchors if a in trusted])
    target = model.target(min_hits_for(model, config))
    informed = set(trusted) | refinement_confirmed(tracker, results, chained or {})

    def information_of(frame_id: str, target: ModelTarget = target) -> np.ndarray:  # bound now: ``target`` is reused below
        if frame_id not in informed:
            return np.zeros((6, 6))
        pose = results[frame_id].pose
        points, _ = tracker.crop(frame_id, pose, margin=0.0)
        return registration_information(untransform(pose, points), target, config.registration.fine_distance, config.information_sigma)

    target.grid()  # built here, before the work forks: the workers inherit it
    information = ordered_map(information_of, order, config.worker_count())
    priors = {}
    placed = {m: P for m, P in (placed or {}).items() if m in results and results[m].ok}
    if placed:
        correction = np.linalg.inv(common_correction({m: results[m].pose for m in placed}, placed, tracker.symmetric))
        info = np.diag([1 / np.radians(config.manual_rotation_sigma_deg) ** 2] * 3 + [1 / config.manual_translation_sigma**2] * 3)
        for m, P in placed.items():
            T = results[m].pose
            D = invert(T) @ P @ correction  # T exp(d) = placed, in the tracked object frame
            if tracker.symmetric:
                D[:3, :3] = closest_about_y(D[:3, :3], np.eye(3))
            target = pose_log(D)
            priors[order.index(m)] = (target, info)
    poses = smooth_poses(
        [results[f].pose for f in order],
        information,
        np.radians(config.rotation_acceleration_deg),
        config.translation_acceleration,
        free_y=tracker.symmetric,
        priors=priors,
    )
    return {f: FrameResult(p, results[f].ok, results[f].figures) for f, p in zip(order, poses)}


def undo_smoothing_bends(tracker: Tracker, refined: dict[str, FrameResult], smoothed: dict[str, FrameResult], anchors: list[str] = ()) -> dict[str, FrameResult]:
    """``smoothed`` with each frame that the smoothing turned more than ``config.smoothing_undo_deg`` (and at most
    ``config.smoothing_undo_max_deg``) back at its ``refined`` pose where that fits clearly better (fitness against
    the model of the trusted smoothed frames, on the frame's points cropped at its refined pose
    (:func:`_fitness_pair`), higher by ``config.smoothing_undo_gain``). Figures stay.

    The smoothing gives no evidence to a frame whose chains disagreed; a long run of such frames is then bent only
    by the acceleration prior between the evidence on either side, linearised about poses that may jump, and can
    come out tens of degrees off where the refinement had it right and fitting clearly worse. A turn beyond
    ``smoothing_undo_max_deg`` is a flip, not a bend: a mug's body fits itself flipped, so there the refined pose
    may be the flipped one, fitting as well, while the smoothing had the frame right.
    """
    config = tracker.config
    if config.smoothing_undo_deg <= 0:
        return smoothed
    turns = {f: pose_difference(refined[f].pose, smoothed[f].pose, tracker.symmetric)[0] for f in smoothed if refined[f].ok}
    moved = [f for f, deg in turns.items() if config.smoothing_undo_deg < deg <= config.smoothing_undo_max_deg]
    if not moved:
        return smoothed
    model = trusted_model(tracker, smoothed, list(anchors))
    if model is None:
        return smoothed
    target = model.target(min_hits_for(model, config))
    out = dict(smoothed)
    for frame_id in moved:  # a few frames, two KD queries each
        at_refined, at_smoothed = _fitness_pair(tracker, frame_id, refined[frame_id].pose, smoothed[frame_id].pose, target)
        if at_refined >= at_smoothed + config.smoothing_undo_gain:
            out[frame_id] = FrameResult(refined[frame_id].pose, smoothed[frame_id].ok, smoothed[frame_id].figures)
    return out


def refinement_confirmed(tracker: Tracker, results: dict[str, FrameResult], chained: dict[str, np.ndarray]) -> set[str]:
    """Frames whose chains disagree but whose refined pose fits and lies within the chain-disagreement
    thresholds of the pose the chains gave them (``chained``, 4x4): the model of all frames confirmed it.

    Such a frame keeps its information in the smoothing: interpolated from its neighbours, a laptop frame whose
    chains disagreed by a centimetre and whose refinement had it right can turn several degrees off. A refined pose
    far from the chains' (a shallow bowl refined tens of degrees away from chains that had it right: a slide on a
    near-sphere) is better interpolated.
    """
    config = tracker.config
    out = set()
    for frame_id, result in results.items():
        if frame_id not in chained or not result.ok or result.figures.get("fitness", 0.0) < config.min_fitness:
            continue
        deg, metres = pose_difference(chained[frame_id], result.pose, tracker.symmetric)
        if deg <= config.max_chain_disagreement_deg and metres <= config.max_chain_disagreement_m:
            out.add(frame_id)
    return out


#: a tracked frame turned further than this from the frame before it (degrees; symmetric objects: between the axes)
#: has turned over: a hand turns an object a few degrees per frame (the synthetic sequences at most 9)
FLIP_DEG = 90.0


def repair_flips(tracker: Tracker, results: dict[str, FrameResult], anchors: list[str] = ()) -> dict[str, FrameResult]:
    """Frames turned over from the frame before them, registered again from that frame's pose.

    Walking from the first trusted frame (a manual frame, or one whose chains agreed) forward to the end and back to
    the start, a frame more than ``FLIP_DEG`` from the frame before it (as repaired) is registered again, from that
    frame's pose, to the model of the trusted frames; where that lands more than ``FLIP_DEG`` away again (or fails), the
    frame takes that pose as it is. Poses only, with the turn noted as ``flip_repaired_deg`` (a flag reason).

    Where the chains lose a bottle, the joint refinement can leave single frames upside down (a bottle's ends fit
    each other's place, even better than the right pose), and the smoothing then averages their neighbours with
    them, turning frames that were right tens of degrees off.
    """
    order = list(results)
    config = tracker.config
    symmetric = tracker.symmetric
    pinned = set(anchors)
    trusted = [i for i, f in enumerate(order) if results[f].ok and (f in pinned or not suspect(results[f], config))]
    if not trusted or not np.any(rotation_jumps([r.pose for r in results.values() if r.ok], symmetric) > FLIP_DEG):
        return results
    model = trusted_model(tracker, results, anchors)
    hits = min_hits_for(model, config) if model is not None else 1
    out = dict(results)

    def walk(indices) -> None:
        previous = None
        for i in indices:
            frame_id = order[i]
            result = out[frame_id]
            if not result.ok:
                continue
            turned = pose_difference(previous, result.pose, symmetric)[0] if previous is not None else 0.0
            if turned > FLIP_DEG and frame_id not in pinned:
                again = tracker.register(frame_id, previous, model, hits) if model is not None else None
                pose = again.pose if again is not None and again.ok and pose_difference(previous, again.pose, symmetric)[0] <= FLIP_DEG else previous.copy()
                out[frame_id] = FrameResult(pose, True, {**result.figures, "flip_repaired_deg": turned})
            previous = out[frame_id].pose

    walk(range(trusted[0], len(order)))
    walk(range(trusted[0], -1, -1))
    return out


def trusted_model(tracker: Tracker, results: dict[str, FrameResult], anchors: list[str] = ()) -> ObjectModel | None:
    """The model of the frames that are not suspect and fit well (object frame), or None when fewer
    than a quarter of the frames (at least 3) are such."""
    config = tracker.config
    good = {f: r.pose for f, r in results.items() if r.ok and not suspect(r, config) and r.figures.get("fitness", 0.0) >= config.min_fitness}
    if len(good) < max(3, len(results) // 4):
        return None
    return build_model(tracker, good, config.max_global_frames, [a for a in anchors if a in good])


def recheck_single_chains(
    tracker: Tracker,
    results: dict[str, FrameResult],
    ends: list[list[str]],
    anchors: list[str] = (),
    model: ObjectModel | None = None,
) -> dict[str, FrameResult]:
    """A second chain through the frames outside the manual frames' span, where only one chain ran.

    ``ends``: frame ids from a manual frame's inner neighbour, through the manual frame, outward to
    the end of the sequence (``[a + 1, a, a - 1, ..., 0]``). The second chain registers each outer
    frame to the model of the trusted final poses, starting from the constant-velocity prediction
    of the two poses before it (its own, from the manual frame on), so it carries the motion seen
    inside the span outward; the first chain started from the young model of the manual frame
    alone. Where the two land more than the chain-disagreement thresholds apart, the frame's
    ``chain_disagreement_deg`` / ``_m`` say so (and flag it): a single chain can slide several degrees
    off in the frames before its first manual frame, with its fitness still above 0.5.
    Unless the second chain is no rival: where the final pose, registered to the same model, fits
    clearly better (``RIVAL_FITNESS_MARGIN``), the second chain sits in a worse minimum; the figures
    are then the final pose's own re-registration (``second_chain_fitness`` kept) and the chain goes
    on from there. A lost second chain would otherwise flag frames that are right, and with them
    flagged the carving leaves a hand remnant (the mesh too tall).
    ``model``: :func:`trusted_model` of ``results`` when the caller has it already.
    """
    config = tracker.config
    ends = [e for e in ends if len(e) > 2]
    if model is None and ends:
        model = trusted_model(tracker, results, anchors)
    if not ends or model is None:
        return results
    hits = min_hits_for(model, config)
    out = dict(results)
    for end in ends:
        before, previous = results[end[0]].pose, results[end[1]].pose
        for frame_id in end[2:]:
            second = tracker.register(frame_id, predict(previous, before), model, hits)
            if not second.ok:
                break  # the second chain lost the frame: nothing more to compare
            final = results[frame_id]
            deg, metres = pose_difference(final.pose, second.pose, tracker.symmetric)
            figures = dict(final.figures)
            if final.ok and (deg > config.max_chain_disagreement_deg or metres > config.max_chain_disagreement_m):
                # a rival only if it fits as well: the final pose, registered to the same model, fitting clearly
                # better means the second chain sits in a worse minimum (lost), and it goes on from there
                own = tracker.register(frame_id, final.pose, model, hits)
                if own.ok and second.figures["fitness"] < own.figures["fitness"] - RIVAL_FITNESS_MARGIN:
                    figures["second_chain_fitness"] = second.figures["fitness"]
                    deg, metres = pose_difference(final.pose, own.pose, tracker.symmetric)
                    second = own
            figures["chain_disagreement_deg"], figures["chain_disagreement_m"] = deg, metres
            out[frame_id] = FrameResult(final.pose, final.ok, figures)
            before, previous = previous, second.pose
    return out
