"""Checks of the final poses against independent evidence: the chains they came from, and the motion.

The joint refinement and the smoothing replace the chains' poses; a frame whose final pose left
both chains far behind has no witness left. A disc (a mug's bottom turned to the camera) fits any spin
about its normal: the refinement can slide a stretch of frames about it, fitting well, while the chains
that reached those frames stayed near the object's pose.
"""

from __future__ import annotations

import numpy as np

from .quality import pose_difference


def chain_departures(
    poses: dict[str, np.ndarray],
    chain_poses: dict[str, tuple[np.ndarray, ...]],
    symmetric: bool,
) -> dict[str, tuple[float, float]]:
    """Per frame of ``chain_poses``: (degrees, metres) from its final pose (4x4) to the nearest of its chains' poses.

    Both in the same object frame. The nearest chain in rotation is taken (its distance in metres
    reported with it): a frame is only as trustworthy as the best witness it kept.
    """
    out = {}
    for frame_id, chains in chain_poses.items():
        if frame_id not in poses:
            continue
        diffs = [pose_difference(poses[frame_id], c, symmetric) for c in chains]
        out[frame_id] = min(diffs)
    return out


def rotation_jumps(poses: list[np.ndarray], symmetric: bool) -> np.ndarray:
    """Per frame (in order), the larger rotation (degrees) to its previous and its next pose (4x4 each).

    A hand turns an object by a few degrees per frame at 30 fps (the synthetic sequences at most
    9); a frame far from both neighbours, or next to a manual frame that kept its placed box while
    the tracked frames around it slid off, shows as a jump.
    """
    # for symmetry y the angle between the y axes: the free spin about y is no motion
    steps = np.asarray([pose_difference(a, b, symmetric)[0] for a, b in zip(poses, poses[1:])], dtype=float)
    out = np.zeros(len(poses))
    if len(steps):
        out[:-1] = steps
        out[1:] = np.maximum(out[1:], steps)
    return out


def free_spin_runs(order: list[str], free: set[str], pinned: set[str]) -> dict[str, tuple[int, bool]]:
    """Per frame of ``free`` (its geometry leaves the spin about the axis free): (length of its run of
    consecutive free frames in ``order``, whether the run is one-sided: no frame before it or none after it
    fixes the spin). Frames in ``pinned`` (manual frames) end a run even when their geometry is free.

    Inside a run the spin comes only from the smoothing's interpolation between the frames at its ends,
    and beyond the last frame that fixes it, from a one-sided extrapolation (smooth.py): the error grows
    with the run's length, and fastest on the one-sided runs, where a hand turns the object on unseen.
    """
    out: dict[str, tuple[int, bool]] = {}
    run: list[str] = []
    for position, frame_id in enumerate(list(order) + [None]):
        if frame_id is not None and frame_id in free and frame_id not in pinned:
            run.append(frame_id)
            continue
        if run:
            one_sided = position - len(run) == 0 or frame_id is None
            out.update({f: (len(run), one_sided) for f in run})
            run = []
    return out


def flagged_gaps(order: list[str], flagged: set[str], eligible: set[str], max_gap: int) -> dict[str, tuple[str, str]]:
    """Per frame of ``eligible`` in a run of at most ``max_gap`` consecutive unflagged frames (in ``order``, all
    eligible) with a flagged frame right before and right after it: those two flagged frames.

    The smoothing and the refinement's neighbours tie a frame's pose to the frames around it, so a frame or two
    between flagged runs leans on suspect poses.
    """
    out: dict[str, tuple[str, str]] = {}
    if max_gap <= 0:
        return out
    last_flagged: int | None = None
    for position, frame_id in enumerate(order):
        if frame_id not in flagged:
            continue
        gap = order[last_flagged + 1 : position] if last_flagged is not None else []
        if 0 < len(gap) <= max_gap and all(f in eligible for f in gap):
            out.update({f: (order[last_flagged], frame_id) for f in gap})
        last_flagged = position
    return out


def flags_grown(order: list[str], flagged: set[str], eligible: set[str], figures: dict[str, dict], limits: dict[str, float],
                share: float, reach: int) -> dict[str, tuple[str, str, float, float]]:
    """Frames of ``eligible`` next to a flagged frame (in ``order``; then next to those, in turn, at most ``reach``
    frames out) whose figure named in ``limits`` reaches ``share`` of its flag limit: per frame, (the flagged neighbour,
    the figure, its value, its limit). A hysteresis, as an edge detector's: a chain that goes astray crosses its limit
    a frame or two after it left the object, and those frames' figures are already high."""
    position = {f: k for k, f in enumerate(order)}
    out: dict[str, tuple[str, str, float, float]] = {}
    frontier = [f for f in order if f in flagged]
    for _ in range(max(reach, 0)):
        grown = []
        for frame_id in frontier:
            k = position[frame_id]
            for neighbour in order[max(k - 1, 0) : k + 2]:
                if neighbour in flagged or neighbour in out or neighbour not in eligible:
                    continue
                passed = [(key, float(figures[neighbour][key]), limit) for key, limit in limits.items()
                          if figures[neighbour].get(key) is not None and float(figures[neighbour][key]) >= share * limit]
                if passed:
                    key, value, limit = max(passed, key=lambda p: p[1] / p[2])
                    out[neighbour] = (frame_id, key, value, limit)
                    grown.append(neighbour)
        frontier = grown
    return out
