"""Refine's basin: how often the browser tool's refine brings a box that is up to 10 deg / 2 cm off onto the truth.

    .venv/bin/python benchmarks/bench_refine.py [--engines chains graph] [--trials 12] [--only NAME ...] [--data DIR]

On the bundled sample and a few suite sequences (benchmarks/suite.yaml, built into DIR once): the truth in some frames
(the other posed frames a refine fits to: every 10th frame, or 3 evenly spread ones as an annotator's first boxes),
then in ``--trials`` other frames the true box turned about a random axis by up to 10 deg and moved in a random
direction by up to 2 cm (both uniform), and refined as the page does (annotate.app_refine: the engine's refine_frame
with the panel's configuration; a result the panel declines leaves the box where it was). Per sequence, engine and
setting: the share converged (within 2 deg and 5 mm of the truth; symmetry y ignores the turn about y), the share the
panel declined with a reason, the share taken but not converged (and of all, the share taken, not converged and further
from the truth than the start in rotation or centre), the median errors before and after, and the median refine time
(ms, this process, Open3D on one thread).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from annotate.app_refine import engine_config, judge_refine  # noqa: E402
from annotate.engines import tracking_engine  # noqa: E402
from benchmarks.suite.run import manual_frames  # noqa: E402
from benchmarks.suite.spec import build, load_suite  # noqa: E402
from evaluate.metrics.pose_errors import rotation_error, translation_error  # noqa: E402
from sequences.annotation import Annotation, FramePose  # noqa: E402
from sequences.reader import open_sequence  # noqa: E402
from sequences.sample import cache_dir, sample_sequence  # noqa: E402
from sequences.truth import open_truth  # noqa: E402

#: The suite's sequences refined by default: a mug with its handle, a can (symmetry y), a box, a bowl (symmetry y).
SEQUENCES = ("dev-mug-pattern", "dev-nocs-can-tall", "dev-ycb-cracker-box", "dev-nocs-bowl-blue")
#: How far a box starts off at most (deg, m), and what counts as converged (deg, m).
START_DEG, START_M = 10.0, 0.02
CONVERGED_DEG, CONVERGED_M = 2.0, 0.005
#: The posed frames a refine fits to: the truth in every 10th frame, or in 3 frames spread as an annotator's first boxes.
SETTINGS = ("every10", "boxes3")


def posed_frames(ids: list[str], setting: str) -> list[str]:
    return ids[::10] if setting == "every10" else manual_frames(ids, 3)


def perturbed(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The true pose turned about a random axis by up to START_DEG and moved in a random direction by up to START_M."""
    out = T.copy()
    axis = rng.normal(size=3)
    out[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(START_DEG) * rng.uniform()).as_matrix() @ T[:3, :3]
    direction = rng.normal(size=3)
    out[:3, 3] += direction / np.linalg.norm(direction) * START_M * rng.uniform()
    return out


def errors(T: np.ndarray, truth: np.ndarray, symmetry: str) -> tuple[float, float]:
    return float(rotation_error(truth[:3, :3], T[:3, :3], symmetry)), float(translation_error(truth[:3, 3], T[:3, 3]))


def bench(root: Path, engine_name: str, setting: str, trials: int, seed: int = 0) -> dict:
    """The figures of one sequence, engine and setting (see the module's docstring)."""
    sequence, truth = open_sequence(root), open_truth(root)
    ids = [f for f in sequence.ids if f in truth.poses]
    base = Annotation(root.name, truth.category, truth.symmetry, np.asarray(truth.extents, float))
    for frame_id in posed_frames(ids, setting):
        base.frames[frame_id] = FramePose.from_matrix(truth.poses[frame_id], "manual")
    free = [f for f in ids if f not in base.frames]
    chosen = [free[i] for i in np.unique(np.linspace(0, len(free) - 1, trials).round().astype(int))]
    engine = tracking_engine(engine_name)
    config = engine_config(engine)
    rng = np.random.default_rng(seed)
    rows = []
    for frame_id in chosen:  # one refine each: the quantity measured
        start = perturbed(truth.poses[frame_id], rng)
        document = base.copy()
        document.frames[frame_id] = FramePose.from_matrix(start, "manual")
        t0 = time.perf_counter()
        result = engine.refine_frame(sequence, document, frame_id, config)
        seconds = time.perf_counter() - t0
        verdict = judge_refine(result, config)
        final = result.matrix if verdict.ok else start
        before = errors(start, truth.poses[frame_id], truth.symmetry)
        after = errors(final, truth.poses[frame_id], truth.symmetry)
        rows.append((verdict.ok, before, after, seconds))
    ok = np.array([r[0] for r in rows])
    after = np.array([r[2] for r in rows])
    converged = (after[:, 0] <= CONVERGED_DEG) & (after[:, 1] <= CONVERGED_M)
    before = np.array([r[1] for r in rows])
    worse = ok & ~converged & ((after[:, 0] > before[:, 0]) | (after[:, 1] > before[:, 1]))
    return {"n": len(rows), "converged": float(converged.mean()), "declined": float((~ok).mean()), "taken_wrong": float((ok & ~converged).mean()),
            "taken_worse": float(worse.mean()),
            "before_deg": float(np.median(before[:, 0])), "before_mm": float(np.median(before[:, 1]) * 1000),
            "after_deg": float(np.median(after[:, 0])), "after_mm": float(np.median(after[:, 1]) * 1000),
            "ms": float(np.median([r[3] for r in rows]) * 1000), "converged_flags": converged.tolist()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--engines", nargs="+", default=["chains", "graph"])
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=SETTINGS)
    parser.add_argument("--trials", type=int, default=12)
    parser.add_argument("--only", nargs="+", help="suite sequences (default: %s); 'sample' for the bundled sample" % ", ".join(SEQUENCES))
    parser.add_argument("--data", default=str(cache_dir() / "suite"), help="cache of generated suite sequences")
    args = parser.parse_args()
    suite = load_suite()
    names = args.only or ["sample", *SEQUENCES]
    roots = {}
    for name in names:
        if name == "sample":
            roots[name] = Path(sample_sequence())
        else:
            entry = next(e for e in suite.entries if e.name == name)
            roots[name] = build(entry, suite.frames, Path(args.data))
    print(f"refine from up to {START_DEG:.0f} deg / {START_M * 1000:.0f} mm off; converged: within {CONVERGED_DEG:.0f} deg and "
          f"{CONVERGED_M * 1000:.0f} mm; {args.trials} frames per row; load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    header = f"{'sequence':24s} {'engine':7s} {'posed':8s} {'converged':>9s} {'declined':>8s} {'taken wrong':>11s} {'before deg/mm':>14s} {'after deg/mm':>13s} {'ms':>6s}"
    print(header)
    totals: dict[tuple[str, str], list] = {}
    for name, root in roots.items():
        for engine in args.engines:
            for setting in args.settings:
                row = bench(root, engine, setting, args.trials)
                totals.setdefault((engine, setting), []).append(row)
                print(f"{name:24s} {engine:7s} {setting:8s} {row['converged']:9.0%} {row['declined']:8.0%} {row['taken_wrong']:11.0%} "
                      f"{row['before_deg']:6.1f} /{row['before_mm']:5.1f} {row['after_deg']:6.2f} /{row['after_mm']:5.1f} {row['ms']:6.0f}", flush=True)
    print("all sequences:")
    for (engine, setting), rows in totals.items():
        flags = [c for r in rows for c in r["converged_flags"]]
        declined = np.average([r["declined"] for r in rows], weights=[r["n"] for r in rows])
        wrong = np.average([r["taken_wrong"] for r in rows], weights=[r["n"] for r in rows])
        worse = np.average([r["taken_worse"] for r in rows], weights=[r["n"] for r in rows])
        print(f"  {engine:7s} {setting:8s} converged {np.mean(flags):.0%} of {len(flags)}, declined {declined:.0%}, taken wrong {wrong:.0%} "
              f"(worse than the start in rotation or centre: {worse:.0%}), "
              f"median refine {np.median([r['ms'] for r in rows]):.0f} ms (median of the rows' medians)")


if __name__ == "__main__":
    main()
