"""Joint refinement: every frame registered to the model built from all frames, so drift cannot build up.

The model of all frames (at their current poses) averages the views; voxels seen in fewer than
``global_min_hits`` frames (a hand that moved relative to the object) are left out of the target.
A few rounds alternate between rebuilding the model and re-registering each frame to it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .model import ObjectModel
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

    A frame whose registration fails keeps its pose and figures (with the failure noted).
    """
    config = tracker.config
    for _ in range(rounds):
        poses = {k: r.pose for k, r in results.items()}
        model = build_model(tracker, poses, config.max_global_frames, list(anchors))
        hits = min_hits_for(model, config)
        updated: dict[str, FrameResult] = {}
        for frame_id, previous in results.items():
            result = tracker.register(frame_id, previous.pose, model, hits)
            if result.ok:
                figures = dict(previous.figures)
                figures.update(result.figures)
                figures.pop("error", None)
                updated[frame_id] = FrameResult(result.pose, True, figures)
            else:
                figures = dict(previous.figures)
                figures.setdefault("error", result.figures.get("error", "registration failed"))
                updated[frame_id] = FrameResult(previous.pose, False, figures)
            if step is not None:
                step()
        results = updated
    return results
