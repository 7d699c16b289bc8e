"""One evaluation sample: a frame, the object's true pose, box and (optional) mesh, in ShapeNet axes.

Frames and units: ``position`` is the box centre in the OpenCV camera frame (metres),
``orientation`` the object->camera quaternion x, y, z, w, ``extents`` the box's full side lengths
along the object's ShapeNet axes (y up), metres. The mesh (when there is one) is in the same
object frame, box-centred, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evaluate.geometry import pose_matrix
from sequences.camera import Camera


@dataclass
class Sample:
    """Ground truth of one object in one frame."""

    dataset: str
    sequence: str
    frame: str  # frame id (the colour file's frame number, or its stem)
    category: str
    symmetry: str  # "none" | "y" (continuous symmetry about object +y)
    position: np.ndarray  # (3,) m, camera frame
    orientation: np.ndarray  # (4,) x y z w, object -> camera
    extents: np.ndarray  # (3,) m, full side lengths along ShapeNet x, y, z
    camera: Camera = field(default_factory=Camera)
    color_path: Path | None = None
    depth_path: Path | None = None
    mesh_path: Path | None = None  # None: no mesh; shape metrics are skipped for this sample
    instance: str | None = None  # instance id where a frame holds several objects (NOCS)
    mask_path: Path | None = None  # the dataset's own mask image (NOCS instance ids; masks reconstruct-sequence wrote)
    handle_visible: bool | None = None  # mugs: whether the handle is visible in this frame (NOCS gt_handle_visibility); None = unknown

    def __post_init__(self) -> None:
        self.position = np.asarray(self.position, dtype=np.float64).reshape(3)
        self.orientation = np.asarray(self.orientation, dtype=np.float64).reshape(4)
        self.extents = np.asarray(self.extents, dtype=np.float64).reshape(3)

    @property
    def key(self) -> tuple[str, str, str | None]:
        """(sequence, frame, instance): what a predictions file matches on."""
        return (self.sequence, self.frame, self.instance)

    @property
    def label(self) -> str:
        """Human-readable sample name for reports: ``sequence/frame[/instance]``."""
        return "/".join(part for part in self.key if part is not None)

    @property
    def pose(self) -> np.ndarray:
        """4x4 object -> camera transform."""
        return pose_matrix(self.position, self.orientation)

    @property
    def has_frames(self) -> bool:
        return self.color_path is not None and self.depth_path is not None
