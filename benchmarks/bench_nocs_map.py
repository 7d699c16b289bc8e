"""Time of a REDWOOD75-size evaluation with NOCS-style mAP: 75 samples, 3 methods, and of NOCS mAP alone.

    .venv/bin/python benchmarks/bench_nocs_map.py [--repeat 3] [--redwood75 ../shared/data/redwood75] [--scale 2750]

Three methods are evaluated from predictions files (how methods not run here are evaluated), written once:
the truth disturbed by seeded noise of three sizes (1 cm / 5 deg / 5 %, 2 cm / 10 deg / 10 %, 4 cm / 20 deg /
20 %), each prediction with a seeded random score.  Printed, best of ``--repeat`` runs, wall clock and CPU:

* the whole ``evaluate`` command in a fresh process (imports, reading, errors, NOCS mAP, every output file
  and both plots), the figure the goal is about (under 10 s on 2 cores); once for the three predictions
  files (poses only), once for three noisy ``oracle`` methods of the same noise, which also return the true
  mesh as their reconstruction, so that chamfer distance and F-score are computed for the 30 samples
  with a mesh (10,000 surface points each, the default);
* inside one process: ``evaluate_dataset`` (all metrics), ``write_outputs``, and the NOCS mAP share of
  them (matching and AP of the 3 methods; the NOCS plot);
* NOCS mAP alone on a synthetic set of REAL275's kind (``--scale`` images with 5 objects of 6 categories
  each, one detection per object plus one stray per image), as :func:`evaluate.metrics.nocs_map.nocs_map`
  computes it from scratch; nearly all of it is the exact symmetric IoU of the pairs whose truth is a
  bottle, bowl or can (:func:`evaluate.metrics.box_iou.symmetric_box_iou_batch`), printed per pair so the
  full REAL275 test split (2754 images) can be extrapolated.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: The three methods: (name, position noise m, rotation noise deg, relative extents noise).
METHODS = (("good", 0.01, 5.0, 0.05), ("fair", 0.02, 10.0, 0.10), ("poor", 0.04, 20.0, 0.20))


def write_predictions(dataset, folder: Path, seed: int) -> list[str]:
    """One predictions file per method (seeded noise and scores); returns the NAME=FILE specs."""
    rng = np.random.default_rng(seed)
    specs = []
    for name, position, degrees, extents in METHODS:
        lines = []
        for s in dataset:
            turn = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.radians(degrees))
            q = (turn * Rotation.from_quat(s.orientation)).as_quat()
            entry = {"sequence": s.sequence, "frame": s.frame, "position": (s.position + rng.normal(0, position / np.sqrt(3), 3)).tolist(),
                     "orientation": q.tolist(), "extents": (s.extents * (1 + rng.normal(0, extents, 3))).clip(1e-3).tolist(), "score": float(rng.random())}
            lines.append(json.dumps(entry))
        path = folder / f"{name}.jsonl"
        path.write_text("\n".join(lines) + "\n")
        specs.append(f"{name}={path}")
    return specs


def best(fn, repeat: int) -> tuple[float, float]:
    """Best (wall, CPU of this process) seconds of ``repeat`` calls."""
    runs = []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        runs.append((time.perf_counter() - t, time.process_time() - c))
    return min(r[0] for r in runs), min(r[1] for r in runs)


def command_time(args: list[str], repeat: int) -> tuple[float, float]:
    """Best (wall, CPU of the child) seconds of the ``evaluate`` command in a fresh process."""
    runs = []
    for _ in range(repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "evaluate.cli", *args, "--quiet"], cwd=REPO, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - t
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        runs.append((wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)))
    return min(r[0] for r in runs), min(r[1] for r in runs)


def real275_scale(images: int, seed: int):
    """A synthetic detection set of REAL275's size: per image 5 objects of random categories, each detected
    with noise and a score, plus one stray detection."""
    from evaluate.metrics.nocs_map import nocs_symmetric

    categories = np.array(["bottle", "bowl", "camera", "can", "laptop", "mug"])
    rng = np.random.default_rng(seed)
    n = images * 5
    gt_image = np.repeat(np.arange(images), 5).astype(str)
    gt_category = categories[rng.integers(0, 6, n)]
    gt_pose = np.tile(np.eye(4), (n, 1, 1))
    gt_pose[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    gt_pose[:, :3, 3] = rng.uniform(-0.3, 0.3, (n, 3)) + [0, 0, 1]
    gt_extents = rng.uniform(0.05, 0.3, (n, 3))
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(8), (n, 3)))
    det_pose = gt_pose.copy()
    det_pose[:, :3, :3] = (Rotation.from_matrix(gt_pose[:, :3, :3]) * noise).as_matrix()
    det_pose[:, :3, 3] += rng.normal(0, 0.02, (n, 3))
    stray = np.tile(np.eye(4), (images, 1, 1))
    stray[:, :3, 3] = rng.uniform(-0.3, 0.3, (images, 3)) + [0, 0, 1]
    return dict(
        gt_image=gt_image, gt_category=gt_category, gt_pose=gt_pose, gt_extents=gt_extents, gt_symmetric=nocs_symmetric(gt_category),
        det_image=np.concatenate([gt_image, np.arange(images).astype(str)]),
        det_category=np.concatenate([gt_category, categories[rng.integers(0, 6, images)]]),
        det_score=rng.random(n + images),
        det_pose=np.concatenate([det_pose, stray]),
        det_extents=np.concatenate([gt_extents * rng.uniform(0.85, 1.15, (n, 3)), rng.uniform(0.05, 0.3, (images, 3))]),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--redwood75", default=str(REPO.parent / "shared" / "data" / "redwood75"))
    parser.add_argument("--scale", type=int, default=100, help="images of the synthetic REAL275-like run (REAL275's test split: 2754)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from evaluate.config import build_config
    from evaluate.datasets import open_dataset
    from evaluate.metrics.nocs_map import nocs_map
    from evaluate.report import write_nocs_png, write_outputs
    from evaluate.runner import evaluate_dataset, nocs_ground_truth, nocs_map_of_method, score_method

    cores = len(os.sched_getaffinity(0))
    print(f"machine: {cores} cores available, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    dataset = open_dataset(args.redwood75)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        specs = write_predictions(dataset, tmp, args.seed)
        cli = ["--dataset", args.redwood75, *sum((["--method", s] for s in specs), []), "--out", str(tmp / "out")]
        print(f"REDWOOD75: {len(dataset)} samples x {len(specs)} methods (predictions files with scores)")
        wall, cpu = command_time(cli, args.repeat)
        print(f"  whole evaluate command, 3 predictions files   {wall:6.2f} s wall  {cpu:6.2f} s CPU   goal < 10 s")
        oracles = tmp / "oracles.yaml"
        oracles.write_text(json.dumps({"dataset": args.redwood75, "out": str(tmp / "out3"), "methods": [
            {"name": name, "spec": "oracle", "config": {"position_noise": p / np.sqrt(3), "rotation_noise": d, "extents_noise": e, "seed": k}}
            for k, (name, p, d, e) in enumerate(METHODS)]}))
        wall, cpu = command_time(["--config", str(oracles)], args.repeat)
        print(f"  whole evaluate command, 3 oracles with shapes {wall:6.2f} s wall  {cpu:6.2f} s CPU   goal < 10 s")

        import argparse as _argparse

        config = build_config(_argparse.Namespace(dataset=args.redwood75, method=specs, out=str(tmp / "out2")))
        holder = {}
        wall, cpu = best(lambda: holder.update(e=evaluate_dataset(config, progress=False)), args.repeat)
        print(f"  evaluate_dataset (every metric)           {wall:6.2f} s wall  {cpu:6.2f} s CPU")
        evaluation = holder["e"]
        wall, cpu = best(lambda: write_outputs(config.out, dataset.name, evaluation.results, dataset.categories, evaluation.notes), args.repeat)
        print(f"  write_outputs (tables, JSON, both plots)  {wall:6.2f} s wall  {cpu:6.2f} s CPU")

        # the NOCS share: matching and AP of the 3 methods (errors of the own pairs reused), and the NOCS plot
        from evaluate.methods import get_method

        truth = nocs_ground_truth(dataset)
        predicted = []
        for spec in specs:
            method = get_method(spec, {}, dataset.samples[0].camera, dataset)
            rows = []
            for s in dataset:
                p = method.predict(s, None)
                rows.append((p.position, p.orientation, p.extents, None, p.score, p.category))
            predicted.append((rows, score_method(dataset, rows, [None] * len(dataset), config.fscore_threshold)))
        wall, cpu = best(lambda: [nocs_map_of_method(truth, rows, errors) for rows, errors in predicted], args.repeat)
        print(f"    of which NOCS mAP, 3 methods            {wall:6.3f} s wall  {cpu:6.3f} s CPU")
        wall, cpu = best(lambda: write_nocs_png(tmp / "nocs.png", dataset.name, evaluation.results), args.repeat)
        print(f"    of which the NOCS plot                  {wall:6.3f} s wall  {cpu:6.3f} s CPU")
        for r in evaluation.results:
            print(f"    {r.name}: mAP IoU25/50/75 " + " ".join(f"{100 * v:.1f}" for v in r.nocs.mean(r.nocs.iou_ap))
                  + ", 5°2cm 5°5cm 10°2cm 10°5cm " + " ".join(f"{100 * v:.1f}" for v in r.nocs.mean(r.nocs.pose_ap)))

    from evaluate.metrics.nocs_map import candidate_pairs

    data = real275_scale(args.scale, args.seed)
    pairs = candidate_pairs(data["gt_image"], data["gt_category"], data["det_image"], data["det_category"])
    symmetric = int(data["gt_symmetric"][pairs.gt].sum())
    holder = {}
    wall, cpu = best(lambda: holder.update(r=nocs_map(**data)), max(1, args.repeat - 1))
    r = holder["r"]
    print(f"REAL275-like: {args.scale} images, {len(data['gt_image'])} objects, {len(data['det_image'])} detections, "
          f"{len(pairs.det)} pairs ({symmetric} with symmetric truth)")
    print(f"  nocs_map from scratch (exact IoUs)        {wall:6.2f} s wall  {cpu:6.2f} s CPU"
          f"   ({1000 * cpu / max(symmetric, 1):.1f} ms CPU per symmetric pair; mAP IoU50 {100 * r.mean(r.iou_ap)[1]:.1f}, 10°5cm {100 * r.mean(r.pose_ap)[3]:.1f})")


if __name__ == "__main__":
    main()
