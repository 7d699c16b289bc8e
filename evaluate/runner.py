"""Running an evaluation: predictions of every method for every sample, their errors, precision.

Counting rules: every sample counts for every threshold tuple; a failed sample (no prediction, or
a malformed one) is incorrect at every threshold. A tuple with an F-score threshold counts only
the samples that have a true mesh (the others cannot be scored and are reported); a prediction
without a reconstruction fails such a tuple.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evaluate.config import EvaluateConfig
from evaluate.datasets import Dataset, Sample, open_dataset
from evaluate.methods import FrameInputs, Prediction, PredictionFailure, SampleMethod, get_method
from evaluate.methods.predictions import PredictionsFile
from evaluate.report import MethodResult, ThresholdPrecision
from sequences.errors import InputError

#: per-sample error arrays, NaN = not available
ERROR_KINDS = ("translation", "rotation", "iou", "chamfer", "fscore", "fscore_precision", "fscore_recall")


@dataclass
class Evaluation:
    dataset: Dataset
    results: list[MethodResult]
    notes: list[str]


def resolve_methods(config: EvaluateConfig, dataset: Dataset) -> list[SampleMethod]:
    camera = dataset.samples[0].camera
    methods = [get_method(entry.spec, entry.config, camera, dataset, entry.base) for entry in config.methods]
    names = [m.name for m in methods]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise InputError(None, f"two methods are named {duplicates[0]!r}: name them NAME=SPEC")
    return methods


def check_frames(dataset: Dataset, methods: list[SampleMethod], frames: Path | None) -> None:
    """Methods run here need every sample's frames: fail early, in one line, when any is missing."""
    runners = [m.name for m in methods if m.needs_frames]
    if not runners:
        return
    if frames is None and dataset.samples[0].color_path is None:
        raise InputError(dataset.root, f"method {runners[0]} runs here and needs the RGB-D frames: give --frames ROOT (ROOT/<sequence>/rgb|depth or ROOT/<category>/rgbd/<sequence>/rgb|depth)")
    for sample in dataset:
        if sample.color_path is None or sample.depth_path is None:
            raise InputError(frames, f"no frames of sequence {sample.sequence} (looked for {sample.sequence}/rgb and {sample.category}/rgbd/{sample.sequence}/rgb); method {runners[0]} needs them")
        for path in (sample.color_path, sample.depth_path):
            if not path.is_file():
                raise InputError(path, f"frame of sample {sample.label} not found; method {runners[0]} needs it")


def _reconstruction_points(reconstruction, n: int, seed: int) -> np.ndarray:
    from evaluate.metrics.sampling import sample_surface

    if getattr(reconstruction, "faces", None) is not None:
        return sample_surface(reconstruction, n, seed)
    return np.asarray(reconstruction, dtype=np.float64)


class ShapeScorer:
    """Chamfer distance and F-score of posed reconstructions against the posed true mesh; the true
    mesh is sampled and indexed once per mesh file, whatever the number of samples and methods."""

    def __init__(self, dataset: Dataset, n: int, seed: int, fscore_threshold: float) -> None:
        self.dataset, self.n, self.seed, self.threshold = dataset, n, seed, fscore_threshold
        self._index: dict[Path, object] = {}

    def index(self, sample: Sample):
        from evaluate.metrics.sampling import ShapeIndex

        if sample.mesh_path not in self._index:
            self._index[sample.mesh_path] = ShapeIndex.from_mesh(self.dataset.mesh(sample), self.n, self.seed)
        return self._index[sample.mesh_path]

    def score(self, sample: Sample, prediction: Prediction) -> dict[str, float]:
        from evaluate.metrics.shape_metrics import chamfer_from_distances, fscore_from_distances

        index = self.index(sample)
        try:
            points = _reconstruction_points(prediction.reconstruction, self.n, self.seed)
        except ValueError as error:
            raise PredictionFailure(f"reconstruction cannot be sampled ({error})") from error
        # the posed reconstruction in the true object frame: the same distances as between the posed
        # clouds in the camera frame (cpas_toolbox scores posed points), with the true side indexed once
        R_gt, R_pred = _matrix(sample.orientation), _matrix(prediction.orientation)
        posed = (points @ R_pred.T + prediction.position - sample.position) @ R_gt
        d_gt_to_pred, d_pred_to_gt = index.distances(posed)
        score = fscore_from_distances(d_gt_to_pred, d_pred_to_gt, self.threshold)
        return {
            "chamfer": chamfer_from_distances(d_gt_to_pred, d_pred_to_gt),
            "fscore": float(score.fscore),
            "fscore_precision": float(score.precision),
            "fscore_recall": float(score.recall),
        }


def _matrix(q) -> np.ndarray:
    from evaluate.geometry import quat_to_matrix

    return quat_to_matrix(q)


def pose_errors(sample: Sample, prediction: Prediction) -> dict[str, float]:
    from evaluate.geometry import pose_matrix
    from evaluate.metrics.box_iou import box_iou, symmetric_box_iou
    from evaluate.metrics.pose_errors import rotation_error, translation_error

    T_gt, T_pred = pose_matrix(sample.position, sample.orientation), pose_matrix(prediction.position, prediction.orientation)
    iou = box_iou if sample.symmetry == "none" else symmetric_box_iou
    return {
        "translation": float(translation_error(sample.position, prediction.position)),
        "rotation": float(rotation_error(T_gt[:3, :3], T_pred[:3, :3], symmetry=sample.symmetry)),
        "iou": float(iou(sample.extents, T_gt, prediction.extents, T_pred)),
    }


def _correct(errors: dict[str, np.ndarray], threshold: dict, fscore_ok: np.ndarray) -> np.ndarray:
    """Boolean (N,): samples meeting every used threshold (NaN errors never do)."""
    ok = np.ones(len(fscore_ok), dtype=bool)
    with np.errstate(invalid="ignore"):
        if threshold["position"] is not None:
            ok &= errors["translation"] <= threshold["position"]
        if threshold["degrees"] is not None:
            ok &= errors["rotation"] <= threshold["degrees"]
        if threshold["iou"] is not None:
            ok &= errors["iou"] >= threshold["iou"]
        if threshold["fscore"] is not None:
            ok &= errors["fscore"] >= threshold["fscore"]
    return ok


def precision_at(errors: dict[str, np.ndarray], threshold: dict, categories: np.ndarray, has_mesh: np.ndarray, category_names: list[str]) -> ThresholdPrecision:
    counted = has_mesh if threshold["fscore"] is not None else np.ones(len(categories), dtype=bool)
    correct = _correct(errors, threshold, has_mesh)

    def share(selection: np.ndarray) -> float | None:
        n = int(selection.sum())
        return None if n == 0 else float(correct[selection].sum()) / n

    return ThresholdPrecision(
        threshold["position"], threshold["degrees"], threshold["iou"], threshold["fscore"],
        share(counted), {c: share(counted & (categories == c)) for c in category_names}, int(counted.sum()),
    )


def curves(errors: dict[str, np.ndarray], grids: dict[str, list[float]], has_mesh: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Overall precision against each single threshold (Fig. 5)."""
    out = {}
    n = len(has_mesh)
    for kind, grid in grids.items():
        grid = np.asarray(grid, dtype=np.float64)
        counted = has_mesh if kind == "fscore" else np.ones(n, dtype=bool)
        if not counted.any():
            continue
        values = []
        for g in grid:
            threshold = {"position": None, "degrees": None, "iou": None, "fscore": None, kind: g}
            values.append(_correct(errors, threshold, has_mesh)[counted].mean())
        out[kind] = (grid, np.asarray(values))
    return out


def evaluate_dataset(config: EvaluateConfig, progress: bool = True) -> Evaluation:
    """Run and score every method on every sample of the configured dataset."""
    from tqdm import tqdm

    dataset = open_dataset(config.dataset, config.frames)
    if len(dataset) == 0:
        raise InputError(config.dataset, "dataset has no samples")
    methods = resolve_methods(config, dataset)
    check_frames(dataset, methods, config.frames)
    shapes = ShapeScorer(dataset, config.surface_samples, config.seed, config.fscore_threshold)
    n = len(dataset)
    errors = {m.name: {k: np.full(n, np.nan) for k in ERROR_KINDS} for m in methods}
    failures: dict[str, list[dict]] = {m.name: [] for m in methods}
    reasons: dict[str, list[str | None]] = {m.name: [None] * n for m in methods}
    bar = tqdm(total=n * len(methods), desc="evaluate", unit="prediction", disable=not progress)
    for i, sample in enumerate(dataset):
        inputs = FrameInputs(dataset, sample)
        for method in methods:
            bar.set_postfix_str(f"{method.name} {sample.label}", refresh=False)
            try:
                prediction = method.predict(sample, inputs)
                values = pose_errors(sample, prediction)
                if sample.mesh_path is not None and prediction.reconstruction is not None:
                    values.update(shapes.score(sample, prediction))
            except PredictionFailure as failure:
                reason = " ".join(str(failure).split())
                entry = {"sequence": sample.sequence, "frame": sample.frame}
                if sample.instance is not None:
                    entry["instance"] = sample.instance
                entry["reason"] = reason
                failures[method.name].append(entry)
                reasons[method.name][i] = reason
            else:
                for key, value in values.items():
                    errors[method.name][key][i] = value
            bar.update(1)
    bar.close()
    categories = np.array([s.category for s in dataset])
    has_mesh = np.array([s.mesh_path is not None for s in dataset])
    names = dataset.categories
    notes = []
    if not has_mesh.all():
        missing = sorted({s.sequence for s in dataset if s.mesh_path is None})
        notes.append(f"{int((~has_mesh).sum())} of {n} samples have no true mesh (sequences {', '.join(missing)}): F-score thresholds count only the other {int(has_mesh.sum())}; their pose and IoU are evaluated.")
    results = []
    for method in methods:
        failed = failures[method.name]
        if isinstance(method, PredictionsFile):
            notes.extend(f"{method.name}: {method.path.name} line {number} ignored: {reason}" for number, reason in method.problems)
            unmatched = method.unmatched(dataset.samples)
            if unmatched:
                notes.append(f"{method.name}: {len(unmatched)} predictions name no sample of the dataset and were ignored (first: {'/'.join(p for p in unmatched[0] if p)}).")
        rows = []
        for i, sample in enumerate(dataset):
            row = {"method": method.name, "sequence": sample.sequence, "frame": sample.frame, "instance": sample.instance, "category": sample.category, "symmetry": sample.symmetry, "has_mesh": int(has_mesh[i]), "failure": reasons[method.name][i]}
            row.update({k: float(errors[method.name][k][i]) for k in ERROR_KINDS})
            rows.append(row)
        results.append(
            MethodResult(
                name=method.name,
                samples=n,
                failed=failed,
                precision=[precision_at(errors[method.name], t, categories, has_mesh, names) for t in config.thresholds],
                curves=curves(errors[method.name], config.curves, has_mesh),
                rows=rows,
            )
        )
    return Evaluation(dataset, results, notes)

