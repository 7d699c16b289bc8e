"""Running an evaluation: predictions of every method for every sample, their errors, precision,
and NOCS-style mAP.

Counting rules: every sample counts for every threshold tuple; a failed sample (no prediction, or
a malformed one) is incorrect at every threshold. A tuple with an F-score threshold counts only
the samples that have a true mesh (the others cannot be scored and are reported); a prediction
without a reconstruction fails such a tuple.

NOCS-style mAP (:mod:`evaluate.metrics.nocs_map`): every sample is one ground-truth box of its image
(sequence and frame); each method's prediction for a sample is one detection in that image, of the
category it names (the sample's by default) and with its score (1.0 by default); a failed sample has
no detection, so its box is missed.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evaluate.config import EvaluateConfig
from evaluate.datasets import Dataset, Sample, open_dataset
from evaluate.methods import FrameInputs, PredictionFailure, SampleMethod, get_method
from evaluate.methods.predictions import PredictionsFile
from evaluate.report import MethodResult, ThresholdPrecision
from sequences.errors import InputError



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


def reconstruction_points(reconstruction, n: int, seed: int) -> np.ndarray | None:
    """A reconstruction as points (object frame, m): a mesh is sampled (``n`` points, seeded), points are kept."""
    from evaluate.metrics import sample_surface

    if reconstruction is None:
        return None
    if getattr(reconstruction, "faces", None) is not None:
        try:
            return sample_surface(reconstruction, n, seed)
        except ValueError as error:
            raise PredictionFailure(f"reconstruction mesh cannot be sampled ({error})") from error
    return np.asarray(reconstruction, dtype=np.float64)


class ShapeIndexCache:
    """The true mesh of each object sampled and KD-tree-indexed once, for every sample and method."""

    def __init__(self, dataset: Dataset, n: int, seed: int) -> None:
        self.dataset, self.n, self.seed = dataset, n, seed
        self._index: dict[Path, object] = {}

    def get(self, sample: Sample):
        from evaluate.metrics import ShapeIndex

        if sample.mesh_path is None:
            return None
        if sample.mesh_path not in self._index:
            self._index[sample.mesh_path] = ShapeIndex.from_mesh(self.dataset.mesh(sample), self.n, self.seed)
        return self._index[sample.mesh_path]


def score_method(dataset: Dataset, predictions: list, shapes: list, fscore_threshold: float):
    """SampleErrors (evaluate.metrics) of one method: ``predictions`` holds per sample a
    (position, orientation, extents, points, score, category) tuple or None for a failed sample."""
    from evaluate.metrics import compute_sample_errors

    samples = dataset.samples
    pick = lambda k: [None if p is None else p[k] for p in predictions]  # noqa: E731
    return compute_sample_errors(
        np.array([s.position for s in samples]),
        np.array([s.orientation for s in samples]),
        np.array([s.extents for s in samples]),
        [s.symmetry for s in samples],
        shapes,
        pick(0), pick(1), pick(2), pick(3),
        fscore_threshold=fscore_threshold,
        compute_chamfer=True,
    )


def nocs_ground_truth(dataset: Dataset) -> dict:
    """The dataset as NOCS ground truth: image labels (sequence/frame), categories, poses (N, 4, 4),
    extents (N, 3) m and NOCS's symmetric flags (the symmetry label, and mugs whose handle is not visible)."""
    from evaluate.metrics.nocs_map import nocs_symmetric

    samples = dataset.samples
    categories = np.array([s.category for s in samples], dtype=object)
    return {
        "image": np.array([f"{s.sequence}/{s.frame}" for s in samples], dtype=object),
        "category": categories,
        "pose": np.array([s.pose for s in samples]).reshape(-1, 4, 4),
        "extents": np.array([s.extents for s in samples]).reshape(-1, 3),
        "symmetric": nocs_symmetric(categories, [s.symmetry for s in samples], [s.handle_visible for s in samples]),
        "label_symmetric": np.array([s.symmetry == "y" for s in samples], dtype=bool),
    }


def nocs_map_of_method(truth: dict, predictions: list, errors):
    """NOCS-style mAP of one method: one detection per sample with a prediction (see the module docstring).

    The pair of a detection and its own sample reuses the IoU and pose errors already in ``errors`` when
    the two agree on the symmetry (always, unless a mug's handle is hidden): the symmetric IoU is the
    costly part, and it is the same computation.
    """
    from evaluate.geometry import quat_to_matrix
    from evaluate.metrics.nocs_map import Pairs, candidate_pairs, nocs_map_from_pairs, pair_errors

    owner = np.array([i for i, p in enumerate(predictions) if p is not None and not errors.failed[i]], dtype=np.int64)
    position = np.array([predictions[i][0] for i in owner]).reshape(-1, 3)
    orientation = np.array([predictions[i][1] for i in owner]).reshape(-1, 4)
    pose = np.tile(np.eye(4), (len(owner), 1, 1))
    if len(owner):
        pose[:, :3, :3], pose[:, :3, 3] = quat_to_matrix(orientation / np.linalg.norm(orientation, axis=1, keepdims=True)), position
    extents = np.array([predictions[i][2] for i in owner]).reshape(-1, 3)
    score = np.array([predictions[i][4] for i in owner], dtype=np.float64)
    category = np.array([predictions[i][5] or truth["category"][i] for i in owner], dtype=object)
    image = truth["image"][owner]
    pairs = candidate_pairs(truth["image"], truth["category"], image, category)
    own = owner[pairs.det] == pairs.gt
    known = own & (truth["symmetric"][pairs.gt] == truth["label_symmetric"][pairs.gt])
    known &= np.isfinite(errors.iou[pairs.gt]) & np.isfinite(errors.rotation_error[pairs.gt])
    iou, degrees, metres = np.zeros(len(pairs.det)), np.zeros(len(pairs.det)), np.zeros(len(pairs.det))
    iou[known], degrees[known], metres[known] = (v[pairs.gt[known]] for v in (errors.iou, errors.rotation_error, errors.position_error))
    rest = ~known
    if rest.any():
        computed = pair_errors(Pairs(pairs.det[rest], pairs.gt[rest]), truth["pose"], truth["extents"], truth["symmetric"], pose, extents)
        iou[rest], degrees[rest], metres[rest] = computed.iou, computed.degrees, computed.position
    pairs = Pairs(pairs.det, pairs.gt, iou, degrees, metres)
    return nocs_map_from_pairs(pairs, truth["image"], truth["category"], image, category, score)


def precision_rows(errors, thresholds: list[dict], categories: np.ndarray, has_mesh: np.ndarray, names: list[str]) -> list[ThresholdPrecision]:
    """Precision per threshold tuple, overall and per category; F-score tuples over the samples with a true mesh."""
    from evaluate.metrics import Threshold, precision_table

    rows = []
    for t in thresholds:
        counted = has_mesh if t["fscore"] is not None else np.ones(len(categories), dtype=bool)
        if counted.any():
            row = precision_table(errors.subset(counted), [Threshold(**t)], categories[counted])[0]
            overall, per_category = row["overall"], row["per_category"]
        else:
            overall, per_category = None, {}
        rows.append(ThresholdPrecision(t["position"], t["degrees"], t["iou"], t["fscore"], overall, {c: per_category.get(c) for c in names}, int(counted.sum())))
    return rows


def curves(errors, grids: dict[str, list[float]], has_mesh: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Overall precision against each single threshold (Fig. 5); the F-score curve over the samples with a true mesh."""
    from evaluate.metrics import precision_curves

    out = {}
    pose = precision_curves(errors, None, position=grids["position"], degrees=grids["degrees"], iou=grids["iou"], fscore=None)
    for kind, curve in pose.items():
        out[kind] = (np.asarray(curve["thresholds"]), np.asarray(curve["overall"]))
    if has_mesh.any():
        shape = precision_curves(errors.subset(has_mesh), None, position=None, degrees=None, iou=None, fscore=grids["fscore"])["fscore"]
        out["fscore"] = (np.asarray(shape["thresholds"]), np.asarray(shape["overall"]))
    return {k: out[k] for k in ("position", "degrees", "iou", "fscore") if k in out}


def predict_sample(method: SampleMethod, sample: Sample, inputs: FrameInputs, config: EvaluateConfig) -> tuple[tuple | None, str | None]:
    """One method's prediction for one sample: ((position, orientation, extents, points, score, category), None),
    or (None, the reason it failed)."""
    try:
        p = method.predict(sample, inputs)
        points = reconstruction_points(p.reconstruction, config.surface_samples, config.seed) if sample.mesh_path is not None else None
        return (p.position, p.orientation, p.extents, points, p.score, p.category), None
    except PredictionFailure as failure:
        return None, " ".join(str(failure).split())
    except (Exception, SystemExit) as error:  # a method's own bug or exit is that sample's failure, not the run's end
        return None, " ".join(f"method raised {error.__class__.__name__}: {error}".split())[:300]


def evaluate_dataset(config: EvaluateConfig, progress: bool = True, predict=None) -> Evaluation:
    """Run and score every method on every sample of the configured dataset.

    ``predict(dataset, methods, predicted, reasons)``, when given, fills ``predicted[name][i]`` and
    ``reasons[name][i]`` (as :func:`predict_sample` gives them) in place of the loop here (:mod:`evaluate.units`
    runs them as a batch)."""
    from tqdm import tqdm

    dataset = open_dataset(config.dataset, config.frames)
    if len(dataset) == 0:
        raise InputError(config.dataset, "dataset has no samples")
    methods = resolve_methods(config, dataset)
    check_frames(dataset, methods, config.frames)
    index = ShapeIndexCache(dataset, config.surface_samples, config.seed)
    n = len(dataset)
    predicted: dict[str, list] = {m.name: [None] * n for m in methods}
    reasons: dict[str, list[str | None]] = {m.name: [None] * n for m in methods}
    if predict is not None:  # the caller runs the methods (evaluate.units: a batch)
        predict(dataset, methods, predicted, reasons)
    else:
        bar = tqdm(total=n * len(methods), desc="evaluate", unit="prediction", disable=not progress)
        for i, sample in enumerate(dataset):
            inputs = FrameInputs(dataset, sample)
            for method in methods:
                bar.set_postfix_str(f"{method.name} {sample.label}", refresh=False)
                predicted[method.name][i], reasons[method.name][i] = predict_sample(method, sample, inputs, config)
                bar.update(1)
        bar.close()
    shapes = [index.get(s) for s in dataset]
    categories = np.array([s.category for s in dataset])
    has_mesh = np.array([s.mesh_path is not None for s in dataset])
    names = dataset.categories
    notes = []
    if not has_mesh.all():
        missing = sorted({s.sequence if s.instance is None else s.label for s in dataset if s.mesh_path is None})
        notes.append(f"{int((~has_mesh).sum())} of {n} samples have no true mesh ({', '.join(missing)}): F-score thresholds count only the other {int(has_mesh.sum())}; their pose and IoU are evaluated.")
    truth = nocs_ground_truth(dataset)
    results = []
    for method in tqdm(methods, desc="score", unit="method", disable=not progress or len(methods) < 2, file=sys.stderr):
        errors = score_method(dataset, predicted[method.name], shapes, config.fscore_threshold)
        nocs = nocs_map_of_method(truth, predicted[method.name], errors)
        if nocs.ignored:
            notes.append(f"{method.name}: {nocs.ignored} detections name a category the dataset lacks; NOCS-style mAP ignores them.")
        failed = []
        for i, sample in enumerate(dataset):
            if reasons[method.name][i] is None and errors.failed[i]:
                reasons[method.name][i] = errors.failure[i]
            if reasons[method.name][i] is not None:
                entry = {"sequence": sample.sequence, "frame": sample.frame}
                if sample.instance is not None:
                    entry["instance"] = sample.instance
                entry["reason"] = reasons[method.name][i]
                failed.append(entry)
        if isinstance(method, PredictionsFile):
            notes.extend(f"{method.name}: {method.path.name} line {number} ignored: {reason}" for number, reason in method.problems)
            unmatched = method.unmatched(dataset.samples)
            if unmatched:
                notes.append(f"{method.name}: {len(unmatched)} predictions name no sample of the dataset and were ignored (first: {'/'.join(p for p in unmatched[0] if p)}).")
        values = {"translation": errors.position_error, "rotation": errors.rotation_error, "iou": errors.iou, "chamfer": errors.chamfer, "fscore": errors.fscore}
        rows = []
        for i, sample in enumerate(dataset):
            row = {"method": method.name, "sequence": sample.sequence, "frame": sample.frame, "instance": sample.instance, "category": sample.category, "symmetry": sample.symmetry, "has_mesh": int(has_mesh[i]), "failure": reasons[method.name][i]}
            row.update({k: float(v[i]) for k, v in values.items()})
            rows.append(row)
        results.append(
            MethodResult(
                name=method.name,
                samples=n,
                failed=failed,
                precision=precision_rows(errors, config.thresholds, categories, has_mesh, names),
                curves=curves(errors, config.curves, has_mesh),
                rows=rows,
                nocs=nocs,
            )
        )
    return Evaluation(dataset, results, notes)
