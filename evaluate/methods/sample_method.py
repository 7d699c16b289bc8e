"""What the evaluation asks of every method: a prediction for one dataset sample, or a reason it has none.

Three kinds answer it: a :class:`~evaluate.methods.base.Method` run here on the sample's frames
(:class:`FrameMethod`), a predictions file (:mod:`evaluate.methods.predictions`), and the oracle
(:mod:`evaluate.methods.oracle`). A sample whose prediction is missing or malformed raises
:class:`PredictionFailure`; the evaluation counts it as incorrect and lists the reason.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from evaluate.datasets import Dataset, Sample
from sequences.errors import InputError

from .base import Method, Prediction

#: A predicted quaternion further than this from unit norm is malformed, not renormalised.
QUATERNION_NORM_TOLERANCE = 1e-3


class PredictionFailure(Exception):
    """A sample has no usable prediction; the message is the reason reported in ``failed``."""


class FrameInputs:
    """One sample's colour (H, W, 3) uint8, depth (H, W) float32 m and mask (H, W) bool, read once, on demand."""

    def __init__(self, dataset: Dataset, sample: Sample) -> None:
        self.dataset, self.sample = dataset, sample
        self._color = self._depth = self._mask = None

    @property
    def color(self) -> np.ndarray:
        if self._color is None:
            self._color = self.dataset.color(self.sample)
        return self._color

    @property
    def depth(self) -> np.ndarray:
        if self._depth is None:
            self._depth = self.dataset.depth(self.sample)
        return self._depth

    @property
    def mask(self) -> np.ndarray:
        if self._mask is None:
            self._mask = self.dataset.mask(self.sample, self.depth)
        return self._mask


class SampleMethod(ABC):
    """Gives a :class:`Prediction` for a dataset sample."""

    name: str = "method"
    #: whether it reads the sample's RGB-D frames (then ``--frames`` is needed)
    needs_frames: bool = False

    @abstractmethod
    def predict(self, sample: Sample, inputs: FrameInputs) -> Prediction:
        """The prediction for ``sample``; raises :class:`PredictionFailure` when there is none."""

    def prepare_shared(self, categories: list[str], folder) -> None:
        """What every sample of ``categories`` shares, once for a batch (:meth:`evaluate.methods.base.Method.prepare_shared`).
        Nothing by default."""


class FrameMethod(SampleMethod):
    """Runs a :class:`Method` on the sample's frames and instance mask."""

    needs_frames = True

    def __init__(self, name: str, method: Method) -> None:
        self.name, self.method = name, method

    def prepare_shared(self, categories: list[str], folder) -> None:
        """The method's :meth:`~evaluate.methods.base.Method.prepare_shared` (a class of cpas_toolbox's lacks it)."""
        prepare = getattr(self.method, "prepare_shared", None)
        if callable(prepare):
            prepare(categories, folder)

    def predict(self, sample: Sample, inputs: FrameInputs) -> Prediction:
        mask = inputs.mask
        if not mask.any():
            raise PredictionFailure("empty instance mask (object not visible)")
        try:
            prediction = self.method.inference(inputs.color, inputs.depth, mask, sample.category, sample.camera)
        except (PredictionFailure, InputError, KeyboardInterrupt):
            raise
        except Exception as error:
            # a method failing on one frame is a wrong answer for that frame, not the end of a long
            # run; the exception type and message are listed with the failed sample
            raise PredictionFailure(f"method raised {error.__class__.__name__}: {' '.join(str(error).split())}"[:300]) from error
        return check_prediction(prediction)


def check_prediction(prediction: Any) -> Prediction:
    """Validate a method's answer: finite (3,) position, unit (4,) quaternion, positive finite (3,) extents,
    a reconstruction that is None, finite (N, 3) points (N > 0) or a mesh with triangles, a finite score
    and a category that is None or a name.
    Returns it with the quaternion normalised; raises :class:`PredictionFailure` naming the problem."""
    if not isinstance(prediction, Prediction):
        raise PredictionFailure(f"method returned {type(prediction).__name__}, not a Prediction")
    for field, n in (("position", 3), ("orientation", 4), ("extents", 3)):
        value = np.asarray(getattr(prediction, field))
        if value.shape != (n,):
            raise PredictionFailure(f"{field} has shape {value.shape}, expected ({n},)")
        if not np.isfinite(value).all():
            raise PredictionFailure(f"{field} is not finite: {value.tolist()}")
    norm = float(np.linalg.norm(prediction.orientation))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise PredictionFailure(f"orientation is not a unit quaternion (norm {norm:.6g})")
    if (prediction.extents <= 0).any():
        raise PredictionFailure(f"extents must be positive: {prediction.extents.tolist()}")
    reconstruction = prediction.reconstruction
    if reconstruction is not None:
        vertices = getattr(reconstruction, "vertices", None)
        if vertices is not None:  # a mesh
            if len(getattr(reconstruction, "faces", [])) == 0:
                raise PredictionFailure("reconstruction mesh has no triangles")
            points = np.asarray(vertices)
        else:
            points = np.asarray(reconstruction, dtype=np.float64)
            if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
                raise PredictionFailure(f"reconstruction points have shape {points.shape}, expected (N, 3) with N > 0")
            reconstruction = points
        if not np.isfinite(points).all():
            raise PredictionFailure("reconstruction has non-finite coordinates")
    score = prediction.score
    if isinstance(score, bool) or not isinstance(score, (int, float, np.integer, np.floating)) or not np.isfinite(score):
        raise PredictionFailure(f"score must be a finite number, got {score!r}")
    category = prediction.category
    if category is not None and (not isinstance(category, str) or not category.strip()):
        raise PredictionFailure(f"category must be a non-empty string, got {category!r}")
    return Prediction(prediction.position, prediction.orientation / norm, prediction.extents, reconstruction, float(score), category)
