"""Benchmark evaluate.metrics against cpas_toolbox 1.0.0 on the same inputs, in one run.

    .venv/bin/python benchmarks/bench_metrics.py [--repeat 5] [--redwood75 DIR]

Prints one table: seconds per unit for cpas_toolbox and for ours, and the speed-up ratio.  Each figure is
the best of ``--repeat`` runs (least disturbed by other processes), as wall clock and as this process's
CPU time (the fairer figure on a shared, loaded machine); the machine load is printed too.
Rows:
* IoU per pair: cpas ``iou_3d`` (Qhull) vs our ``box_iou`` (one call per pair) and ``box_iou_batch``.
* symmetric IoU: cpas's ``correct_thresh`` with an IoU threshold and a symmetry axis raises ValueError
  (reported); for scale, a fixed version of its loop (100 angles of ``iou_3d``) vs our exact maximum.
* F-score at 10k/10k points: cpas ``reconstruction_fscore`` vs our ``fscore`` and ``ShapeIndex.fscore``
  (ground-truth tree built once per object, as the evaluation uses it).
* REDWOOD75 threshold grid for one sample (cpas config redwood75.yaml: the Fig. 5 curves and the 4
  Table 2 tuples, 58 threshold tuples): cpas calls ``correct_thresh`` once per tuple, as its
  ``Evaluator._eval_correctness_metric`` does (its per-metric re-sampling of the mesh with open3d is
  left out, which favours cpas); ours computes the sample's errors once (``compute_sample_errors`` with
  the object's prebuilt ``ShapeIndex``) and compares them with all 58 tuples.  What it leaves out is
  printed below it: the object's setup (mesh sampling, KD-tree, the grid of ``ShapeIndex.hits``; once
  per object for all its samples and methods) amortised over ``--samples-per-object``, and the same
  sample with IoU and chamfer distance as ``evaluate.runner`` computes them (full distances both ways).
* With ``--redwood75 DIR``: the same grid over the 30 REDWOOD75 samples that have a true mesh (6 real
  meshes, 5 samples each), ours including each object's setup (see ``redwood75_row``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluate.metrics import (  # noqa: E402
    ShapeIndex,
    Threshold,
    box_iou,
    box_iou_batch,
    compute_sample_errors,
    correct,
    fscore,
    sample_surface,
    symmetric_box_iou,
    symmetric_box_iou_batch,
)


class Timing(NamedTuple):
    """Seconds: wall clock, and CPU time of this process (less sensitive to other processes' load)."""

    wall: float
    cpu: float

    def __truediv__(self, n: float) -> "Timing":
        return Timing(self.wall / n, self.cpu / n)


def best_time(fn, repeat: int) -> Timing:
    """The fastest of ``repeat`` runs (by wall clock), with its CPU time."""
    best = Timing(np.inf, np.inf)
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        if wall < best.wall:
            best = Timing(wall, cpu)
    return best


def pose(rotation: Rotation, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation.as_matrix()
    T[:3, 3] = t
    return T


def redwood75_grid():
    pos = [0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03, 0.035, 0.04, 0.045, 0.05]
    f = [0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0]
    grid = [(p, None, None, None) for p in pos] + [(None, d, None, None) for d in range(21)] + [(None, None, None, x) for x in f]
    return grid + [(0.02, 10, None, None), (0.01, 5, None, None), (0.02, 10, None, 0.6), (0.01, 5, None, 0.8)]


def redwood75_row(root: Path, grid, thresholds, repeat: int):
    """The threshold grid over every sample of a REDWOOD75 copy that has a true mesh (its real meshes,
    ~5 samples per object), per sample; ours includes each object's setup (ShapeIndex and grid).
    Predictions: the true pose turned by ~2 deg and moved by ~1 cm, and a reconstruction that is the
    true mesh sampled again (another seed), 2 % larger, with 2 mm noise.  cpas as in its evaluator:
    rotational_symmetry_axis=1 for symmetric categories, posed points."""
    import cpas_toolbox.metrics as cpas

    from evaluate.datasets import open_dataset

    dataset = open_dataset(root)
    samples = [s for s in dataset if s.mesh_path is not None]
    meshes = {s.mesh_path: dataset.mesh(s) for s in samples}
    rng = np.random.default_rng(0)
    predictions = []
    for k, s in enumerate(samples):
        rotation = Rotation.from_quat(s.orientation) * Rotation.from_rotvec(rng.normal(size=3) * np.radians(1.2))
        points = sample_surface(meshes[s.mesh_path], 10000, seed=k + 1) * 1.02 + rng.normal(size=(10000, 3)) * 0.002
        predictions.append((s.position + rng.normal(size=3) * 0.006, rotation, points))

    def ours():
        indices, decisions = {}, []
        for s, (t, rotation, points) in zip(samples, predictions):
            if s.mesh_path not in indices:
                indices[s.mesh_path] = ShapeIndex.from_mesh(meshes[s.mesh_path], n=10000, seed=0)
                indices[s.mesh_path].prepare(0.01)
            errors = compute_sample_errors(s.position, s.orientation, s.extents, s.symmetry, indices[s.mesh_path], t,
                                           rotation.as_quat(), s.extents, points, compute_iou=False)
            decisions.append(correct(errors, thresholds)[:, 0])
        return np.array(decisions)

    def theirs():
        decisions = []
        for s, (t, rotation, points) in zip(samples, predictions):
            r_gt = Rotation.from_quat(s.orientation)
            gt = r_gt.apply(ShapeIndex.from_mesh(meshes[s.mesh_path], n=10000, seed=0).points) + s.position
            pred = rotation.apply(points) + t
            axis = 1 if s.symmetry == "y" else None
            decisions.append([cpas.correct_thresh(s.position, t, r_gt, rotation, s.extents, s.extents, gt, pred, p, d, i, f,
                                                  rotational_symmetry_axis=axis) for p, d, i, f in grid])
        return np.array(decisions, dtype=bool)

    ours_decisions, cpas_decisions = ours(), theirs()
    assert np.array_equal(ours_decisions, cpas_decisions)
    n = len(samples)
    t_ours = best_time(ours, repeat) / n
    t_cpas = best_time(theirs, 1) / n
    return (f"  REDWOOD75, {n} samples with a mesh, incl. setup", t_cpas, t_ours,
            f"identical decisions; {len(meshes)} objects, {ours_decisions.mean():.2f} correct")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--pairs", type=int, default=200)
    parser.add_argument("--samples-per-object", type=int, default=5, help="to amortise the per-object setup over")
    parser.add_argument("--redwood75", type=Path, default=None, metavar="DIR",
                        help="also time the grid over the samples with a true mesh of this REDWOOD75 copy (annotations.json, meshes/)")
    args = parser.parse_args()
    import cpas_toolbox.metrics as cpas

    rng = np.random.default_rng(0)
    n = args.pairs
    r1, r2 = Rotation.random(n, random_state=1), Rotation.random(n, random_state=2)
    p1, p2 = rng.normal(size=(n, 3)) * 0.03, rng.normal(size=(n, 3)) * 0.03
    e1, e2 = rng.uniform(0.05, 0.2, (n, 3)), rng.uniform(0.05, 0.2, (n, 3))
    T1 = np.stack([pose(r1[i], p1[i]) for i in range(n)])
    T2 = np.stack([pose(r2[i], p2[i]) for i in range(n)])
    rows = []

    np.random.seed(0)
    t_cpas = best_time(lambda: [cpas.iou_3d(p1[i], r1[i], e1[i], p2[i], r2[i], e2[i]) for i in range(n)], args.repeat) / n
    t_one = best_time(lambda: [box_iou(e1[i], T1[i], e2[i], T2[i]) for i in range(n)], args.repeat) / n
    t_batch = best_time(lambda: box_iou_batch(e1, T1, e2, T2), args.repeat) / n
    diff = np.abs(box_iou_batch(e1, T1, e2, T2) - np.array([cpas.iou_3d(p1[i], r1[i], e1[i], p2[i], r2[i], e2[i]) for i in range(n)])).max()
    rows.append(("IoU, per pair, one call each", t_cpas, t_one, f"max |ours - cpas| = {diff:.1e}"))
    rows.append((f"IoU, per pair, batched ({n} pairs)", t_cpas, t_batch, ""))

    # symmetric IoU
    try:
        cpas.correct_thresh(p1[0], p2[0], r1[0], r2[0], e1[0], e2[0], iou_3d_threshold=0.5, rotational_symmetry_axis=1)
        note = "cpas ran"
    except ValueError as error:
        note = f"cpas raises ValueError: {str(error)[:40]}..."
    m = 10
    q2 = [r2[i] * Rotation.from_euler("y", 0.0) for i in range(m)]
    fixed = lambda i: max(cpas.iou_3d(p1[i], r1[i], e1[i], p2[i], q2[i] * Rotation.from_rotvec([0, a, 0]), e2[i])  # noqa: E731
                          for a in np.linspace(0, np.pi, 100))
    t_cpas_sym = best_time(lambda: [fixed(i) for i in range(m)], max(1, args.repeat // 2)) / m
    t_sym = best_time(lambda: [symmetric_box_iou(e1[i], T1[i], e2[i], T2[i]) for i in range(m)], max(1, args.repeat // 2)) / m
    t_sym_b = best_time(lambda: symmetric_box_iou_batch(e1[:m], T1[:m], e2[:m], T2[:m]), max(1, args.repeat // 2)) / m
    rows.append(("symmetric IoU, per pair (cpas: fixed 100-angle loop)", t_cpas_sym, t_sym, note))
    rows.append((f"symmetric IoU, per pair, batched ({m} pairs)", t_cpas_sym, t_sym_b, "ours: exact max, see box_iou.py"))

    # F-score 10k / 10k
    # surface samples of a 10 x 16 x 10 cm ellipsoid; the "reconstruction" 2 % too big, 3 mm noise
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    mesh.vertices *= [1.0, 1.6, 1.0]
    index = ShapeIndex.from_mesh(mesh, n=10000, seed=0)
    gt = index.points
    pred = sample_surface(mesh, n=10000, seed=1) * 1.02 + rng.normal(size=(10000, 3)) * 0.003
    assert fscore(gt, pred).fscore == cpas.reconstruction_fscore(gt, pred, 0.01)
    t_cpas_f = best_time(lambda: cpas.reconstruction_fscore(gt, pred, 0.01), args.repeat)
    t_f = best_time(lambda: fscore(gt, pred, 0.01), args.repeat)
    t_fi = best_time(lambda: index.fscore(pred, 0.01), args.repeat)
    rows.append(("F-score, 10k / 10k points", t_cpas_f, t_f, "identical value"))
    rows.append(("F-score, 10k / 10k, gt tree prebuilt (ShapeIndex)", t_cpas_f, t_fi, ""))

    # REDWOOD75 threshold grid for one sample
    grid = redwood75_grid()
    thresholds = [Threshold(position=p, degrees=d, iou=i, fscore=f) for p, d, i, f in grid]
    r_gt, r_pred = r1[0], r1[0] * Rotation.from_rotvec([0.02, 0.05, -0.03])
    t_gt, t_pred = np.array([0.0, 0.0, 0.8]), np.array([0.005, -0.004, 0.81])
    posed_gt, posed_pred = r_gt.apply(gt) + t_gt, r_pred.apply(pred) + t_pred
    ext = np.array([0.1, 0.2, 0.1])

    def cpas_grid():
        return [cpas.correct_thresh(t_gt, t_pred, r_gt, r_pred, ext, ext, posed_gt, posed_pred, p, d, i, f) for p, d, i, f in grid]

    def our_grid():
        errors = compute_sample_errors(t_gt, r_gt.as_quat(), ext, "none", index, t_pred, r_pred.as_quat(), ext, pred, compute_iou=False)
        return correct(errors, thresholds)[:, 0]

    assert np.array_equal(np.array(cpas_grid(), dtype=bool), our_grid())
    t_cpas_g = best_time(cpas_grid, max(1, args.repeat // 2))
    t_g = best_time(our_grid, args.repeat)
    rows.append((f"REDWOOD75 grid, one sample ({len(grid)} tuples)", t_cpas_g, t_g, "identical decisions; goal < 10 ms, >= 50x"))

    # what the per-sample figure leaves out: the object's setup, paid once per object for every sample
    # and method (sampling its mesh, the KD-tree, the grid of ShapeIndex.hits at the F-score distance)
    def object_setup():
        ShapeIndex.from_mesh(mesh, n=10000, seed=0).prepare(0.01)

    t_setup = best_time(object_setup, args.repeat)
    k = args.samples_per_object
    t_amortised = Timing(t_g.wall + t_setup.wall / k, t_g.cpu + t_setup.cpu / k)
    rows.append((f"  + object setup / {k} samples (setup {t_setup.cpu * 1e3:.1f} ms CPU)", t_cpas_g, t_amortised,
                 "REDWOOD75: ~5 samples per object, setup shared by all methods"))

    # what evaluate.runner.score_method computes per sample today: IoU and the chamfer distance too, so
    # full nearest-neighbour distances both ways instead of ShapeIndex.hits
    def runner_errors():
        return compute_sample_errors(t_gt, r_gt.as_quat(), ext, "none", index, t_pred, r_pred.as_quat(), ext, pred, compute_chamfer=True)

    assert runner_errors().fscore[0] == compute_sample_errors(t_gt, r_gt.as_quat(), ext, "none", index, t_pred, r_pred.as_quat(), ext, pred).fscore[0]
    t_runner = best_time(lambda: correct(runner_errors(), thresholds), args.repeat)
    rows.append(("  same, with IoU and chamfer (as evaluate.runner)", t_cpas_g, t_runner, "cpas computes neither for these tuples"))

    if args.redwood75 is not None:
        rows.append(redwood75_row(args.redwood75, grid, thresholds, args.repeat))

    load = os.getloadavg()
    print(f"evaluate.metrics vs cpas_toolbox 1.0.0  (best of {args.repeat}; load average {load[0]:.1f} {load[1]:.1f} "
          f"{load[2]:.1f} on {os.cpu_count()} CPUs)")
    print(f"{'':55s} {'---------- wall clock ----------':>33s}  {'----------- CPU time -----------':>33s}")
    print(f"{'benchmark':55s} {'cpas':>11s} {'ours':>11s} {'speed-up':>9s}  {'cpas':>11s} {'ours':>11s} {'speed-up':>9s}  note")
    for name, theirs, ours, note in rows:
        print(f"{name:55s} {theirs.wall * 1e3:8.3f} ms {ours.wall * 1e3:8.3f} ms {theirs.wall / ours.wall:8.1f}x  "
              f"{theirs.cpu * 1e3:8.3f} ms {ours.cpu * 1e3:8.3f} ms {theirs.cpu / ours.cpu:8.1f}x  {note}")


if __name__ == "__main__":
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        main()
