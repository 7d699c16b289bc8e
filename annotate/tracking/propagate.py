"""Frame-to-model tracking along the sequence, forward or backward from a posed frame.

The chain's model starts with the anchor frame's points and grows with every frame that
registers well, so a frame is aligned to everything seen so far, not only to its neighbour.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from evaluate.geometry import invert, rigid

from .config import TrackingConfig
from .quality import pose_difference
from .tracker import FrameResult, Tracker


def predict(previous: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Constant-velocity prediction of the next pose (4x4, rigid) from the last two."""
    # the object's motion in the camera frame between the last two frames, applied once more
    motion = previous @ invert(before)
    # made rigid again: ``invert`` transposes, so a rotation block off by e gives a prediction off by about 2e
    # plus the error before it, and a chain's poses drift off the rotations further each frame (from rounding at
    # first to a shear of the points within a few dozen frames); the seams' jump costs (reconcile) and the
    # refinement's flip repair use it too
    return rigid(motion @ previous)


def follows(result: FrameResult, start: np.ndarray, config: TrackingConfig) -> bool:
    """Whether a chain takes a frame's registered pose as its next step (grows its model with the frame and predicts
    from it): it fits the chain's model (``min_fitness``), or it fits at least ``chain_follow_fitness`` and lies
    within ``chain_follow_step_deg`` / ``_m`` of the pose it started from (``start``, 4x4).

    The fitness counts the frame's points near the model, and a model of the few frames seen so far covers little
    of an object that turns new surfaces to the camera: a chain that waits for ``min_fitness`` holds its last pose
    while the object moves on, and loses it; its later frames then register far off at a low fitness, with many
    ICP iterations each. A frame that fits less well but stays near where it started keeps the chain on the
    object. A lost chain's registrations move far from where they start: the step bound keeps them out.
    """
    if not result.ok:
        return False
    fitness = result.figures.get("fitness", 0.0)
    if fitness >= config.min_fitness:
        return True
    if fitness < config.chain_follow_fitness:
        return False
    turn, move = pose_difference(result.pose, start, False)
    return turn <= config.chain_follow_step_deg and move <= config.chain_follow_step_m


def run_chain(
    tracker: Tracker,
    frame_ids: list[str],
    start_pose: np.ndarray,
    step: Callable[[], None] | None = None,
) -> dict[str, FrameResult]:
    """Track ``frame_ids[1:]`` in order, starting from ``frame_ids[0]`` posed at ``start_pose`` (4x4).

    Returns each tracked frame's result (the start frame excluded). A frame the chain does not follow
    (:func:`follows`) is not added to the model; the chain goes on from the last pose it followed.
    """
    config = tracker.config
    model = tracker.new_model()
    tracker.add_to_model(model, frame_ids[0], start_pose)
    results: dict[str, FrameResult] = {}
    previous, before = start_pose, None
    for frame_id in frame_ids[1:]:
        start = predict(previous, before) if before is not None else previous.copy()
        result = tracker.register(frame_id, start, model, refresh_every=config.model_refresh)
        if not result.ok and before is not None:
            start = previous.copy()  # the velocity guess may have overshot
            result = tracker.register(frame_id, start, model, refresh_every=config.model_refresh)
        results[frame_id] = result
        if follows(result, start, config):
            tracker.add_to_model(model, frame_id, result.pose)
            previous, before = result.pose, previous
        if step is not None:
            step()
    return results
