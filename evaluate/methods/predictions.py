"""The predictions-file method: a JSON Lines file, one object per sample, for methods not run here.

Each line: ``{"sequence", "frame" (frame id; a colour file name or stem, or the frame number
as an integer, also matches),
"instance" (only for datasets with several objects per frame), "position" [3] (m, camera
frame), "orientation" [4] (x, y, z, w, object -> camera), "extents" [3] (m, full side lengths,
ShapeNet axes), "reconstruction" (optional: a mesh or point file, object frame, metres; relative
paths are relative to the predictions file), "score" (optional: the detection's confidence, a finite
number, default 1.0; ranks detections for NOCS-style mAP), "category" (optional: the detected category,
default the sample's)}``.

A sample without a line, or whose line is malformed (not finite, wrong shape, non-unit quaternion,
unreadable reconstruction, two lines for one sample) counts as incorrect, with the reason.
Lines that cannot be attributed to a sample (not JSON, no sequence/frame) are kept in
:attr:`PredictionsFile.problems`; lines for samples the dataset lacks in :attr:`PredictionsFile.unmatched`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from evaluate.datasets import Sample
from evaluate.datasets.redwood75 import frame_id
from sequences.documents import parse_json
from sequences.errors import InputError

from .base import Prediction
from .sample_method import FrameInputs, PredictionFailure, SampleMethod, check_prediction

POINT_SUFFIXES = (".npy", ".xyz", ".txt", ".pts")

Key = tuple[str, str, "str | None"]


def _key(sequence: Any, frame: Any, instance: Any) -> Key:
    """Matching key: a frame given as a number (5), a zero-padded id ("0000005") or a Redwood file name
    ("0000005-000000134064.jpg") all name the same frame."""
    frame = frame_id(str(frame))
    if frame.isdigit():
        frame = str(int(frame))
    return (str(sequence), frame, None if instance is None else str(instance))


class PredictionsFile(SampleMethod):
    """Predictions read from a JSON Lines file (see the module docstring)."""

    needs_frames = False

    def __init__(self, name: str, path: str | Path) -> None:
        self.name, self.path = name, Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "predictions file not found")
        try:
            lines = self.path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as error:
            raise InputError(self.path, f"cannot read predictions ({error.__class__.__name__})") from error
        self.entries: dict[Key, tuple[int, dict]] = {}
        self.duplicates: dict[Key, list[int]] = {}
        self.problems: list[tuple[int, str]] = []  # (line number, reason) of lines not attributable to a sample
        self._loaded: dict[Path, object] = {}  # reconstruction file -> mesh or points
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                entry = parse_json(line)
            except ValueError as error:
                self.problems.append((number, f"not JSON ({error})"))
                continue
            if not isinstance(entry, dict) or not isinstance(entry.get("sequence"), (str, int)) or not isinstance(entry.get("frame"), (str, int)):
                self.problems.append((number, "not an object with 'sequence' and 'frame'"))
                continue
            key = _key(entry["sequence"], entry["frame"], entry.get("instance"))
            if key in self.entries:
                self.duplicates.setdefault(key, [self.entries[key][0]]).append(number)
            else:
                self.entries[key] = (number, entry)

    def unmatched(self, samples: list[Sample]) -> list[Key]:
        """Keys of lines that name no sample of the dataset."""
        known = {_key(*s.key) for s in samples}
        return sorted((k for k in self.entries if k not in known), key=str)

    def predict(self, sample: Sample, inputs: FrameInputs | None = None) -> Prediction:
        key = _key(*sample.key)
        if key in self.duplicates:
            raise PredictionFailure(f"several predictions (lines {self.duplicates[key]} of {self.path.name})")
        if key not in self.entries:
            raise PredictionFailure("no prediction")
        number, entry = self.entries[key]
        at = f"line {number} of {self.path.name}"
        values = {}
        for field, n in (("position", 3), ("orientation", 4), ("extents", 3)):
            value = entry.get(field)
            if not isinstance(value, list) or len(value) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                raise PredictionFailure(f"{at}: {field} must be a list of {n} numbers")
            if not all(math.isfinite(v) for v in value):
                raise PredictionFailure(f"{at}: {field} is not finite")
            values[field] = np.asarray(value, dtype=np.float64)
        score = entry.get("score", 1.0)
        if isinstance(score, bool) or not isinstance(score, (int, float)) or not math.isfinite(score):
            raise PredictionFailure(f"{at}: score must be a finite number")
        category = entry.get("category")
        if category is not None and (not isinstance(category, str) or not category.strip()):
            raise PredictionFailure(f"{at}: category must be a non-empty string")
        reconstruction = None
        if entry.get("reconstruction") is not None:
            reconstruction = self._reconstruction(at, entry["reconstruction"])
        try:
            return check_prediction(Prediction(values["position"], values["orientation"], values["extents"], reconstruction, float(score), category))
        except PredictionFailure as failure:
            raise PredictionFailure(f"{at}: {failure}") from None

    def _reconstruction(self, at: str, value: Any):
        if not isinstance(value, str) or not value:
            raise PredictionFailure(f"{at}: reconstruction must be a file name")
        path = Path(value)
        if not path.is_absolute():
            path = self.path.parent / path
        if not path.is_file():
            raise PredictionFailure(f"{at}: reconstruction file {value} not found")
        try:
            # several samples (frames of one sequence) often share one reconstruction file: read it once
            if path not in self._loaded:
                self._loaded[path] = load_reconstruction(path)
            return self._loaded[path]
        except (ValueError, OSError) as error:
            raise PredictionFailure(f"{at}: unreadable reconstruction {value} ({error.__class__.__name__}: {' '.join(str(error).split())})"[:300]) from error


def load_reconstruction(path: Path):
    """A mesh (trimesh.Trimesh) or (N, 3) points from a file: .npy / .xyz / .txt / .pts points,
    anything else through trimesh (a point-only .ply gives points)."""
    suffix = path.suffix.lower()
    if suffix == ".npy":
        points = np.load(path, allow_pickle=False)
    elif suffix in POINT_SUFFIXES:
        points = np.loadtxt(path, ndmin=2)
    else:
        import trimesh

        try:
            loaded = trimesh.load(str(path), process=False)
        except Exception as error:  # trimesh raises many types on corrupt files
            raise ValueError(f"{error.__class__.__name__}: {error}") from error
        if isinstance(loaded, trimesh.Scene):
            loaded = loaded.dump(concatenate=True) if loaded.geometry else None
        if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces):
            return loaded
        if loaded is not None and hasattr(loaded, "vertices") and len(loaded.vertices):
            points = np.asarray(loaded.vertices)
        else:
            raise ValueError("no geometry in the file")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points have shape {points.shape}, expected (N, 3)")
    return points
