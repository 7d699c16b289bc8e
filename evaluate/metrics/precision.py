"""Precision over threshold tuples (the paper's Table 2) and precision-versus-threshold curves (its Fig. 5).

Errors are computed once per sample (:class:`SampleErrors`); every threshold, tuple and curve point is
then a vectorised comparison, never a recomputation.  A sample counts as correct for a threshold tuple
when every threshold that is set holds (the comparisons of cpas_toolbox's ``correct_thresh``):

    position_error <= position,  rotation_error <= degrees,  iou >= iou,  fscore >= fscore.

A failed sample (missing or malformed prediction) is never correct, and neither is a NaN error under a
threshold that uses it (e.g. an F-score threshold for a method without a reconstruction).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Sequence

import numpy as np

#: F-score distance threshold (m) of the paper's F-score thresholds (cpas_toolbox hard-codes 0.01).
DEFAULT_FSCORE_DISTANCE = 0.01


def threshold_label(position: float | None, degrees: float | None, iou: float | None, fscore: float | None,
                    separator: str = " ", at_least: str = "≥") -> str:
    """A threshold tuple's name from its used parts (position in m, shown in cm), e.g. '10° 2 cm F≥0.6'."""
    parts = []
    if degrees is not None:
        parts.append(f"{degrees:g}°")
    if position is not None:
        parts.append(f"{position * 100:g} cm")
    if iou is not None:
        parts.append(f"IoU{at_least}{iou:g}")
    if fscore is not None:
        parts.append(f"F{at_least}{fscore:g}")
    return separator.join(parts)


@dataclass(frozen=True)
class Threshold:
    """One threshold tuple; ``None`` means the criterion is not used."""

    position: float | None = None  # metres: correct if position error <= position
    degrees: float | None = None  # degrees: correct if rotation error <= degrees
    iou: float | None = None  # correct if box IoU >= iou
    fscore: float | None = None  # correct if F-score (at the configured distance) >= fscore

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None and not (isinstance(value, (int, float, np.floating, np.integer)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"Threshold.{f.name} must be a non-negative number or None, got {value!r}")

    def label(self) -> str:
        """Short human-readable name, e.g. '10° 2 cm F≥0.6'."""
        return threshold_label(self.position, self.degrees, self.iou, self.fscore) or "any"

    def as_dict(self) -> dict:
        return {"position": self.position, "degrees": self.degrees, "iou": self.iou, "fscore": self.fscore}


#: The paper's Table 2: (10°, 2 cm), (5°, 1 cm), (10°, 2 cm, F ≥ 0.6), (5°, 1 cm, F ≥ 0.8), F at 1 cm.
DEFAULT_THRESHOLDS: tuple[Threshold, ...] = (
    Threshold(position=0.02, degrees=10),
    Threshold(position=0.01, degrees=5),
    Threshold(position=0.02, degrees=10, fscore=0.6),
    Threshold(position=0.01, degrees=5, fscore=0.8),
)

#: Fig. 5 curve thresholds, from cpas_toolbox 1.0.0 config/redwood75.yaml (identical in real275.yaml):
#: correct_position, correct_degree and correct_fscore.  cpas lists F-score 0.4 twice; we drop the copy.
POSITION_CURVE = np.round(np.arange(0, 11) * 0.005, 6)  # 0 .. 5 cm
DEGREE_CURVE = np.arange(0, 21, dtype=np.float64)  # 0 .. 20 degrees
FSCORE_CURVE = np.round(np.arange(0, 21) * 0.05, 6)  # 0 .. 1
#: Not in cpas_toolbox's configs (it has no IoU curve): ours, 0 .. 1 in steps of 0.05.
IOU_CURVE = np.round(np.arange(0, 21) * 0.05, 6)


def _array(values, n: int, name: str) -> np.ndarray:
    a = np.full(n, np.nan) if values is None else np.asarray(values, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"SampleErrors.{name}: expected {n} values, got {a.shape}")
    return a


@dataclass
class SampleErrors:
    """Per-sample errors (N,), NaN where not available; ``failed`` marks missing/malformed predictions."""

    position_error: np.ndarray  # m
    rotation_error: np.ndarray  # degrees (about the symmetry axis for symmetric objects)
    iou: np.ndarray  # oriented-box IoU (symmetric IoU for symmetric objects)
    fscore: np.ndarray  # F-score at the configured distance (posed shapes, as cpas_toolbox)
    failed: np.ndarray | None = None  # bool
    chamfer: np.ndarray | None = None  # m, optional
    failure: list = field(default_factory=list)  # reason per sample (None when not failed)

    def __post_init__(self) -> None:
        n = np.asarray(self.position_error).reshape(-1).shape[0]
        self.position_error = _array(self.position_error, n, "position_error")
        self.rotation_error = _array(self.rotation_error, n, "rotation_error")
        self.iou = _array(self.iou, n, "iou")
        self.fscore = _array(self.fscore, n, "fscore")
        self.chamfer = _array(self.chamfer, n, "chamfer")
        self.failed = np.zeros(n, bool) if self.failed is None else np.asarray(self.failed, dtype=bool).reshape(-1)
        if self.failed.shape != (n,):
            raise ValueError("SampleErrors.failed: wrong length")
        self.failure = list(self.failure) if self.failure else [None] * n
        if len(self.failure) != n:
            raise ValueError("SampleErrors.failure: wrong length")

    def __len__(self) -> int:
        return len(self.position_error)

    def subset(self, mask) -> "SampleErrors":
        """The samples selected by a boolean mask or index array."""
        idx = np.arange(len(self))[mask]
        return SampleErrors(self.position_error[idx], self.rotation_error[idx], self.iou[idx], self.fscore[idx],
                            self.failed[idx], self.chamfer[idx], [self.failure[i] for i in idx])

    @staticmethod
    def concatenate(parts: Sequence["SampleErrors"]) -> "SampleErrors":
        """All samples of ``parts``, in order."""
        if not parts:
            return SampleErrors(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        return SampleErrors(cat("position_error"), cat("rotation_error"), cat("iou"), cat("fscore"), cat("failed"),
                            cat("chamfer"), [r for p in parts for r in p.failure])


def _threshold_arrays(thresholds: Sequence[Threshold]) -> tuple[np.ndarray, ...]:
    nan = lambda v: np.nan if v is None else float(v)  # noqa: E731
    return tuple(np.array([nan(getattr(t, k)) for t in thresholds], dtype=np.float64) for k in ("position", "degrees", "iou", "fscore"))


def correct(errors: SampleErrors, thresholds: Sequence[Threshold]) -> np.ndarray:
    """(T, N) bool: whether each sample is correct under each threshold tuple."""
    if isinstance(thresholds, Threshold):
        thresholds = [thresholds]
    p, d, i, f = (x[:, None] for x in _threshold_arrays(thresholds))
    ok = ~errors.failed[None, :]
    ok = ok & (np.isnan(p) | (errors.position_error[None, :] <= p))
    ok = ok & (np.isnan(d) | (errors.rotation_error[None, :] <= d))
    ok = ok & (np.isnan(i) | (errors.iou[None, :] >= i))
    ok = ok & (np.isnan(f) | (errors.fscore[None, :] >= f))
    return ok


def precision(errors: SampleErrors, threshold: Threshold) -> float:
    """Fraction of samples correct under ``threshold`` (NaN for zero samples)."""
    if len(errors) == 0:
        return float("nan")
    return float(correct(errors, [threshold])[0].mean())


def _categories(categories, n: int) -> np.ndarray | None:
    if categories is None:
        return None
    c = np.asarray(categories, dtype=object).reshape(-1)
    if c.shape != (n,):
        raise ValueError(f"categories: expected one category per sample ({n}), got {c.shape[0]}")
    return c


def _per_category(ok: np.ndarray, categories: np.ndarray | None) -> dict[str, list[float]]:
    """{category: precision per row of ok (T, N)}, categories sorted by name."""
    if categories is None:
        return {}
    return {str(c): ok[:, categories == c].mean(axis=1).tolist() for c in sorted(set(categories.tolist()))}


def precision_table(errors: SampleErrors, thresholds: Sequence[Threshold] = DEFAULT_THRESHOLDS, categories=None) -> list[dict]:
    """One row per threshold tuple, in DESIGN.md's results.json shape:

    ``{"position", "degrees", "iou", "fscore", "overall", "per_category": {category: precision}}``
    (``overall`` over all samples, as cpas_toolbox; NaN for zero samples).
    """
    n = len(errors)
    cats = _categories(categories, n)
    ok = correct(errors, thresholds)
    overall = ok.mean(axis=1) if n else np.full(len(thresholds), np.nan)
    per_cat = _per_category(ok, cats)
    return [
        {**t.as_dict(), "overall": float(overall[k]), "per_category": {c: v[k] for c, v in per_cat.items()}}
        for k, t in enumerate(thresholds)
    ]


def precision_curves(errors: SampleErrors, categories=None, position=POSITION_CURVE, degrees=DEGREE_CURVE,
                     fscore=FSCORE_CURVE, iou=IOU_CURVE) -> dict[str, dict]:
    """Precision versus each threshold alone (Fig. 5): ``{"position"|"degrees"|"fscore"|"iou":
    {"thresholds": [...], "overall": [...], "per_category": {category: [...]}}}``; a curve whose
    threshold list is None is left out.  Position thresholds in metres.
    """
    n = len(errors)
    cats = _categories(categories, n)
    out = {}
    for name, values in (("position", position), ("degrees", degrees), ("fscore", fscore), ("iou", iou)):
        if values is None:
            continue
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        ok = correct(errors, [Threshold(**{name: float(v)}) for v in values])
        out[name] = {
            "thresholds": values.tolist(),
            "overall": (ok.mean(axis=1) if n else np.full(len(values), np.nan)).tolist(),
            "per_category": _per_category(ok, cats),
        }
    return out
