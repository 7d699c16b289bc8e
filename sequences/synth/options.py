"""The generator's options and their checks, importable without the heavy renderer (so bad input fails fast)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..annotation import CATEGORIES
from ..errors import InputError

#: Bumped whenever the generator's output changes, so cached sample sequences are regenerated.
GENERATOR_VERSION = 5
#: Categories the generator can build without a mesh file.
PROCEDURAL_CATEGORIES = ("bottle", "bowl", "mug", "can", "camera", "laptop")
#: Axes a given mesh may use: ShapeNet's (y up), or REDWOOD75's raw axes (x = ShapeNet z, y = -ShapeNet y, z = ShapeNet x).
MESH_AXES = ("shapenet", "redwood75")


def check_arguments(out: Path, category: str, frames: int, mesh: str | Path | None, mesh_axes: str) -> None:
    """Refuse bad arguments before any work: an existing non-empty OUT, a bad category, frame count or axes."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "output exists and is not an empty folder; choose a new folder (nothing was written)")
    allowed = CATEGORIES if mesh is not None else PROCEDURAL_CATEGORIES
    if category not in allowed:
        hint = "" if mesh is not None or category not in CATEGORIES else " without --mesh"
        raise InputError(out, f"category {category!r} is not one of {', '.join(allowed)}{hint}")
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise InputError(out, f"frames must be a positive integer, got {frames!r}")
    if mesh_axes not in MESH_AXES:
        raise InputError(mesh if mesh is not None else out, f"mesh axes {mesh_axes!r} are not one of {', '.join(MESH_AXES)}")
