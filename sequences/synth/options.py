"""The generator's options and their checks, importable without the heavy renderer (so bad input fails fast).

A sequence is made from a shape (procedural, or a mesh file), a coverage (how the object is shown),
a texture and a sensor model. :class:`SensorOptions` and :class:`CaptureOptions` hold them; their
defaults look like Redwood's captures: a PrimeSense's disparity steps and flying pixels, colour and
depth a fraction of a frame apart, a pixel of colour-to-depth registration error.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..annotation import CATEGORIES
from ..axes import MESH_AXES
from ..errors import InputError

#: Bumped whenever the generator's output changes, so cached sample sequences are regenerated.
GENERATOR_VERSION = 10
#: Procedural shapes and their category: each category's plain shape, and variants that keep the category's
#: label (bottles and bowls say ``symmetry: y``) but are no solids of revolution, and mugs with other handles.
PROCEDURAL_SHAPES = {
    "bottle": "bottle", "flat_bottle": "bottle", "fluted_bottle": "bottle",
    "bowl": "bowl", "square_bowl": "bowl", "oval_bowl": "bowl",
    "can": "can",
    "mug": "mug", "mug_d_handle": "mug", "mug_ring_handle": "mug",
    "camera": "camera", "laptop": "laptop",
}
#: Categories the generator can build without a mesh file.
PROCEDURAL_CATEGORIES = ("bottle", "bowl", "mug", "can", "camera", "laptop")
#: How the object is shown: every side (turned through all orientations, opening and bottom to the camera),
#: a few key orientations only (as people show objects; the bottom or the opening may never be seen), or
#: resting on a table, picked up, shown, put down and picked up again.
COVERAGES = ("every_side", "key_orientations", "table")
#: The object's look: a seeded pattern (stripes, a checkered band), a label on a plain body, or one plain colour.
TEXTURES = ("pattern", "label", "plain")


@dataclass(frozen=True)
class SensorOptions:
    """The depth sensor's imperfections beyond its noise and holes (see :mod:`.sensor`); zero turns one off."""

    quantisation: bool = True  # disparity in 1/8 pixel steps: depth steps growing with z^2 (1 mm at 0.6 m, 3 mm at 1 m)
    flying_pixels: float = 0.5  # chance that a pixel next to a depth jump reads a depth between the two surfaces
    depth_offset_frames: float = 0.3  # depth taken up to this many frame periods before or after colour (per sequence)
    registration_px: float = 1.0  # colour-to-depth registration error, pixels (one direction per sequence)

    @classmethod
    def ideal(cls) -> "SensorOptions":
        """Noise and holes only: no quantisation, flying pixels, time offset or registration error."""
        return cls(quantisation=False, flying_pixels=0.0, depth_offset_frames=0.0, registration_px=0.0)


@dataclass(frozen=True)
class CaptureOptions:
    """How a sequence is made besides its shape: coverage, key orientations, turn speed, texture, sensor."""

    coverage: str = "every_side"
    #: for key_orientations: a REDWOOD75 annotations.json and a sequence id in it ("FILE:ID"), whose annotated
    #: orientations the object passes through in order; None draws a few orientations as people show objects
    keys: str | None = None
    turn_speed: float = 1.0  # times the default pace of turning (about 4.5 degrees per frame while held)
    texture: str = "pattern"
    sensor: SensorOptions = field(default_factory=SensorOptions)

    def to_dict(self) -> dict:
        return asdict(self)


def check_arguments(out: Path, category: str, frames: int, mesh: str | Path | None, mesh_axes: str, shape: str | None = None) -> None:
    """Refuse bad arguments before any work: an existing non-empty OUT, a bad category, shape, frame count or axes."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "output exists and is not an empty folder; choose a new folder (nothing was written)")
    allowed = CATEGORIES if mesh is not None else PROCEDURAL_CATEGORIES
    if category not in allowed:
        hint = "" if mesh is not None or category not in CATEGORIES else " without --mesh"
        raise InputError(out, f"category {category!r} is not one of {', '.join(allowed)}{hint}")
    if shape is not None:
        if mesh is not None:
            raise InputError(out, "give either --shape (a procedural shape) or --mesh (a mesh file), not both")
        if shape not in PROCEDURAL_SHAPES:
            raise InputError(out, f"shape {shape!r} is not one of {', '.join(PROCEDURAL_SHAPES)}")
        if PROCEDURAL_SHAPES[shape] != category:
            raise InputError(out, f"shape {shape!r} is a {PROCEDURAL_SHAPES[shape]}, not a {category}")
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise InputError(out, f"frames must be a positive integer, got {frames!r}")
    if mesh_axes not in MESH_AXES:
        raise InputError(mesh if mesh is not None else out, f"mesh axes {mesh_axes!r} are not one of {', '.join(MESH_AXES)}")


def check_capture(out: Path, capture: CaptureOptions, frames: int) -> None:
    """Refuse capture options out of range (one-line InputError naming ``out``)."""
    if capture.coverage not in COVERAGES:
        raise InputError(out, f"coverage {capture.coverage!r} is not one of {', '.join(COVERAGES)}")
    if capture.texture not in TEXTURES:
        raise InputError(out, f"texture {capture.texture!r} is not one of {', '.join(TEXTURES)}")
    if not (np.isfinite(capture.turn_speed) and 0.25 <= capture.turn_speed <= 4.0):
        raise InputError(out, f"turn speed {capture.turn_speed!r} is outside 0.25 .. 4 (times the default pace)")
    if capture.keys is not None and capture.coverage != "key_orientations":
        raise InputError(out, "key orientations (--keys) apply to --coverage key_orientations only")
    if capture.coverage == "table" and frames < 40:
        raise InputError(out, f"the table coverage needs at least 40 frames, got {frames}")
    sensor = capture.sensor
    if not (0.0 <= sensor.flying_pixels <= 1.0):
        raise InputError(out, f"flying-pixel chance {sensor.flying_pixels!r} is outside 0 .. 1")
    if not (0.0 <= sensor.depth_offset_frames < 0.5):
        raise InputError(out, f"depth offset {sensor.depth_offset_frames!r} frames is outside 0 .. 0.5 (colour and depth pair by nearest time)")
    if not (0.0 <= sensor.registration_px <= 5.0):
        raise InputError(out, f"registration error {sensor.registration_px!r} px is outside 0 .. 5")
