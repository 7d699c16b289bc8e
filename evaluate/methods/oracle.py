"""``oracle``: the ground truth itself, optionally disturbed by seeded noise (for testing the evaluation).

Configuration (all optional, default 0 = the exact truth):

- ``position_error`` (m): the position moved by exactly this distance, in a random direction;
- ``rotation_error`` (deg): the orientation turned by exactly this angle about a random axis
  perpendicular to the object's y axis, so the rotation error is this angle for symmetric and
  non-symmetric objects alike;
- ``extents_error``: every extent multiplied by ``1 + extents_error``, and so is the reconstruction;
- ``position_noise`` (m), ``rotation_noise`` (deg), ``extents_noise`` (relative): Gaussian standard
  deviations added on top (per axis; the angle about a uniformly random axis);
- ``reconstruction`` (true): return the true mesh (scaled as the extents) as the reconstruction;
- ``seed`` (0): noise for a sample depends only on the seed and the sample's name, not on order.
"""

from __future__ import annotations

import zlib

import numpy as np
from scipy.spatial.transform import Rotation

from evaluate.datasets import Dataset, Sample
from sequences.errors import InputError

from .base import Prediction
from .sample_method import FrameInputs, PredictionFailure, SampleMethod

OPTIONS = {
    "position_error": 0.0,
    "rotation_error": 0.0,
    "extents_error": 0.0,
    "position_noise": 0.0,
    "rotation_noise": 0.0,
    "extents_noise": 0.0,
    "reconstruction": True,
    "seed": 0,
}


class OracleMethod(SampleMethod):
    """The truth with configurable seeded noise (see the module docstring)."""

    needs_frames = False

    def __init__(self, config: dict | None = None, dataset: Dataset | None = None, name: str = "oracle") -> None:
        config = dict(config or {})
        unknown = sorted(set(config) - set(OPTIONS))
        if unknown:
            raise InputError(None, f"oracle: unknown options {unknown}; expected {sorted(OPTIONS)}")
        values = {**OPTIONS, **config}
        for key, value in values.items():
            if key == "reconstruction":
                if not isinstance(value, bool):
                    raise InputError(None, f"oracle: reconstruction must be true or false, got {value!r}")
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                raise InputError(None, f"oracle: {key} must be a number, got {value!r}")
            if key != "seed" and value < 0:
                raise InputError(None, f"oracle: {key} must not be negative, got {value!r}")
        if values["extents_error"] <= -1:
            raise InputError(None, "oracle: extents_error must be above -1")
        self.options = values
        self.name = name
        self.dataset = dataset

    def rng(self, sample: Sample) -> np.random.Generator:
        return np.random.default_rng([int(self.options["seed"]), zlib.crc32(sample.label.encode())])

    def predict(self, sample: Sample, inputs: FrameInputs | None = None) -> Prediction:
        o, rng = self.options, self.rng(sample)
        direction = rng.normal(size=3)
        position = sample.position + o["position_error"] * direction / np.linalg.norm(direction) + rng.normal(scale=o["position_noise"], size=3)
        # exact turn about an axis in the object's xz plane (perpendicular to the symmetry axis)
        phi = rng.uniform(0.0, 2.0 * np.pi)
        turn = Rotation.from_rotvec(np.radians(o["rotation_error"]) * np.array([np.cos(phi), 0.0, np.sin(phi)]))
        axis = rng.normal(size=3)
        jitter = Rotation.from_rotvec(np.radians(rng.normal(scale=o["rotation_noise"])) * axis / np.linalg.norm(axis))
        orientation = (Rotation.from_quat(sample.orientation) * turn * jitter).as_quat()
        factor = (1.0 + o["extents_error"]) * (1.0 + rng.normal(scale=o["extents_noise"], size=3))
        if (factor <= 0).any():
            raise PredictionFailure("oracle: extents noise made an extent non-positive")
        reconstruction = None
        if o["reconstruction"] and self.dataset is not None:
            mesh = self.dataset.mesh(sample)
            if mesh is not None:
                reconstruction = mesh.copy()
                reconstruction.vertices = np.asarray(mesh.vertices) * factor
        return Prediction(position, orientation, sample.extents * factor, reconstruction)
