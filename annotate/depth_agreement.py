"""Whether a frame's depth confirms an object model at a pose: both tracking engines judge a refine by it.

The votes (:func:`depth_votes`; each engine projects the points over its own frames: tracking.freespace.
free_space_votes, estimator.model.seen_through): of the model's points (object frame) put into the frame at the
pose, those whose pixel's depth lies within a tolerance of them (seen) and those whose pixel's depth lies beyond them
(seen through: the camera looks through where the pose puts the object). A pixel in front of a point (the object's
own near side, a hand) or without depth gives no vote. The agreement is seen / (seen + seen through).

Unlike a registration's fitness (the share of the box's points that pair with the model), the agreement does not
fall where the frame shows sides the model lacks (a model from the few frames an annotator posed) or a hand covers
the object: those points give no vote. A box off the object puts the model where the camera sees through it. What
it cannot see: a box slid along a flat face it holds, or turned about an axis the shape leaves free, keeps its
agreement. benchmarks/bench_refine.py measures what a refine judged by it converges to.
"""

from __future__ import annotations

import numpy as np

#: A model point is seen where the frame's depth lies within this (m) of it, seen through beyond it.
AGREEMENT_TOLERANCE = 0.005
#: The least agreement (share) of a pose the frame's depth confirms.
MIN_AGREEMENT = 0.7
#: The least votes (model points the frame measures at or beyond the pose): fewer, and the frame hardly sees the
#: object where the pose puts it (hidden, out of view, or the box on something else in front of it).
MIN_VOTES = 100


def depth_votes(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray, z: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Per point (N,) bool: (seen through, seen) in a depth image (h, w) m (0: none), the points given by their
    pixels (int rows and columns in that image; outside it: no vote) and their depths ``z`` (m; <= 0: no vote)."""
    inside = (rows >= 0) & (rows < depth.shape[0]) & (cols >= 0) & (cols < depth.shape[1]) & (z > 0)
    measured = np.zeros(len(z), dtype=np.float64)
    measured[inside] = depth[rows[inside], cols[inside]]
    valid = inside & (measured > 0)
    return valid & (measured > z + tolerance), valid & (np.abs(measured - z) <= tolerance)


def agreement_figures(seen: int, through: int) -> dict:
    """The document's figures of the votes: ``depth_agreement`` (share; absent without votes) and ``depth_votes``."""
    votes = int(seen) + int(through)
    figures: dict = {"depth_votes": votes}
    if votes:
        figures["depth_agreement"] = round(int(seen) / votes, 4)
    return figures


def agreement_reason(figures: dict) -> str | None:
    """Why the frame's depth does not confirm the pose (words), or None where it does or was not asked."""
    if "depth_votes" not in figures:
        return None
    votes = int(figures["depth_votes"])
    if votes < MIN_VOTES:
        return (f"the frame measures only {votes} points of the object the other posed frames show where the box puts it "
                "(hidden, out of view, or the box is on something in front of it)")
    agreement = float(figures["depth_agreement"])
    if agreement < MIN_AGREEMENT:
        return (f"only {agreement:.0%} of the object the other posed frames show lies where this frame measures it "
                f"(at least {MIN_AGREEMENT:.0%} needed; the camera sees through the rest)")
    return None
