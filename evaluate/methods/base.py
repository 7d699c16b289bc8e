"""The method interface: one RGB-D frame, an instance mask and a category in; pose, box and shape out.

Frames and units: inputs are the colour image (H, W, 3) uint8 RGB, the depth image (H, W) float32
in metres (0 = no measurement), the instance mask (H, W) bool, and the camera. The prediction's
pose maps object to camera (OpenCV camera, metres; quaternion x, y, z, w) with the object in
ShapeNet axes (y up), box-centred; ``extents`` are the box's full side lengths in metres.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sequences.camera import Camera


@dataclass
class Prediction:
    """A method's answer for one sample."""

    position: np.ndarray  # (3,) box centre, camera frame, m
    orientation: np.ndarray  # (4,) object->camera quaternion x, y, z, w
    extents: np.ndarray  # (3,) full side lengths along object x, y, z, m
    reconstruction: Any = None  # optional: (N, 3) points or a trimesh.Trimesh, object frame, m
    score: float = 1.0  # detection confidence, higher = surer (ranks detections for NOCS-style mAP)
    category: str | None = None  # detected category; None = the sample's category

    def __post_init__(self) -> None:
        self.position = np.asarray(self.position, dtype=np.float64).reshape(3)
        self.orientation = np.asarray(self.orientation, dtype=np.float64).reshape(4)
        self.extents = np.asarray(self.extents, dtype=np.float64).reshape(3)


class Method(ABC):
    """A pose-and-shape estimator run here, frame by frame."""

    name: str = "method"

    @abstractmethod
    def inference(self, color: np.ndarray, depth: np.ndarray, mask: np.ndarray, category: str, camera: Camera) -> Prediction:
        """Estimate the pose, extents and (optionally) the shape of the masked object."""

    def prepare_shared(self, categories: list[str], folder: Path) -> None:
        """Prepare what every sample of ``categories`` shares (a category's template, ...) once for a batch: each
        unit calls it before its samples, with the same ``folder`` to keep it in, where the first unit writes it
        (atomically) and the later ones read it. Nothing by default."""
