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
    # plus the error before it, and a chain's poses drifted off the rotations 2.4 times further each frame
    # (measured: from rounding, 1e-6 after 16 frames and 0.7, a shear of the points, after 40: v5 bowl seed 0,
    # 3 manual frames); the seams' jump costs (reconcile) and the refinement's flip repair use it too
    return rigid(motion @ previous)


def follows(result: FrameResult, start: np.ndarray, config: TrackingConfig) -> bool:
    """Whether a chain takes a frame's registered pose as its next step (grows its model with the frame and predicts
    from it): it fits the chain's model (``min_fitness``), or it fits at least ``chain_follow_fitness`` and lies
    within ``chain_follow_step_deg`` / ``_m`` of the pose it started from (``start``, 4x4).

    The fitness counts the frame's points near the model, and a model of the few frames seen so far covers little
    of an object that turns new surfaces to the camera: a chain that waited for ``min_fitness`` held its last pose
    while the object moved on, and lost it. Measured on v5 laptop seed 0 (4 manual frames off by up to 3 deg / 5 mm /
    8 %): the chain back from frame 35 fitted frames 34-28 at 0.49-0.34 within 1 deg, took none of them, lost the
    laptop at frame 27 and registered its last 24 frames 5-180 deg off at fitness 0.00-0.21 (30-60 ICP iterations
    each); taking them, its fitness rose to 0.64-0.99. Over that sequence's 8 chains (192 registrations) the worst
    frame went from 180 to 3.9 deg off, the frames more than 10 mm off from 102 to 37, and the ICP iterations from
    20.8 to 8.8 per registration. A lost chain's registrations move far from where they start: the step bound keeps
    them out.
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
