"""What a tracking run keeps and what it changed: the anchors before it, the moved frames after it.

The anchors are the boxes a person placed (manual), refined, or accepted in review: the engines' rule
(``annotate.estimator.anchor_frames``). A run keeps them as anchors: the engine sees them as placed boxes (an engine
that anchors only ``manual`` boxes anchors them all), and afterwards each gets its own source back. An anchor takes
the pose the engine estimated where the engine kept the person's box beside it (engines.anchored_pose: within the
placement's tolerance, so that the object frame is one and no pose jumps at an anchor); the box stays what later runs
anchor on. Any other pose an engine gives an anchor is undone. The engine's figures and flags about it stay beside
them. The other frames in the range get the engine's poses; :func:`pose_changes` measures how far each frame that
had a pose moved (degrees, ignoring the turn about y for symmetry y, and millimetres of the box centre).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evaluate.metrics.pose_errors import rotation_error, translation_error
from sequences.annotation import PLACED_KEY, Annotation, FramePose

#: A frame counts as changed when its box turned or moved at least this much (deg, m): below, rounding.
CHANGED_DEG = 0.05
CHANGED_M = 0.0001
#: Frames listed by name on the page (the rest are counted).
SHOWN = 8


def anchors(annotation: Annotation, ids: list[str]) -> list[str]:
    """The frames of ``ids`` (in order) a run keeps: placed, refined or accepted (the engines' rule)."""
    from .estimator import anchor_frames

    return anchor_frames(annotation, ids)


def why_kept(pose: FramePose) -> str:
    """A word for why a frame is an anchor: placed, refined or accepted."""
    if pose.extra.get("reviewed") == "accepted":
        return "accepted"
    return {"manual": "placed", "refined": "refined"}.get(pose.source, pose.source)


def engine_view(annotation: Annotation, kept: list[str]) -> Annotation:
    """A copy of the document in which the anchors ``kept`` are placed boxes (source ``manual``), as every engine
    anchors those."""
    view = annotation.copy()
    for frame_id in kept:
        view.frames[frame_id].source = "manual"
    return view


def restore_anchors(result: Annotation, annotation: Annotation, kept: list[str]) -> Annotation:
    """``result`` with each anchor's source as in ``annotation`` (the engine's figures about it kept), and its pose
    the engine's where the engine kept the person's box beside it or gave back that box, else the pose it had."""
    for frame_id in kept:
        before = annotation.frames[frame_id]
        after = result.frames.get(frame_id)
        if after is None:
            result.frames[frame_id] = FramePose(before.position.copy(), before.orientation.copy(), before.source, dict(before.extra))
            continue
        extra = {**after.extra, **{k: v for k, v in before.extra.items() if k == "reviewed"}}
        if on_the_track(before, after) or np.allclose(after.matrix, before.placed_matrix, atol=1e-9):
            # on the track with the box beside it, or back at the person's box (beyond the tolerance)
            result.frames[frame_id] = FramePose(after.position.copy(), after.orientation.copy(), before.source, extra)
        else:
            extra = {k: v for k, v in extra.items() if k != PLACED_KEY}
            if PLACED_KEY in before.extra:
                extra[PLACED_KEY] = before.extra[PLACED_KEY]
            result.frames[frame_id] = FramePose(before.position.copy(), before.orientation.copy(), before.source, extra)
    return result


def on_the_track(before: FramePose, after: FramePose) -> bool:
    """Whether a run posed the anchor ``before`` on the track as ``after``: it kept the same person's box beside it."""
    if PLACED_KEY not in after.extra:
        return False
    return bool(np.allclose(after.placed_matrix, before.placed_matrix, atol=1e-9))


@dataclass(frozen=True)
class Change:
    """A frame whose pose a run changed: index in the sequence (0-based), id, turn (deg), move (m)."""

    index: int
    frame_id: str
    degrees: float
    metres: float


def pose_changes(before: Annotation, after: Annotation, ids: list[str], all_ids: list[str]) -> tuple[list[Change], int]:
    """The frames of ``ids`` that had a pose in ``before`` and moved in ``after``, largest first (by the larger of
    degrees / 1 deg and metres / 1 cm), and how many got a pose they did not have."""
    symmetry = before.symmetry
    changes, new = [], 0
    for frame_id in ids:
        old, now = before.frames.get(frame_id), after.frames.get(frame_id)
        if now is None:
            continue
        if old is None:
            new += 1
            continue
        degrees = float(rotation_error(old.matrix[:3, :3], now.matrix[:3, :3], symmetry))
        metres = float(translation_error(old.position, now.position))
        if degrees >= CHANGED_DEG or metres >= CHANGED_M:
            changes.append(Change(all_ids.index(frame_id), frame_id, degrees, metres))
    changes.sort(key=lambda c: -max(c.degrees / 1.0, c.metres / 0.01))
    return changes, new


def keep_markdown(annotation: Annotation, ids: list[str], all_ids: list[str]) -> str:
    """What a run over ``ids`` will keep and replace, for the page (frames counted from 1)."""
    kept = anchors(annotation, ids)
    if not kept:
        return "A run needs a box a person placed, refined or accepted in the range: none yet."
    names = ", ".join(f"{all_ids.index(f) + 1} ({why_kept(annotation.frames[f])})" for f in kept[:SHOWN])
    more = f" and {len(kept) - SHOWN} more" if len(kept) > SHOWN else ""
    others = len(ids) - len(kept)
    posed = sum(1 for f in ids if f in annotation.frames and f not in kept)
    replaced = f", replacing the {posed} tracked ones there" if posed else ""
    return (f"A run over frames {all_ids.index(ids[0]) + 1}-{all_ids.index(ids[-1]) + 1} **keeps {len(kept)} box"
            f"{'es' if len(kept) != 1 else ''}** as anchors: frame{'s' if len(kept) != 1 else ''} {names}{more}; it poses the other {others}{replaced}. "
            "An anchor takes the pose the other frames agree on where that lies within its placement's tolerance "
            "(its box stays in the document, and later runs anchor on it); else it keeps its box and is flagged.")


def changes_markdown(changes: list[Change], new: int) -> str:
    """A run's changes for the page: the frames that moved, largest first (frames counted from 1), and the new ones."""
    if not changes:
        moved = "no posed frame moved"
    else:
        items = "; ".join(f"{c.index + 1}: {c.degrees:.1f}°, {c.metres * 1000:.0f} mm" for c in changes[:SHOWN])
        more = f"; and {len(changes) - SHOWN} more" if len(changes) > SHOWN else ""
        moved = f"**{len(changes)} posed frame{'s' if len(changes) != 1 else ''} moved** (frame: turn, shift), largest first: {items}{more}"
    return f"{moved}; {new} frame{'s' if new != 1 else ''} got a first pose."
