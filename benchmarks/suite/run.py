"""Running the suite on one sequence: track from placed boxes, reconstruct, score against the truth; and the tables.

For each sequence: the true surface's observed part is found once (:func:`evaluate.annotation_quality.true_surface`);
then ``truth`` reconstructs from the true poses, and each tracked setting places its boxes (the true poses of evenly
spread frames, off by up to the setting's amounts, extents too), tracks every frame (``annotate.tracking``), and
reconstructs from the tracked poses (``reconstruct``). Every setting is scored the same way (see
:mod:`evaluate.annotation_quality`). The toolkit sees what a user gives it: the sequence and an annotation document
(category, symmetry, extents, boxes); never the generator's seed, texture or shape.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from evaluate.annotation_quality import extents_error_mm, pose_scores, posed_fscore, revolution_fscore, shape_scores, true_surface
from reconstruct.seen import BOUNDED
from sequences.annotation import Annotation, FramePose
from sequences.reader import Sequence, open_sequence
from sequences.synth.truth import truth_annotation
from sequences.truth import Truth, open_truth

from .spec import Setting

#: The goals of the tracking and reconstruction issues, per sequence: (figure, limit, True when it must stay at or below).
TRACKING_GOALS = (("rot_median_deg", 1.5, True), ("rot_p90_deg", 3.0, True), ("centre_median_mm", 3.0, True),
                  ("posed_f5", 0.85, False), ("flagged_share", 0.15, True), ("unflagged_over_5deg", 0, True),
                  ("unflagged_over_10mm", 0, True))
RECONSTRUCTION_GOALS = (("observed_recall5", 0.95, False), ("observed_precision5", 0.90, False), ("measured_face_error_mm", 3.0, True),
                        ("observed_share_gap_pp", 5.0, True), ("reconstruct_s_per_100", 10.0, True), ("nonround_shape_f5", 0.9, False))
#: A true mesh whose revolution_fscore is below this is no solid of revolution (a square bowl 0.82; round shapes 0.88-1.0):
#: labelled symmetric, its reconstruction must keep its shape (nonround_shape_f5, the issue's F@5mm >= 0.9).
ROUND_F5 = 0.85


def manual_frames(ids: list[str], count: int) -> list[str]:
    """Evenly spread frames, a few in from both ends, as an annotator would pick them."""
    n = len(ids)
    return [ids[i] for i in np.linspace(min(3, n - 1), max(n - 4, 0), count).round().astype(int)]


def measured_frames(sequence: Sequence, truth: Truth) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(true pose, the object's measured points in the camera frame) per frame: depth inside the true mask."""
    for frame_id in sequence.ids:  # one image per frame
        if frame_id in truth.poses:
            points, _ = sequence.camera.backproject(sequence.depth(frame_id), truth.mask(frame_id))
            yield truth.poses[frame_id], points


def true_pose_annotation(truth: Truth, name: str) -> Annotation:
    """A document holding every frame's true pose and the true extents (reconstruction from the truth)."""
    frames = {f: FramePose.from_matrix(T, "manual") for f, T in truth.poses.items()}
    return Annotation(sequence=name, category=truth.category, symmetry=truth.symmetry, extents=np.asarray(truth.extents, float), frames=frames)


def symmetric_extents_error(extents: np.ndarray, truth: Truth) -> float:
    """The largest box-side error (mm); for symmetry y the x and z sides compared in sorted order (the spin about y is free)."""
    a, b = np.asarray(extents, float), np.asarray(truth.extents, float)
    if truth.symmetry == "y":
        a, b = np.array([a[[0, 2]].max(), a[1], a[[0, 2]].min()]), np.array([b[[0, 2]].max(), b[1], b[[0, 2]].min()])
    return float(np.abs(extents_error_mm(a, b)).max())


def missed_goals(row: dict, goals) -> list[str]:
    """The ``goals`` ((figure, limit, True when it must stay at or below) each) a row misses, as "figure value" strings;
    a figure not measured is not judged."""
    misses = []
    for key, limit, at_most in goals:
        value = row.get(key)
        if value is not None and (value > limit if at_most else value < limit):
            misses.append(f"{key} {value:.3g}")
    return misses


def goal_misses(row: dict) -> list[str]:
    """The tracking and reconstruction goals a suite row misses (a ``truth`` row has no tracking figures)."""
    return missed_goals(row, RECONSTRUCTION_GOALS + (TRACKING_GOALS if row["setting"] != "truth" else ()))


def reconstruction_scores(sequence: Sequence, annotation: Annotation, truth: Truth, surface, mesh_surface: str | None = None) -> dict:
    """Scores of ``reconstruct_sequence`` on ``annotation``; ``mesh_surface``: its ``surface`` option (None: its default)."""
    from reconstruct.pipeline import SURFACE, reconstruct_sequence
    from sequences.errors import InputError

    start = time.perf_counter()
    try:
        recon = reconstruct_sequence(sequence, annotation, voxel_size=0.002, surface=mesh_surface or SURFACE)
    except InputError as error:  # the reconstruction is one of the parts measured: a failure is a figure
        return {"reconstruct_error": str(error)}
    seconds = time.perf_counter() - start
    reported = None if recon.surface is None else recon.surface.shares["observed"]
    # the observed part's precision on what the reconstruction says it observed (its labels, held honest by the share gap)
    claimed = None if recon.surface is None else recon.surface.observed_faces(recon.mesh.faces)
    shape = shape_scores(recon.mesh, recon.poses, surface, truth.poses, observed_faces=claimed)
    measured = None if recon.surface is None else sorted(f for f, state in recon.surface.faces.items() if state in BOUNDED)
    exported = any(f in truth.poses for f in recon.poses)
    return {
        # the export's poses are re-centred on the reconstruction's tight box: the centre a user of the ground truth gets
        "export_centre_median_mm": pose_scores(recon.poses, {}, truth.poses, truth.symmetry)["centre_median_mm"] if exported else None,
        "posed_f5": posed_fscore(recon.mesh, recon.poses, surface, truth.poses),
        **shape,
        "extents_error_mm": symmetric_extents_error(recon.extents, truth),
        "observed_share_reported": reported,
        "measured_faces": measured,
        # the largest error of a box face a measurement bounds (all six when the reconstruction does not say)
        "measured_face_error_mm": max((abs(v) for f, v in shape["face_errors_mm"].items() if measured is None or f in measured), default=None),
        "reconstruct_s": seconds,
        "surface": mesh_surface or SURFACE,
        "support_plane": recon.report.get("support_plane"),  # the plane a static object stood on, where one was found
    }


def run_sequence(root: Path, settings: list[Setting], name: str, seed: int, workers: int | None = None, engine: str | None = None,
                 mesh_surface: str | None = None) -> list[dict]:
    """Rows of figures for one sequence: ``truth`` and each of ``settings`` (its boxes drawn from ``seed``), tracked by
    ``engine`` (annotate.engines; default: the default engine), reconstructed with ``mesh_surface`` (reconstruct.pipeline's
    SURFACES; default: its default)."""
    from annotate.engines import engine_name, tracking_engine

    engine = engine_name(engine)
    track_sequence = tracking_engine(engine).track_sequence

    sequence, truth = open_sequence(root), open_truth(root)
    surface = true_surface(truth.mesh, measured_frames(sequence, truth))
    base = {"sequence": name, "category": truth.category, "symmetry": truth.symmetry, "frames": len(sequence),
            "observed_share_truth": surface.observed_share,
            "revolution_f5": revolution_fscore(truth.mesh) if truth.symmetry == "y" else None}
    rows = [{**base, "setting": "truth", **reconstruction_scores(sequence, true_pose_annotation(truth, name), truth, surface, mesh_surface)}]
    for setting in settings:
        placed = truth_annotation(truth, manual_frames(sequence.ids, setting.boxes), setting.degrees, setting.metres, setting.extents, seed=seed)
        config = None
        if engine == "chains" and workers is not None:
            from annotate.tracking import TrackingConfig

            config = TrackingConfig(workers=workers)
        start, cpu = time.perf_counter(), _cpu_seconds()
        tracked = track_sequence(sequence, placed, config=config)
        wall, cpu = time.perf_counter() - start, _cpu_seconds() - cpu
        poses = {f: p.matrix for f, p in tracked.frames.items()}
        flagged = {f: bool(p.extra.get("flagged")) for f, p in tracked.frames.items()}
        row = {**base, "setting": setting.name, "engine": engine, **pose_scores(poses, flagged, truth.poses, truth.symmetry),
               "ms_per_frame": 1000 * wall / len(sequence), "cpu_ms_per_frame": 1000 * cpu / len(sequence)}
        row.update(reconstruction_scores(sequence, tracked, truth, surface, mesh_surface))
        rows.append(row)
    for row in rows:
        if row.get("observed_share_reported") is not None:  # percentage points between what the export says was seen and what was
            row["observed_share_gap_pp"] = 100.0 * abs(row["observed_share_reported"] - row["observed_share_truth"])
        if row["revolution_f5"] is not None and row["revolution_f5"] < ROUND_F5 and row.get("shape_f5") is not None:
            row["nonround_shape_f5"] = row["shape_f5"]  # labelled symmetric, not round: judged on keeping its shape
        if row.get("reconstruct_s") is not None:
            row["reconstruct_s_per_100"] = 100.0 * row["reconstruct_s"] / len(sequence)
        row["goals_missed"] = goal_misses(row)
    return rows


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (the tracker's workers)."""
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


# ------------------------------------------------------------------------------------------------ tables

COLUMNS = (  # (key, header, format)
    ("rot_median_deg", "rot med°", "{:.2f}"), ("rot_p90_deg", "p90°", "{:.2f}"), ("centre_median_mm", "ctr mm", "{:.1f}"),
    ("export_centre_median_mm", "export ctr mm", "{:.1f}"), ("flagged_share", "flagged", "{:.0%}"), ("unflagged_over_5deg", ">5° unfl.", "{:d}"),
    ("posed_f5", "posed F5", "{:.3f}"),
    ("shape_f5", "shape F5", "{:.3f}"), ("observed_precision5", "obs P5", "{:.3f}"), ("observed_recall5", "obs R5", "{:.3f}"),
    ("extents_error_mm", "ext mm", "{:.1f}"), ("measured_face_error_mm", "meas. face mm", "{:.1f}"), ("observed_share_gap_pp", "share gap pp", "{:.0f}"),
    ("reconstruct_s_per_100", "rec. s/100 f", "{:.1f}"), ("ms_per_frame", "ms/f", "{:.0f}"),
)


def _cell(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    return fmt.format(int(value)) if fmt == "{:d}" else fmt.format(value)


def sequence_table(rows: list[dict]) -> str:
    """A Markdown table: one row per sequence and setting, and the goals it misses."""
    head = "| sequence | setting | obs. share (reported) | " + " | ".join(h for _, h, _ in COLUMNS) + " | goals missed |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for row in rows:
        cells = [_cell(row.get(k), f) for k, _, f in COLUMNS]
        missed = "; ".join(row.get("goals_missed", []) + (["reconstruct failed: " + row["reconstruct_error"]] if "reconstruct_error" in row else []))
        reported = f" ({row['observed_share_reported']:.0%})" if row.get("observed_share_reported") is not None else ""
        lines.append(f"| {row['sequence']} | {row['setting']} | {row['observed_share_truth']:.0%}{reported} | " + " | ".join(cells) + f" | {missed} |")
    return "\n".join(lines)


def category_table(rows: list[dict]) -> str:
    """A Markdown table: per setting and category, the median of each figure over its sequences, and how many
    sequences miss a goal."""
    head = "| setting | category | seqs | " + " | ".join(h for _, h, _ in COLUMNS) + " | seqs missing a goal |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for setting in dict.fromkeys(r["setting"] for r in rows):
        mine = [r for r in rows if r["setting"] == setting]
        for category in sorted({r["category"] for r in mine}) + ["all"]:
            group = mine if category == "all" else [r for r in mine if r["category"] == category]
            cells = []
            for key, _, fmt in COLUMNS:
                values = [r[key] for r in group if r.get(key) is not None]
                cells.append(_cell(float(np.median(values)) if values and fmt != "{:d}" else (int(np.sum(values)) if values else None), fmt))
            missing = sum(bool(r.get("goals_missed")) or "reconstruct_error" in r for r in group)
            label = f"**{category}**" if category == "all" else category
            lines.append(f"| {setting} | {label} | {len(group)} | " + " | ".join(cells) + f" | {missing} of {len(group)} |")
    return "\n".join(lines)
