"""Frame-to-model tracking along the sequence, forward or backward from a posed frame.

The chain's model starts with the anchor frame's points and grows with every frame that
registers well, so a frame is aligned to everything seen so far, not only to its neighbour.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from evaluate.geometry import invert, rigid

from .tracker import FrameResult, Tracker


def predict(previous: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Constant-velocity prediction of the next pose (4x4, rigid) from the last two."""
    # the object's motion in the camera frame between the last two frames, applied once more
    motion = previous @ invert(before)
    # made rigid again: ``invert`` transposes, so a rotation block off by e gives a prediction off by about 2e
    # plus the error before it, and a chain's poses drifted off the rotations 2.4 times further each frame
    # (measured: from rounding, 1e-6 after 16 frames and 0.7, a shear of the points, after 40: v5 bowl seed 0,
    # 3 manual frames); the seams' jump costs (reconcile) and the refinement's flip repair use it too
    return rigid(motion @ previous)


def run_chain(
    tracker: Tracker,
    frame_ids: list[str],
    start_pose: np.ndarray,
    step: Callable[[], None] | None = None,
) -> dict[str, FrameResult]:
    """Track ``frame_ids[1:]`` in order, starting from ``frame_ids[0]`` posed at ``start_pose`` (4x4).

    Returns each tracked frame's result (the start frame excluded). A frame that fails keeps the
    prediction and is not added to the model; the chain goes on from the last good pose.
    """
    config = tracker.config
    model = tracker.new_model()
    tracker.add_to_model(model, frame_ids[0], start_pose)
    results: dict[str, FrameResult] = {}
    previous, before = start_pose, None
    for frame_id in frame_ids[1:]:
        guess = predict(previous, before) if before is not None else previous.copy()
        result = tracker.register(frame_id, guess, model, refresh_every=config.model_refresh)
        if not result.ok and before is not None:
            result = tracker.register(frame_id, previous.copy(), model, refresh_every=config.model_refresh)  # the velocity guess may have overshot
        results[frame_id] = result
        if result.ok and result.figures.get("fitness", 0.0) >= config.min_fitness:
            tracker.add_to_model(model, frame_id, result.pose)
            previous, before = result.pose, previous
        if step is not None:
            step()
    return results
