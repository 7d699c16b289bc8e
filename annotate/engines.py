"""The two tracking engines behind one switch, while they are compared (docs/tracking.md).

``graph`` (annotate.estimator): chains, one pose graph over all frames solved by GTSAM, rounds against the model of
all frames. ``chains`` (annotate.tracking): the earlier engine of chains, blends and per-shape corrections. Both
offer ``track_sequence(sequence, annotation, frames=None, config=None, progress=None)`` and ``refine_frame``.
"""

from __future__ import annotations

import os
from types import ModuleType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from sequences.annotation import Annotation, FramePose

#: What a batch's local processes import once (batch.local's server): the tracking engines.
TRACK_PRELOAD = ("numpy", "scipy.spatial", "open3d", "annotate.tracking", "annotate.estimator")
ENGINES = ("graph", "chains")
#: the engine used unless ``--engine`` or $REDWOOD_GT_ENGINE names another
DEFAULT_ENGINE = "chains"


def engine_name(name: str | None = None) -> str:
    """``name``, else $REDWOOD_GT_ENGINE, else the default; ValueError for an unknown one."""
    chosen = name or os.environ.get("REDWOOD_GT_ENGINE") or DEFAULT_ENGINE
    if chosen not in ENGINES:
        raise ValueError(f"unknown tracking engine {chosen!r}: choose one of {', '.join(ENGINES)}")
    return chosen


def tracking_engine(name: str | None = None) -> ModuleType:
    """The module of the engine ``name`` (see :func:`engine_name`)."""
    if engine_name(name) == "graph":
        from . import estimator

        return estimator
    from . import tracking

    return tracking


def kept_by_a_person(pose: "FramePose") -> bool:
    """Whether a frame's box is a person's: placed (``manual``), refined, or accepted in review."""
    return pose.source in ("manual", "refined") or pose.extra.get("reviewed") == "accepted"


def anchor_frames(annotation: "Annotation", ids: list[str]) -> list[str]:
    """The frames of ``ids`` whose box a person placed, refined or accepted, in order: every engine keeps them as
    anchors (their boxes stay in the document, :func:`anchored_pose`) unless the person clears them."""
    return [f for f in ids if f in annotation.frames and kept_by_a_person(annotation.frames[f])]


def anchor_correction(placed: "np.ndarray", estimate: "np.ndarray", symmetric: bool) -> tuple[float, float]:
    """How far an anchor's ``estimate`` lies from the person's box ``placed`` (both 4x4, object to camera at the colour
    instant): degrees between the rotations (between their y axes for symmetry y) and metres between the box centres.
    Every engine judges by it whether the estimate follows the box (:func:`anchored_pose`)."""
    import numpy as np

    from evaluate.metrics.pose_errors import rotation_error

    degrees = float(rotation_error(placed[:3, :3], estimate[:3, :3], "y" if symmetric else "none"))
    return degrees, float(np.linalg.norm(placed[:3, 3] - estimate[:3, 3]))


def anchored_pose(old: "FramePose", estimate: "np.ndarray", extra: dict, follows: bool) -> "FramePose":
    """An anchor's pose after a run, its source kept: where ``follows`` (the estimate lies within the placement's
    tolerance of the person's box), the estimate (4x4, object to camera at the colour instant) with the person's box
    kept under ``placed``; else the person's box. The box a person gives stays what every later run anchors on
    (FramePose.placed_matrix): one rigid object frame needs each placed box moved by its own placement error, or the
    poses jump at every anchor."""
    from sequences.annotation import PLACED_KEY, FramePose

    extra = {k: v for k, v in extra.items() if k != PLACED_KEY}
    person = old.placed_box
    if not follows:
        return FramePose(person.position, person.orientation, old.source, extra)
    extra[PLACED_KEY] = {"position": [float(x) for x in person.position], "orientation": [float(x) for x in person.orientation]}
    return FramePose.from_matrix(estimate, old.source, extra)
