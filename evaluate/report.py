"""Writing an evaluation's outputs, each atomically: ``results.json`` (DESIGN.md's schema), the
precision tables as Markdown and CSV (overall and per category, as the paper's Tables 2 and 3),
precision-versus-threshold plots as PNG (the paper's Fig. 5: one panel per error kind, one line
per method) with their numbers in ``curves.json``, and the per-sample errors as CSV.

NOCS-style mAP (:mod:`evaluate.metrics.nocs_map`) goes alongside: ``results.json`` gains per method
``nocs_map`` (AP per category and mean at the IoU and pose thresholds), ``table.md`` a section of
its own, ``nocs_map.csv`` the long-format table, ``curves.json`` its AP curves under ``nocs_map``,
and ``nocs_map_curves.png`` the curves as NOCS plots them (AP against the IoU threshold, the rotation
threshold and the translation threshold; one line per category and the mean; one row per method).
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evaluate.metrics.nocs_map import NocsMapResult
from evaluate.metrics.precision import threshold_label
from sequences.atomic import temporary_sibling, write_text_atomic

#: Per-sample error columns: (name, unit or description).
ERROR_COLUMNS = (
    ("translation", "m"),
    ("rotation", "deg"),
    ("iou", ""),
    ("chamfer", "m"),
    ("fscore", ""),
)
CURVE_LABELS = {
    "position": ("position error threshold (cm)", 100.0),
    "degrees": ("rotation error threshold (deg)", 1.0),
    "iou": ("3D IoU threshold", 1.0),
    "fscore": ("F-score threshold", 1.0),
}


@dataclass
class ThresholdPrecision:
    """Precision of one method at one threshold tuple (None = threshold not used)."""

    position: float | None
    degrees: float | None
    iou: float | None
    fscore: float | None
    overall: float | None  # None when no sample qualifies (e.g. F-score without any true mesh)
    per_category: dict[str, float | None]
    samples: int  # samples counted (those with a true mesh when an F-score threshold is used)

    def to_json(self) -> dict:
        return {"position": self.position, "degrees": self.degrees, "iou": self.iou, "fscore": self.fscore, "overall": self.overall, "per_category": dict(self.per_category)}

    @property
    def label(self) -> str:
        """The tuple's name in tables, e.g. '10°, 2 cm, F ≥ 0.6'."""
        return threshold_label(self.position, self.degrees, self.iou, self.fscore, ", ", " ≥ ")


@dataclass
class MethodResult:
    name: str
    samples: int
    failed: list[dict]
    precision: list[ThresholdPrecision]
    curves: dict[str, tuple[np.ndarray, np.ndarray]]  # kind -> (thresholds, overall precision)
    rows: list[dict] = field(default_factory=list)  # per-sample errors
    nocs: NocsMapResult | None = None  # NOCS-style mAP


NOCS_CURVE_LABELS = {
    "iou": ("3D IoU threshold (%)", 100.0),
    "degrees": ("rotation error threshold (deg)", 1.0),
    "position": ("translation error threshold (cm)", 100.0),
}


def nocs_labels(nocs: NocsMapResult) -> list[str]:
    """Column names of the NOCS mAP table: 'IoU25', 'IoU50', ..., '5° 2 cm', ..."""
    return [f"IoU{100 * t:g}" for t in nocs.iou_thresholds] + [f"{d:g}° {100 * p:g} cm" for d, p in nocs.pose_thresholds]


def nocs_values(nocs: NocsMapResult) -> tuple[np.ndarray, np.ndarray]:
    """(mean (K + Q,), per category (C, K + Q)) AP in the column order of :func:`nocs_labels`."""
    per_category = np.concatenate([nocs.iou_ap, nocs.pose_ap], axis=1)
    return NocsMapResult.mean(per_category), per_category


def nocs_json(nocs: NocsMapResult) -> dict:
    """results.json's ``nocs_map``: AP (0..1, null where undefined) per threshold, mean and per category."""
    row = lambda ap, k: {"mean": _fraction(NocsMapResult.mean(ap)[k]), "per_category": {c: _fraction(ap[i, k]) for i, c in enumerate(nocs.categories)}}  # noqa: E731
    return {
        "pose_iou_gate": nocs.config.pose_iou_gate,
        "detections": nocs.detections,
        "ground_truth": nocs.ground_truth,
        "iou": [{"iou": float(t), **row(nocs.iou_ap, k)} for k, t in enumerate(nocs.iou_thresholds)],
        "pose": [{"degrees": float(d), "position": float(p), **row(nocs.pose_ap, k)} for k, (d, p) in enumerate(nocs.pose_thresholds)],
    }


def _fraction(value: float | None) -> float | None:
    return None if value is None or (isinstance(value, float) and math.isnan(value)) else float(value)


def results_json(dataset: str, results: list[MethodResult]) -> dict:
    """DESIGN.md's ``results.json``: {dataset, methods: {NAME: {samples, failed, precision: [...]}}}."""
    return {
        "dataset": dataset,
        "methods": {
            r.name: {"samples": r.samples, "failed": r.failed, "precision": [p.to_json() for p in r.precision], **({"nocs_map": nocs_json(r.nocs)} if r.nocs else {})}
            for r in results
        },
    }


def _percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f}"


def markdown_tables(dataset: str, results: list[MethodResult], categories: list[str], notes: list[str]) -> str:
    """Table 2 (overall precision per method and threshold) and Table 3 (per category), in percent."""
    if not results:
        return f"# {dataset}\n\nNo method evaluated.\n"
    labels = [p.label for p in results[0].precision]
    lines = [f"# Evaluation on {dataset}", "", "Precision (%) at each threshold tuple: the share of samples whose prediction meets every threshold of the tuple.", ""]
    lines += ["## Overall", "", "| Method | " + " | ".join(labels) + " | Failed |", "|---" * (len(labels) + 2) + "|"]
    for r in results:
        lines.append(f"| {r.name} | " + " | ".join(_percent(p.overall) for p in r.precision) + f" | {len(r.failed)} / {r.samples} |")
    lines += ["", "## Per category", "", "| Category | Method | " + " | ".join(labels) + " |", "|---" * (len(labels) + 2) + "|"]
    for category in categories:
        for r in results:
            lines.append(f"| {category} | {r.name} | " + " | ".join(_percent(p.per_category.get(category)) for p in r.precision) + " |")
    lines += nocs_markdown([r for r in results if r.nocs is not None], categories)
    counts = list(dict.fromkeys((p.label, p.samples) for r in results for p in r.precision))
    lines += ["", "## Notes", ""]
    lines += [f"- {label}: over {n} samples." for label, n in counts]
    lines += [f"- {note}" for note in notes]
    failed = [(r.name, f) for r in results for f in r.failed]
    if failed:
        lines += ["", "## Failed samples (counted as incorrect)", "", "| Method | Sample | Reason |", "|---|---|---|"]
        for name, f in failed:
            sample = "/".join(str(f[k]) for k in ("sequence", "frame", "instance") if f.get(k) is not None) or f"line {f.get('line')}"
            lines.append(f"| {name} | {sample} | {str(f['reason']).replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def nocs_markdown(results: list[MethodResult], categories: list[str]) -> list[str]:
    """The NOCS-style mAP section of table.md: mean AP per method, then AP per category, in percent."""
    if not results:
        return []
    labels = nocs_labels(results[0].nocs)
    gate = results[0].nocs.config.pose_iou_gate
    lines = ["", "## NOCS-style mAP (%)", "",
             "Average precision of detections ranked by score, matched to the ground truth by exact 3D IoU, "
             "as NOCS's evaluation (evaluate/metrics/nocs_map.py)"
             + (f"; pose AP over the pairs matched at IoU > {gate:g}." if gate is not None else "."), ""]
    lines += ["| Method | " + " | ".join(labels) + " | Detections |", "|---" * (len(labels) + 2) + "|"]
    for r in results:
        mean, _ = nocs_values(r.nocs)
        lines.append(f"| {r.name} | " + " | ".join(_percent(_fraction(v)) for v in mean) + f" | {r.nocs.detections} / {r.nocs.ground_truth} |")
    lines += ["", "| Category | Method | " + " | ".join(labels) + " |", "|---" * (len(labels) + 2) + "|"]
    for category in categories:
        for r in results:
            if category in r.nocs.categories:
                row = nocs_values(r.nocs)[1][r.nocs.categories.index(category)]
                lines.append(f"| {category} | {r.name} | " + " | ".join(_percent(_fraction(v)) for v in row) + " |")
    return lines


def nocs_csv(results: list[MethodResult]) -> str:
    """Long-format NOCS mAP table: method, category ('mean' = the mean over categories), label, iou,
    degrees, position (m), ap (0..1; empty where undefined)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["method", "category", "label", "iou", "degrees", "position", "ap"])
    for r in results:
        if r.nocs is None:
            continue
        thresholds = [(float(t), "", "") for t in r.nocs.iou_thresholds] + [("", float(d), float(p)) for d, p in r.nocs.pose_thresholds]
        mean, per_category = nocs_values(r.nocs)
        for k, label in enumerate(nocs_labels(r.nocs)):
            for category, value in [("mean", mean[k])] + [(c, per_category[i, k]) for i, c in enumerate(r.nocs.categories)]:
                v = _fraction(value)
                writer.writerow([r.name, category, label, *thresholds[k], "" if v is None else v])
    return buffer.getvalue()


def nocs_curves_json(results: list[MethodResult]) -> dict:
    """curves.json's ``nocs_map``: {method: {iou|degrees|position: {thresholds, mean, per_category}}} (AP 0..1, null where undefined)."""
    out = {}
    for r in results:
        if r.nocs is None:
            continue
        out[r.name] = {
            kind: {
                "thresholds": grid.tolist(),
                "mean": [_fraction(v) for v in NocsMapResult.mean(ap)],
                "per_category": {c: [_fraction(v) for v in ap[i]] for i, c in enumerate(r.nocs.categories)},
            }
            for kind, (grid, ap) in r.nocs.curves.items()
        }
    return out


def write_nocs_png(path: Path, dataset: str, results: list[MethodResult]) -> Path:
    """NOCS's AP plots: per method a row of three panels (AP vs 3D IoU, vs rotation, vs translation threshold),
    one line per category and a thick one for the mean."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    results = [r for r in results if r.nocs is not None]
    height = 3.2 * max(len(results), 1)  # inches
    figure, axes = plt.subplots(max(len(results), 1), 3, figsize=(12, height), squeeze=False)
    for row, r in zip(axes, results):
        for ax, (kind, (label, factor)) in zip(row, NOCS_CURVE_LABELS.items()):
            grid, ap = r.nocs.curves[kind]
            for i, category in enumerate(r.nocs.categories):
                ax.plot(grid * factor, ap[i], label=category, linewidth=1)
            ax.plot(grid * factor, NocsMapResult.mean(ap), label="mean", color="black", linewidth=2)
            ax.set_xlabel(label)
            ax.set_ylabel(f"AP ({r.name})")
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3)
        row[0].legend(loc="best", fontsize="small")
    figure.suptitle(f"{dataset}: NOCS-style AP")
    # fixed margins (inches turned into fractions): tight_layout would cost a third of the plot's time
    figure.subplots_adjust(left=0.06, right=0.99, bottom=0.55 / height, top=1 - 0.45 / height, hspace=0.35, wspace=0.22)
    return _save_png(figure, path, dpi=100)


def _save_png(figure, path: Path, dpi: int) -> Path:
    """Save ``figure`` as a PNG at ``path`` atomically (a temporary sibling renamed) and close it."""
    from matplotlib import pyplot as plt

    tmp = temporary_sibling(path)
    try:
        figure.savefig(tmp, format="png", dpi=dpi)
        tmp.replace(path)
    finally:
        plt.close(figure)
        if tmp.exists():
            tmp.unlink()
    return path


def csv_table(results: list[MethodResult], categories: list[str]) -> str:
    """Long-format precision table: method, category ('all' = overall), thresholds, precision, samples."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["method", "category", "label", "position", "degrees", "iou", "fscore", "precision"])
    for r in results:
        for p in r.precision:
            thresholds = ["" if v is None else v for v in (p.position, p.degrees, p.iou, p.fscore)]
            writer.writerow([r.name, "all", p.label, *thresholds, "" if p.overall is None else p.overall])
            for category in categories:
                value = p.per_category.get(category)
                writer.writerow([r.name, category, p.label, *thresholds, "" if value is None else value])
    return buffer.getvalue()


def errors_csv(results: list[MethodResult]) -> str:
    """Per-sample errors of every method (empty cell = not available: failed prediction, no mesh, no reconstruction)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    columns = ["method", "sequence", "frame", "instance", "category", "symmetry", "has_mesh", *[c for c, _ in ERROR_COLUMNS], "failure"]
    writer.writerow(columns)
    for r in results:
        for row in r.rows:
            writer.writerow(["" if row.get(c) is None or (isinstance(row.get(c), float) and math.isnan(row[c])) else row[c] for c in columns])
    return buffer.getvalue()


def write_curves_png(path: Path, dataset: str, results: list[MethodResult]) -> Path:
    """Fig. 5 layout: one panel per error kind (position, rotation, IoU, F-score), one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    kinds = [k for k in CURVE_LABELS if any(k in r.curves for r in results)]
    figure, axes = plt.subplots(1, max(len(kinds), 1), figsize=(4 * max(len(kinds), 1), 3.4), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        label, factor = CURVE_LABELS[kind]
        for r in results:
            if kind in r.curves:
                grid, precision = r.curves[kind]
                ax.plot(np.asarray(grid) * factor, precision, marker=".", label=r.name)
        ax.set_xlabel(label)
        ax.set_ylabel("precision")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].legend(loc="best", fontsize="small")
    figure.suptitle(dataset)
    figure.tight_layout()
    return _save_png(figure, path, dpi=120)


def write_outputs(out: Path, dataset: str, results: list[MethodResult], categories: list[str], notes: list[str]) -> dict[str, Path]:
    """Write every output under ``out`` atomically; returns them by kind."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "results": write_text_atomic(out / "results.json", json.dumps(results_json(dataset, results), indent=2, allow_nan=False) + "\n"),
        "markdown": write_text_atomic(out / "table.md", markdown_tables(dataset, results, categories, notes)),
        "csv": write_text_atomic(out / "table.csv", csv_table(results, categories)),
        "errors": write_text_atomic(out / "errors.csv", errors_csv(results)),
    }
    curves = {r.name: {kind: {"thresholds": grid.tolist(), "overall": values.tolist()} for kind, (grid, values) in r.curves.items()} for r in results}
    document = {"dataset": dataset, "methods": curves}
    if any(r.nocs is not None for r in results):
        document["nocs_map"] = nocs_curves_json(results)
        paths["nocs_csv"] = write_text_atomic(out / "nocs_map.csv", nocs_csv(results))
    paths["curves"] = write_text_atomic(out / "curves.json", json.dumps(document, indent=1) + "\n")
    paths["plot"] = write_curves_png(out / "precision_curves.png", dataset, results)
    if "nocs_csv" in paths:
        paths["nocs_plot"] = write_nocs_png(out / "nocs_map_curves.png", dataset, results)
    return paths
