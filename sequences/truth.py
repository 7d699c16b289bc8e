"""A sequence's true object poses, shape and masks, whatever the sequence's source.

Synthetic sequences keep theirs in ``SEQ/truth/`` (:mod:`sequences.synth.truth`); real datasets with object
poses (YCB-Video, BOP) give one truth per object (:mod:`sequences.ycbv`, :mod:`sequences.bop`).
:func:`open_truth` finds it. Conventions as the annotation document's: poses map the object (ShapeNet
axes, box-centred, metres) to the camera (OpenCV), quaternions x y z w.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from .errors import InputError


@dataclass
class Truth:
    """True poses (frame id -> 4x4 object-to-camera), the object's surface (a mesh, or points where a dataset gives
    only points), per-frame masks on demand, and the facts an annotation document holds (category, symmetry,
    extents: full box sides along object x, y, z, metres)."""

    root: Path
    category: str
    symmetry: str
    extents: np.ndarray
    poses: dict[str, np.ndarray]
    mesh: trimesh.Trimesh | None
    notes: dict = field(default_factory=dict)  # anything else the source holds (a generator's seed, camera, grasps)
    points: np.ndarray | None = None  # (N, 3) surface points, object frame, where there is no mesh
    masks: Callable[[str], np.ndarray] | None = None  # frame id -> (H, W) bool visible-object mask

    @property
    def ids(self) -> list[str]:
        return sorted(self.poses)

    def mask(self, frame_id: str) -> np.ndarray:
        """(H, W) bool: pixels where the object is the visible surface in frame ``frame_id``."""
        if self.masks is None:
            raise InputError(self.root, "this truth has no masks")
        return self.masks(frame_id)

    def surface_points(self, n: int, seed: int = 0) -> np.ndarray:
        """(n', 3) points on the true surface, object frame: ``n`` area-weighted mesh samples, or the given points."""
        if self.mesh is not None:
            return np.asarray(trimesh.sample.sample_surface(self.mesh, n, seed=seed)[0], dtype=np.float64)
        return np.asarray(self.points, dtype=np.float64)


def open_truth(root: str | Path, object_name: str | None = None) -> Truth:
    """The truth of the sequence at ``root``: a synthetic sequence's ``truth/``, or one object's (``object_name``)
    in a YCB-Video video or a BOP scene. Raises InputError where there is none."""
    root = Path(root)
    if (root / "scene_gt.json").is_file():
        from .bop import load_bop_truth

        return load_bop_truth(root, object_name)
    if (root / "poses.json").is_file() and any(root.glob("*-color.*")):
        from .ycbv import load_ycbv_truth

        return load_ycbv_truth(root, object_name)
    from .synth.truth import load_truth

    return load_truth(root)
