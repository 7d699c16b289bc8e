"""Whether a frame's depth confirms an object model at a pose: both tracking engines judge a refine by it.

The votes (each engine counts them over its own frames: tracking.freespace.free_space_votes,
estimator.model.seen_through): of the model's points (object frame) put into the frame at the pose, those whose pixel's
depth lies within a tolerance of them (seen) and those whose pixel's depth lies beyond them (seen through: the camera
looks through where the pose puts the object). A pixel in front of a point (the object's own near side, a hand) or
without depth gives no vote. The agreement is seen / (seen + seen through).

Unlike a registration's fitness (the share of the box's points that pair with the model), the agreement does not
fall where the frame shows sides the model lacks (a model from the few frames an annotator posed) or a hand covers
the object: those points give no vote. A box off the object puts the model where the camera sees through it.
On the refine trials of benchmarks/bench_refine.py (16 dev sequences, 3 posed frames, boxes up to 10 deg / 2 cm off,
the chains engine), judging by the agreement instead of a fitness of 0.5: converged 62 -> 68 %, declined 25 -> 15 %,
taken but not converged 13 -> 17 % (further from the truth than the start 7 -> 8 %). What it cannot see: a box slid
along a flat face it holds, or turned about an axis the shape leaves free, keeps its agreement.
"""

from __future__ import annotations

#: A model point is seen where the frame's depth lies within this (m) of it, seen through beyond it.
AGREEMENT_TOLERANCE = 0.005
#: The least agreement (share) of a pose the frame's depth confirms.
MIN_AGREEMENT = 0.7
#: The least votes (model points the frame measures at or beyond the pose): fewer, and the frame hardly sees the
#: object where the pose puts it (hidden, out of view, or the box on something else in front of it).
MIN_VOTES = 100


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
