"""A slide check along the direction a frame's registration leaves free: a flat object seen on its faces.

Point-to-plane ICP pins a pose down only across the surfaces it sees. A laptop seen from behind is
two planes: sliding it along its hinge moves every frame point along those planes, and the points
that then stick out beyond the model's edge are further than the correspondence distance, so they
drop out of the objective instead of pulling the pose back. The chains, the joint refinement and
the smoothing can all hold a stretch of frames centimetres off along the hinge with the rotation
right, and ICP started from those poses stays there even against the true mesh.

What does see the slide is how many of the frame's points lie on the model at all (the fitness),
counted on a crop a few centimetres wider than the box, so that the part of the object that the slid
box cut off counts again. For each frame whose registration information leaves one translation
direction weak (its smallest eigenvalue under ``TrackingConfig.max_slide_ratio`` of its largest), the pose is moved along
that direction over a grid, and where the fitness rises clearly (``min_slide_gain``) at a shift of at least
``min_slide_m`` the frame takes the centre of the best shifts, provided that the fitness falls again beyond
them (a peak, both edges seen: with one edge hidden by the hand every shift past it fits alike).

Most of the slides it takes, nearly all of them a laptop's, bring frames closer to the truth. A best shift
at the end of the range is no peak (a wider search without that rule sent frames several centimetres off).
The peak test is for the case the unit test renders (on the benchmark sequences it changes little): with one
edge hidden, any shift past the seen edge fits alike. A slide that takes a frame off its neighbours' path is
refused and the frame flagged (:func:`against_the_motion`). Time: about 20 ms CPU per laptop frame (most are
checked; at most ``MAX_SEARCH_POINTS`` points of the crop, on a coarse and a fine grid of shifts).

A whole stretch a few mm off with its manual frame is not a slide this check sees: a ``min_slide_m`` of 2 or
3 mm moves no frame, and the hand is not what holds such a stretch off. Where a stretch's model shares no
surface facing the same way with the rest of the sequence, only the regrasps between them, whose chains are
lost, join it to the rest.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from evaluate.geometry import untransform

from .registration import ModelTarget
from .sampling import every_kth
from .smooth import registration_information
from .tracker import FrameResult, Tracker
from annotate.workers import counting, ordered_map

#: shifts (m) tried along the weak direction, then refined on a finer grid about the best
COARSE_STEP_M = 0.0025
FINE_STEP_M = 0.0005
#: points of the wider crop that the search counts (every k-th beyond): its time stays a few ms per frame
MAX_SEARCH_POINTS = 800
#: a found shift must be a peak: the fitness this much further out (m) lies clearly below it too, else only one
#: edge of the object is seen (the other hidden by the hand) and the best shift is anywhere on a plateau
BEYOND_M = 0.015


def weak_direction(points_obj: np.ndarray, target: ModelTarget, distance: float, sigma: float) -> tuple[np.ndarray, float]:
    """The object-frame unit direction (3,) in which the point-to-plane information of ``points_obj`` (N, 3) m
    against ``target`` is weakest (rotation held), and its eigenvalue ratio to the strongest one (0..1)."""
    info = registration_information(points_obj, target, distance, sigma)[3:, 3:]
    values, vectors = np.linalg.eigh(info)
    if not values[2] > 0:
        return np.zeros(3), 1.0
    return vectors[:, 0], float(values[0] / values[2])


def fitness_along(points_obj: np.ndarray, target: ModelTarget, direction: np.ndarray, shifts: np.ndarray, distance: float) -> np.ndarray:
    """Per shift s (S,) m: the share of ``points_obj`` (N, 3) within ``distance`` of ``target`` once the object
    moves by ``s * direction`` (object frame), i.e. its points move by ``-s * direction`` in the object frame."""
    n = len(points_obj)
    moved = (points_obj[None, :, :] - shifts[:, None, None] * direction[None, None, :]).reshape(-1, 3)
    d, _ = target.nearest(moved, distance)
    return np.isfinite(d).reshape(len(shifts), n).mean(axis=1)


def _plateau_centre(shifts: np.ndarray, fitness: np.ndarray) -> float:
    """The centre of the run of equal highest fitness that holds the first maximum (a plate fits fully over a
    range of shifts as wide as the inlier distance: its middle is the best estimate)."""
    k = int(np.argmax(fitness))
    top = fitness >= fitness[k] - 1e-12
    lo, hi = k, k
    while lo > 0 and top[lo - 1]:
        lo -= 1
    while hi < len(top) - 1 and top[hi + 1]:
        hi += 1
    return float((shifts[lo] + shifts[hi]) / 2)


def best_shift(points_obj: np.ndarray, target: ModelTarget, direction: np.ndarray, max_shift: float, distance: float) -> tuple[float, float, float, float]:
    """(shift m, fitness there, fitness at 0, fitness ``BEYOND_M`` further out) along ``direction``: the middle of
    the best shifts on a fine grid about the middle of the best ones on a coarse grid over +-``max_shift``."""
    coarse = np.arange(-max_shift, max_shift + 1e-9, COARSE_STEP_M)
    centre = _plateau_centre(coarse, fitness_along(points_obj, target, direction, coarse, distance))
    fine = centre + np.arange(-2 * COARSE_STEP_M, 2 * COARSE_STEP_M + 1e-9, FINE_STEP_M)
    fine_fit = fitness_along(points_obj, target, direction, fine, distance)
    at_zero = float(fitness_along(points_obj, target, direction, np.zeros(1), distance)[0])
    shift = _plateau_centre(fine, fine_fit)
    beyond = float(fitness_along(points_obj, target, direction, np.array([shift + np.sign(shift) * BEYOND_M]), distance)[0])
    return shift, float(fine_fit.max()), at_zero, beyond


def slide_corrections(tracker: Tracker, results: dict[str, FrameResult], target: ModelTarget, skip: set[str] = frozenset(),
                      progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """Per frame whose fitness clearly rises when it slides along its weak direction: the object-frame shift (3,) m.

    ``pose @ T(shift)`` (a translation by ``shift`` in the object frame) is the corrected pose. Frames in
    ``skip`` (the manual ones) and failed frames are left alone.
    """
    config = tracker.config
    if not config.slide_check or len(target) == 0:
        return {}
    distance = config.registration.quality_distance
    target.grid()  # built once here, not in every worker (the normals are built with the target)

    def slide(frame_id: str) -> np.ndarray | None:
        """The frame's object-frame shift (3,) m, or None."""
        pose = results[frame_id].pose
        points, _ = tracker.crop(frame_id, pose)
        if len(points) < config.min_points:
            return None
        points = every_kth(points, config.max_points)
        local = untransform(pose, points)
        direction, ratio = weak_direction(local, target, 2 * config.voxel_size, config.information_sigma)
        if ratio > config.max_slide_ratio:
            return None
        # a wider crop: the part of the object that a slid box cut off must count again
        wide, _ = tracker.crop(frame_id, pose, 0.75 * config.max_slide_m)
        wide = every_kth(wide, MAX_SEARCH_POINTS)
        wide_local = untransform(pose, wide)
        shift, fitness, at_zero, beyond = best_shift(wide_local, target, direction, config.max_slide_m, distance)
        # a best shift at the end of the range is no peak found (a wider range without this rule sent frames several
        # cm off), nor one on a plateau that only one edge bounds (the far edge hidden)
        peak = abs(shift) <= config.max_slide_m - 2 * COARSE_STEP_M and fitness - beyond >= config.min_slide_gain / 2
        if peak and abs(shift) >= config.min_slide_m and fitness - at_zero >= config.min_slide_gain:
            return shift * direction
        return None

    todo = [f for f, r in results.items() if f not in skip and r.ok]
    return {f: shift for f, shift in zip(todo, ordered_map(slide, todo, config.worker_count(), counting(progress, len(todo)))) if shift is not None}


def against_the_motion(results: dict[str, FrameResult], slides: dict[str, np.ndarray], tolerance: float, doubtful: set[str] = frozenset()) -> set[str]:
    """The frames whose slide takes their centre further than ``tolerance`` (m) beyond where it was from the
    midpoint of their two neighbours' centres (camera frame, the neighbours' own slides applied): a lone slide
    away from a smooth path. A run of slid frames moves together and keeps its neighbours' support. Neighbours in
    ``doubtful`` (their chains disagreed) judge nothing.

    Judged by every neighbour, it refused right slides next to neighbours that were far off themselves: hence
    ``doubtful``. Most of the slides it refuses are wrong; the few right ones cost their frames a flag.
    """
    order = list(results)
    centre = {f: shifted(r.pose, slides[f])[:3, 3] if f in slides else r.pose[:3, 3] for f, r in results.items()}
    out = set()
    for k, f in enumerate(order):
        if f not in slides or k == 0 or k == len(order) - 1:
            continue
        before, after = results[order[k - 1]], results[order[k + 1]]
        if not (before.ok and after.ok) or order[k - 1] in doubtful or order[k + 1] in doubtful:
            continue
        mid = (centre[order[k - 1]] + centre[order[k + 1]]) / 2
        if np.linalg.norm(centre[f] - mid) > np.linalg.norm(results[f].pose[:3, 3] - mid) + tolerance:
            out.add(f)
    return out


def shifted(pose: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``pose`` (4x4 object to camera) with the object moved by ``shift`` (3,) m along its own axes."""
    out = pose.copy()
    out[:3, 3] = pose[:3, 3] + pose[:3, :3] @ shift
    return out
