"""Accuracy and speed of reconstruct-sequence on synthetic sequences (run on demand; prints figures).

    .venv/bin/python benchmarks/bench_reconstruct.py [--root /tmp/synth] [--categories bottle bowl mug can]
        [--frames 100] [--seed 0] [--voxel-size 0.002] [--k K] [--tol-sigmas S] [--voxel-margin M] [--settle N] [--carved-share S] [--no-shadows]
        [--unbacked N | --no-unbacked] [--evidence-hull | --no-evidence-hull] [--bound]

Use one --root per --seed (a sequence generated there is reused whatever the seed).

For each category a synthetic 640x480 sequence (sequences.synth; generated into ROOT/<category>
when missing) is reconstructed from every frame twice: with the true poses, and with every pose
perturbed by exactly 1 degree (random axis) and 2 mm (random direction). The annotated extents
are off by up to 10 % (the carving margin must cover that). With --bound a third run, "bound",
carves with the true poses every voxel seen free in even one frame (k = 0, no veto, hence no
evidence hull): no rule on free-space votes can carve more, so what it leaves (a cavity or a
hand-covered patch never seen free) is missing from the free-space evidence, not from the rule.
The evidence hull (reconstruct.evidence; off by default) goes further: it also drops
unseen space that no measured surface bounds; --evidence-hull uses it for every object without
symmetry, --no-evidence-hull for none. Printed per run:

- F@5mm, F@1cm: F-score of the mesh against the true mesh (area-weighted surface samples, cKDTree;
  the true mesh's faces buried inside another of its parts are left out: see outer_samples);
- extents error: the tight box's extents minus the true extents (mm, x y z);
- remnant: share of the reconstructed surface farther than 1 cm from the true surface (hand
  remnants, table, uncarved margin), and the largest such distance;
- seconds per stage (carve, mesh) and total (wall clock), the CPU seconds of the reconstruction
  (all threads; the load-independent figure on a shared machine); masks + export separately
  (wall clock, and CPU seconds as xcpu);
- the machine load (os.getloadavg) before and after: the machine is shared.

Goals (issue 4): F@5mm >= 0.9, F@1cm >= 0.98, extents within 3 mm, no remnants; <= 10 s for 100 frames.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from reconstruct.export import export_redwood
from reconstruct.pipeline import reconstruct_sequence
from sequences.annotation import FramePose
from sequences.reader import open_sequence
from sequences.synth import generate_sequence, load_truth, truth_annotation


def outer_samples(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    """Area-weighted samples (metres) of the mesh's outer surface: of ``n`` samples, those not inside another of its
    connected parts. A procedural mesh is a union of overlapping closed parts (a camera's grip sunk halfway into its
    body, a mug handle's ends in the wall): their buried faces are no surface anyone can see or reconstruct."""
    points, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    part_of = labels[face]
    buried = np.zeros(len(points), bool)
    for part in np.unique(labels):  # a few parts
        faces = np.asarray(mesh.faces)[labels == part]
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
        others = part_of != part
        buried[others] |= scene.compute_occupancy(o3d.core.Tensor(points[others].astype(np.float32))).numpy() > 0
    return points[~buried]


def surface_distances(a: trimesh.Trimesh, b: trimesh.Trimesh, n: int = 30000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Distances from area-weighted samples of ``a`` to samples of ``b``'s outer surface and back (metres)."""
    pa = trimesh.sample.sample_surface(a, n, seed=seed)[0]
    pb = outer_samples(b, n, seed + 1)
    return cKDTree(pb).query(pa)[0], cKDTree(pa).query(pb)[0]


def fscore_from(d_ab: np.ndarray, d_ba: np.ndarray, threshold: float) -> float:
    precision, recall = np.mean(d_ab < threshold), np.mean(d_ba < threshold)
    return float(2 * precision * recall / max(precision + recall, 1e-12))


def perturb(annotation, degrees: float, metres: float, seed: int):
    """Every pose composed with a rotation of exactly ``degrees`` (random axis) and moved by exactly ``metres``."""
    rng = np.random.default_rng(seed)
    out = annotation.copy()
    for frame in out.frames.values():
        T = frame.matrix
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(axis * np.radians(degrees)).as_matrix()
        T[:3, 3] = T[:3, 3] + metres * direction
        moved = FramePose.from_matrix(T, frame.source, frame.extra)
        frame.position, frame.orientation = moved.position, moved.orientation
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", default=str(Path(tempfile.gettempdir()) / "synth"))
    parser.add_argument("--categories", nargs="+", default=["bottle", "bowl", "mug", "can"])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--voxel-size", type=float, default=0.002)
    parser.add_argument("--k", type=int, default=None)
    parser.add_argument("--tol-sigmas", type=float, default=None)
    parser.add_argument("--voxel-margin", type=float, default=None, help="half voxel diagonals added to the free-space tolerance (default: reconstruct.pipeline.VOXEL_MARGIN)")
    parser.add_argument("--settle", type=int, default=None, help="free votes after which the veto no longer saves a voxel")
    parser.add_argument("--carved-share", type=float, default=None, help="share of a ring (symmetry y) carved for the whole ring to go")
    parser.add_argument("--no-shadows", action="store_true", help="missing depth stays unknown even where a projector shadow explains it")
    parser.add_argument("--unbacked", type=int, default=None, help="carve voxels never seen behind the surface once seen free in more than N frames")
    parser.add_argument("--no-unbacked", action="store_true", help="no such rule (the k / veto rule alone)")
    parser.add_argument("--evidence-hull", action="store_true", help="drop the unseen space no measured surface bounds for every object without symmetry (reconstruct.evidence)")
    parser.add_argument("--no-evidence-hull", action="store_true", help="keep the unseen space no measured surface bounds for every object")
    parser.add_argument("--bound", action="store_true", help="also carve with the true poses, k = 0 and no veto: what the depth allows at most")
    parser.add_argument("--no-export", action="store_true")
    args = parser.parse_args()
    extra = {}
    if args.k is not None:
        extra["k"] = args.k
    if args.tol_sigmas is not None:
        extra["tol_sigmas"] = args.tol_sigmas
    if args.voxel_margin is not None:
        extra["voxel_margin"] = args.voxel_margin
    if args.settle is not None:
        extra["settle"] = args.settle
    if args.carved_share is not None:
        extra["carved_share"] = args.carved_share
    if args.no_shadows:
        extra["shadows"] = False
    if args.unbacked is not None:
        extra["unbacked"] = args.unbacked
    if args.no_unbacked:
        extra["unbacked"] = None
    if args.evidence_hull:
        extra["evidence_hull"] = True
    if args.no_evidence_hull:
        extra["evidence_hull"] = False

    print(f"load before: {os.getloadavg()} on {os.cpu_count()} cores")
    header = f"{'category':8} {'poses':9} {'F@5mm':>6} {'F@1cm':>6} {'extents err mm (x y z)':>24} {'remnant':>8} {'max mm':>7} {'carve':>6} {'mesh':>5} {'total':>6} {'cpu':>5} {'export':>6} {'xcpu':>5}"
    print(header)
    for category in args.categories:
        root = Path(args.root) / category
        if not (root / "truth" / "truth.json").exists():
            generate_sequence(root, category, frames=args.frames, seed=args.seed)
        truth = load_truth(root)
        sequence = open_sequence(root)
        exact = truth_annotation(truth, truth.ids, 0.0, 0.0, extents_rel=0.1, seed=args.seed)
        runs = {"true": (exact, extra), "1deg+2mm": (perturb(exact, 1.0, 0.002, seed=args.seed + 1), extra)}
        if args.bound:
            runs["bound"] = (exact, {**extra, "k": 0, "veto": None})
        for name, (annotation, options) in runs.items():
            start, cpu = time.perf_counter(), time.process_time()
            rec = reconstruct_sequence(sequence, annotation, args.voxel_size, **options)
            total, cpu = time.perf_counter() - start, time.process_time() - cpu
            export_s = export_cpu = float("nan")
            if not args.no_export:
                with tempfile.TemporaryDirectory() as out:
                    start, export_cpu = time.perf_counter(), time.process_time()
                    export_redwood(rec, sequence, annotation, out)
                    export_s, export_cpu = time.perf_counter() - start, time.process_time() - export_cpu
            mesh = rec.mesh.copy()
            mesh.apply_translation(rec.centre_shift)  # back into the annotated (= true) object frame
            d_ab, d_ba = surface_distances(mesh, truth.mesh)
            error_mm = (rec.extents - truth.extents) * 1000
            remnant = float(np.mean(d_ab > 0.01))
            t = rec.timings
            print(
                f"{category:8} {name:9} {fscore_from(d_ab, d_ba, 0.005):6.3f} {fscore_from(d_ab, d_ba, 0.01):6.3f} "
                f"{error_mm[0]:+7.1f} {error_mm[1]:+7.1f} {error_mm[2]:+7.1f}  {remnant:8.4f} {d_ab.max() * 1000:7.1f} "
                f"{t['carve']:6.2f} {t['mesh']:5.2f} {total:6.2f} {cpu:5.2f} {export_s:6.2f} {export_cpu:5.2f}",
                flush=True,
            )
    print(f"load after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
