"""Joint refinement: every frame registered to the model built from all frames, so drift cannot build up.

The model of all frames (at their current poses) averages the views; voxels seen in fewer than
``global_min_hits`` frames (a hand that moved relative to the object) are left out of the target.
A few rounds alternate between rebuilding the model and re-registering each frame to it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .model import ObjectModel
from .propagate import predict
from .tracker import FrameResult, Tracker


def build_model(tracker: Tracker, poses: dict[str, np.ndarray], max_frames: int, always: list[str] = ()) -> ObjectModel:
    """The model of up to ``max_frames`` evenly spaced posed frames (plus ``always``), object frame."""
    ids = list(poses)
    if len(ids) > max_frames:
        picks = np.unique(np.linspace(0, len(ids) - 1, max_frames).round().astype(int))
        ids = [ids[i] for i in picks]
    ids = list(dict.fromkeys(list(ids) + [m for m in always if m in poses]))
    model = tracker.new_model()
    for frame_id in ids:
        tracker.add_to_model(model, frame_id, poses[frame_id])
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
) -> dict[str, FrameResult]:
    """Re-register every frame of ``results`` (in order) to the model of all of them, ``rounds`` times.

    The model is built from the frames that are not suspect (registration failed, or the chains
    disagree); a suspect frame starts from its predecessor's refined pose (constant velocity)
    instead of its own, so a chain that lost the object is repaired against the whole model.
    A frame whose registration fails keeps its pose and figures (with the failure noted).
    """
    config = tracker.config
    for _ in range(rounds):
        poses = {k: r.pose for k, r in results.items() if not suspect(r, config)}
        if len(poses) < max(3, len(results) // 4):
            poses = {k: r.pose for k, r in results.items()}
        model = build_model(tracker, poses, config.max_global_frames, [a for a in anchors if a in poses])
        hits = min_hits_for(model, config)
        updated: dict[str, FrameResult] = {}
        last: list[np.ndarray] = []
        for frame_id, previous in results.items():
            init = previous.pose
            if suspect(previous, config) and last:
                init = predict(last[-1], last[-2]) if len(last) > 1 else last[-1]
            result = tracker.register(frame_id, init, model, hits)
            if result.ok and init is not previous.pose and result.figures.get("fitness", 0.0) < config.min_fitness:
                result = tracker.register(frame_id, previous.pose, model, hits)  # the prediction was worse than the chains' pose
            if result.ok:
                figures = dict(previous.figures)
                figures.update(result.figures)
                figures.pop("error", None)
                updated[frame_id] = FrameResult(result.pose, True, figures)
                if result.figures.get("fitness", 0.0) >= config.min_fitness:
                    last = (last + [result.pose])[-2:]
            else:
                figures = dict(previous.figures)
                figures.setdefault("error", result.figures.get("error", "registration failed"))
                updated[frame_id] = FrameResult(previous.pose, False, figures)
            if step is not None:
                step()
        results = updated
    return results


def suspect(result: FrameResult, config) -> bool:
    """Whether a frame's current pose is doubtful: failed, or its two chains disagree beyond the thresholds."""
    figures = result.figures
    return (
        not result.ok
        or figures.get("chain_disagreement_deg", 0.0) > config.max_chain_disagreement_deg
        or figures.get("chain_disagreement_m", 0.0) > config.max_chain_disagreement_m
    )
