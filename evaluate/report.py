"""Writing an evaluation's outputs, each atomically: ``results.json`` (DESIGN.md's schema), the
precision tables as Markdown and CSV (overall and per category, as the paper's Tables 2 and 3),
precision-versus-threshold plots as PNG (the paper's Fig. 5: one panel per error kind, one line
per method) with their numbers in ``curves.json``, and the per-sample errors as CSV.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

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


def _fraction(value: float | None) -> float | None:
    return None if value is None or (isinstance(value, float) and math.isnan(value)) else float(value)


def results_json(dataset: str, results: list[MethodResult]) -> dict:
    """DESIGN.md's ``results.json``: {dataset, methods: {NAME: {samples, failed, precision: [...]}}}."""
    return {
        "dataset": dataset,
        "methods": {r.name: {"samples": r.samples, "failed": r.failed, "precision": [p.to_json() for p in r.precision]} for r in results},
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
    tmp = temporary_sibling(path)
    try:
        figure.savefig(tmp, format="png", dpi=120)
        tmp.replace(path)
    finally:
        plt.close(figure)
        if tmp.exists():
            tmp.unlink()
    return path


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
    paths["curves"] = write_text_atomic(out / "curves.json", json.dumps({"dataset": dataset, "methods": curves}, indent=1) + "\n")
    paths["plot"] = write_curves_png(out / "precision_curves.png", dataset, results)
    return paths
