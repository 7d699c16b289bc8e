"""What a refine did, in words: whether its result may replace the box, and why not.

Both tracking engines (annotate.engines) return a ``refined`` FramePose with their figures. The graph engine leaves a
box whose result the frame does not confirm where it was, flagged with its reason; the chains engine returns wherever
its registration ended. The panel judges both alike from the figures: a refine fails where the box holds too few
points, or the frame's depth does not confirm the object the other posed frames show where the result puts it
(annotate.depth_agreement: the camera sees through too much of it; a result without those figures: too small a share
of the box's points lies on that object, the engine's ``min_fitness``); then the box stays as it was and the annotator
reads why and what to do. A refine that succeeds but is flagged for another reason replaces the box, flagged.
"""

from __future__ import annotations

from dataclasses import dataclass

from annotate.depth_agreement import agreement_reason
from sequences.annotation import FramePose

#: What to do when a refine fails: the box must hold the object for its points to fit it.
ADVICE = "move the box onto the object (click it, or step it) and refine again"


@dataclass(frozen=True)
class RefineVerdict:
    """``ok``: the result may replace the box; ``reason``: why not, or why it is flagged (words, empty when neither)."""

    ok: bool
    reason: str = ""


def engine_config(engine):
    """The configuration the interactive refine runs with: the engine's own defaults, a model from the nearest
    :data:`REFINE_MODEL_FRAMES` posed frames where the engine builds it from many (the chains engine, each frame read
    from disk per call); None for an engine without a configuration class."""
    if hasattr(engine, "TrackingConfig"):
        return engine.TrackingConfig(max_global_frames=REFINE_MODEL_FRAMES)
    if hasattr(engine, "EstimatorConfig"):
        return engine.EstimatorConfig()
    return None


#: Posed frames (twice the nearest used) that the chains engine's interactive refine builds its model from.
REFINE_MODEL_FRAMES = 6
#: Thresholds when an engine's configuration does not say (the engines' defaults).
DEFAULT_MIN_FITNESS = 0.5
DEFAULT_MIN_POINTS = 100


def judge_refine(result: FramePose, config=None) -> RefineVerdict:
    """Whether ``result`` (an engine's refine_frame answer) may replace the box, with the reason in words."""
    extra = result.extra
    min_fitness = float(getattr(config, "min_fitness", DEFAULT_MIN_FITNESS))
    min_points = int(getattr(config, "min_points", DEFAULT_MIN_POINTS))
    if extra.get("error"):
        return RefineVerdict(False, f"the registration failed ({extra['error']}): {ADVICE}")
    points = extra.get("points")
    if isinstance(points, (int, float)) and points < min_points:
        return RefineVerdict(False, f"only {int(points)} points of the frame lie in the box: {ADVICE}")
    disagreement = agreement_reason(extra)
    if disagreement:
        return RefineVerdict(False, f"{disagreement}: {ADVICE}")
    fitness = extra.get("fitness")
    if "depth_votes" not in extra and isinstance(fitness, (int, float)) and fitness < min_fitness:
        return RefineVerdict(False, f"only {fitness:.0%} of the box's points lie on the object the other posed frames show "
                                    f"(at least {min_fitness:.0%} needed): {ADVICE}")
    if extra.get("flagged"):
        reason = str(extra.get("flag_reason") or "the tracking engine marked it for review")
        if fitness is None and "fit" in reason:  # an engine that judged the fit itself and left the box where it was
            return RefineVerdict(False, reason)
        return RefineVerdict(True, reason)
    return RefineVerdict(True)
