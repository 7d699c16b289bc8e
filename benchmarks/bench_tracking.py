"""Tracking benchmark (issue 5): accuracy and speed on synthetic sequences of every category.

    .venv/bin/python benchmarks/bench_tracking.py [--data DIR] [--seed 0 [1 2 3]] [--categories mug can ...] [--frames 100]
        [--manual 4] [--manual-error 3 0.005 0.08] [--backends point_to_plane kiss ...] [--compare-on mug can] [--reconstruct] [--json OUT]
        [--poses DIR] [--compare-poses DIR] [--profile N] [--placement-sigma 1 2] [--no-facing]

For each category: a synthetic sequence (sequences.synth, cached in DIR), manual frames = the
truth perturbed by up to 3 deg / 5 mm with extents off by up to 8% (synth.truth_annotation),
then ``track_sequence``. Prints per category: median and 90th percentile rotation error
(symmetry-aware: the angle between y axes for symmetry y), median box-centre error, frames
flagged, frames off by > 10 deg without a flag, and time per frame (wall and CPU), with the
machine's load. ``--backends`` compares registration backends on the ``--compare-on``
categories. ``--reconstruct`` adds reconstruct-sequence's posed mesh against the posed true mesh,
frame by frame: median F-score at 5 mm. Goals: median <= 1.5 deg, p90 <= 3 deg, centre <= 3 mm,
no unflagged frame > 10 deg, <= 150 ms per frame on 2 cores, F-score >= 0.85.

Tracking runs Open3D on one thread (``TrackingConfig.threads``), so a run's figures repeat
exactly, and its independent work (the chains, the joint refinement's registrations, the rechecks, the
slides) on as many processes as there are cores, up to 4 (``TrackingConfig.workers``; the poses are the
same for any count). The wall column is the issue's time per frame on 2 cores; the CPU column adds up
all processes (more than the wall time on several cores). On a shared machine the wall column follows
the load; compare the CPU column between runs, and time the wall column alone. The CPU
column follows the load too, less: on the 2-core test machine the same laptop run (seed 0, same
poses) took 159 ms CPU per frame at load 1 and 177-179 at load 4-6 (bowl seed 0: 74 vs 95), so
compare speed only between runs at a similar load.

A speed change should leave the poses as they are: ``--poses DIR`` writes every frame's pose
and flag (exact floats), and a later run with ``--compare-poses DIR`` reports how many frames
changed and by how much. The chains amplify rounding: reversing the order of a frame's points
before ICP alone (the same sums, in another order) moved v5 laptop seed 1's median centre error
from 24.7 to 10.1 mm and seed 0's p90 rotation error from 7.0 to 2.8 deg, so a change that moves
poses at all is judged on all categories and seeds, pooled, not on one sequence's figures.
``--placement-sigma DEG MM`` sets the tracker's placement sigma (as ``annotate --track`` does) (with 3 manual frames off by up to 5 deg, v5 seeds 0+1: 1.7 deg 2.9 mm brings the figures back to within 3% of the links-only code; the default 1 deg 2 mm is 11% worse in the rot median sum). ``--manual-error 0 0 0`` places the manual frames at the truth, which separates the tracker's own
errors from the placed boxes' (measured, rot median/p90 deg, centre mm, exact vs issue's anchors: camera
seed 0 0.34/0.96, 0.93 vs 1.41/2.24, 3.04; camera seed 1 1.05/2.04, 5.96 vs 1.84/2.37, 2.21; bowl seed 1
1.71/3.76, 2.94 vs 1.53/2.46, 2.45).
``--repeat N`` tracks each sequence N times in a row and reports the medians of their times (the poses must
repeat exactly, and are checked to): on the 2-core machine of 2026-11-28 the same laptop run took 134-235 ms per frame
within the hour. The last line judges the speed goal on the slowest sequence.
``--profile N`` prints the N tracking entries with the most cumulative time (cProfile, on one process; its
overhead inflates the timing columns of that run). The
F-score also measures reconstruct-sequence itself: with every frame at its true pose it is
the reconstruction's own ceiling. Both meshes are sampled at most half the threshold apart
(:func:`surface_samples`): with a fixed 5000 points the v5 laptop scored 0.69-0.83 against
itself at 5 mm, which capped its tracked score at ~0.8 whatever the poses.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from annotate.tracking import BACKENDS, TrackingConfig, track_sequence  # noqa: E402
from annotate.tracking.quality import pose_difference  # noqa: E402
from sequences.reader import open_sequence  # noqa: E402
from sequences.synth import generate_sequence, load_truth, truth_annotation  # noqa: E402

CATEGORIES = ("bottle", "bowl", "mug", "can", "camera", "laptop")


def sequence_for(data: Path, category: str, frames: int, seed: int) -> Path:
    root = data / f"{category}-{frames}-s{seed}"
    if not (root / "truth" / "truth.json").exists():
        print(f"  generating {root} ...", flush=True)
        generate_sequence(root, category, frames=frames, seed=seed)
    return root


def manual_frames(ids: list[str], count: int) -> list[str]:
    """Evenly spread manual frames, a few frames in from both ends (as an annotator would pick)."""
    n = len(ids)
    return [ids[i] for i in np.linspace(min(3, n - 1), max(n - 4, 0), count).round().astype(int)]


#: The issue's manual frames: off by up to 3 deg, 5 mm and 8% of the extents.
MANUAL_ERROR = (3.0, 0.005, 0.08)

#: the issue's speed goal: wall time per frame on 2 cores (ms)
SPEED_GOAL_MS = 150.0


def _cpu_seconds() -> float:
    """CPU seconds of this process and of its finished children (the tracker's worker processes: workers.py)."""
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


def run_one(root: Path, backend: str, manual: int, seed: int, profile: int = 0,
            manual_error: tuple[float, float, float] = MANUAL_ERROR, placement_sigma: tuple[float, float] | None = None,
            facing: bool = True) -> tuple[dict, object, object]:
    truth = load_truth(root)
    sequence = open_sequence(root)
    deg, metres, share = manual_error
    annotation = truth_annotation(truth, manual_frames(sequence.ids, manual), rotation_deg=deg, translation_m=metres, extents_rel=share, seed=seed)
    profiler = cProfile.Profile() if profile > 0 else None
    load_before = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), _cpu_seconds()
    if profiler is not None:
        profiler.enable()
    # a profile sees this process only: all the work in it, on one process
    config = TrackingConfig(backend=backend, workers=1 if profiler is not None else 0)
    if placement_sigma is not None:
        config.manual_rotation_sigma_deg, config.manual_translation_sigma = placement_sigma
    config.registration.facing = facing
    tracked = track_sequence(sequence, annotation, config=config)
    if profiler is not None:
        profiler.disable()
    wall, cpu = time.perf_counter() - wall, _cpu_seconds() - cpu
    if profiler is not None:
        print(profile_summary(profiler, profile), flush=True)
    symmetric = truth.symmetry == "y"
    ids = sequence.ids
    errors = np.array([pose_difference(tracked.frames[f].matrix, truth.poses[f], symmetric) for f in ids])
    flagged = np.array([bool(tracked.frames[f].extra.get("flagged")) for f in ids])
    row = {
        "category": truth.category,
        "backend": backend,
        "frames": len(ids),
        "rot_median_deg": float(np.median(errors[:, 0])),
        "rot_p90_deg": float(np.percentile(errors[:, 0], 90)),
        "centre_median_mm": float(np.median(errors[:, 1]) * 1000),
        "flagged": int(flagged.sum()),
        "unflagged_over_10deg": int(np.sum((errors[:, 0] > 10) & ~flagged)),
        "ms_per_frame_wall": 1000 * wall / len(ids),
        "ms_per_frame_cpu": 1000 * cpu / len(ids),
        "load_1min": float(np.mean([load_before, os.getloadavg()[0]])),
    }
    return row, tracked, truth


def repeated_timing(rows: list[dict]) -> dict:
    """The time columns of one sequence tracked several times: the medians of the runs' wall and CPU ms per frame, and
    the runs' wall figures (the median resists a run that a busy moment of a shared machine slowed)."""
    walls = [r["ms_per_frame_wall"] for r in rows]
    return {"ms_per_frame_wall": float(np.median(walls)), "ms_per_frame_cpu": float(np.median([r["ms_per_frame_cpu"] for r in rows])),
            "ms_per_frame_wall_runs": walls}


def speed_summary(rows: list[dict], repeat: int = 1, goal_ms: float = SPEED_GOAL_MS) -> str:
    """One line on the speed goal: the slowest sequence's wall time per frame (its median over ``repeat`` runs)."""
    if not rows:
        return "speed: no sequence run"
    slowest = max(rows, key=lambda r: r["ms_per_frame_wall"])
    over = [r for r in rows if r["ms_per_frame_wall"] > goal_ms]
    runs = f" (medians of {repeat} runs)" if repeat > 1 else " (one run each; --repeat N for medians)"
    return (f"speed goal (<= {goal_ms:.0f} ms per frame, wall, on {os.cpu_count()} cores){runs}: met on {len(rows) - len(over)} of {len(rows)} "
            f"sequences; slowest {slowest['category']} seed {slowest.get('seed', '?')} at {slowest['ms_per_frame_wall']:.0f} ms per frame")


def profile_summary(profiler: cProfile.Profile, count: int) -> str:
    """The ``count`` entries of the tracking package and of Open3D with the most cumulative time."""
    out = io.StringIO()
    pstats.Stats(profiler, stream=out).sort_stats("cumulative").print_stats(r"annotate/tracking|open3d", count)
    lines = out.getvalue().splitlines()
    start = next((i for i, line in enumerate(lines) if line.lstrip().startswith("ncalls")), 0)
    return "\n".join(lines[start:]).rstrip()


def pose_record(tracked, ids: list[str]) -> dict:
    """Every frame's 4x4 pose (exact floats) and flag, for comparing two runs frame by frame."""
    return {
        "frames": list(ids),
        "poses": [np.asarray(tracked.frames[f].matrix, dtype=float).ravel().tolist() for f in ids],
        "flagged": [bool(tracked.frames[f].extra.get("flagged")) for f in ids],
    }


def pose_changes(before: dict, after: dict, symmetric: bool) -> dict:
    """How two runs' poses differ: frames whose pose changed at all, the largest change (deg, mm), flags that changed."""
    if before["frames"] != after["frames"]:
        raise ValueError("the two runs cover different frames")
    a = np.asarray(before["poses"], dtype=float).reshape(-1, 4, 4)
    b = np.asarray(after["poses"], dtype=float).reshape(-1, 4, 4)
    Ra, Rb = a[:, :3, :3], b[:, :3, :3]
    # angles by atan2 (sine and cosine both measured): accurate at 1e-9 deg, where arccos reads 1e-6 deg
    if symmetric:  # the angle between the y axes
        ya, yb = Ra[:, :, 1], Rb[:, :, 1]
        deg = np.degrees(np.arctan2(np.linalg.norm(np.cross(ya, yb), axis=1), np.einsum("ni,ni->n", ya, yb)))
    else:
        D = np.einsum("nji,njk->nik", Ra, Rb)
        sine = np.linalg.norm(D - D.transpose(0, 2, 1), axis=(1, 2)) / (2 * np.sqrt(2))
        deg = np.degrees(np.arctan2(sine, (np.trace(D, axis1=1, axis2=2) - 1) / 2))
    mm = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1) * 1000
    return {
        "frames_changed": int(np.sum(np.any(a != b, axis=(1, 2)))),
        "max_change_deg": float(deg.max(initial=0.0)),
        "max_change_mm": float(mm.max(initial=0.0)),
        "flags_changed": int(np.sum(np.asarray(before["flagged"]) != np.asarray(after["flagged"]))),
    }


def surface_samples(mesh, threshold: float, minimum: int = 5000) -> int:
    """Points to sample on ``mesh`` so that their spacing is at most half the F-score threshold.

    Two independent samplings of one surface agree only to about their spacing: the v5 laptop (3456 cm^2)
    sampled with 5000 points (6 mm apart) scores F@5mm 0.83 against itself, with 20,000 or more 1.000.
    """
    return max(minimum, int(np.ceil(mesh.area / (threshold / 2) ** 2)))


def reconstruction_fscore(root: Path, tracked, truth, threshold: float = 0.005) -> float:
    """Median over frames of the F-score at ``threshold`` between the posed reconstructed and posed true meshes.

    Computed in the true object frame (distances are the same as between the posed meshes in the camera
    frame): the true mesh's samples are indexed once, the reconstruction's are mapped by T_true^-1 T_tracked.
    """
    from evaluate.metrics.sampling import ShapeIndex, sample_surface
    from reconstruct.pipeline import reconstruct_sequence

    recon = reconstruct_sequence(open_sequence(root), tracked, voxel_size=0.002)
    recon_points = sample_surface(recon.mesh, surface_samples(recon.mesh, threshold), seed=0)
    true_index = ShapeIndex.from_mesh(truth.mesh, n=surface_samples(truth.mesh, threshold), seed=0)
    true_index.prepare(threshold)
    scores = []
    for frame_id, pose in recon.poses.items():
        if frame_id not in truth.poses:
            continue
        to_true = np.linalg.inv(truth.poses[frame_id]) @ pose  # tracked object frame -> true object frame
        scores.append(true_index.fscore(recon_points @ to_true[:3, :3].T + to_true[:3, 3], threshold).fscore)
    return float(np.median(scores))


#: the issue's goals per sequence: (row key, limit, True when the figure must stay at or below it)
GOALS = (("rot_median_deg", 1.5, True), ("rot_p90_deg", 3.0, True), ("centre_median_mm", 3.0, True),
         ("unflagged_over_10deg", 0, True), ("fscore_5mm_median", 0.85, False))


def goal_failures(row: dict) -> list[str]:
    """The goals one benchmark row misses, as "key value" strings (a figure not measured is not judged)."""
    from suite.run import missed_goals

    return missed_goals(row, GOALS)


def pooled_summary(rows: list[dict]) -> str:
    """Per category over its rows (one per seed): the mean rotation median, the mean and worst p90 (deg),
    the mean centre error (mm), frames flagged and unflagged > 10 deg in all, and the goal checks that
    fail; then the sums over all rows, the figures to compare two versions of the tracker by."""
    lines = [f"pooled over seeds {sorted({r['seed'] for r in rows})}:",
             f"{'category':8s} {'seqs':>4s} {'rot med':>7s} {'p90':>6s} {'worst':>6s} {'ctr mm':>6s} {'flagged':>7s} {'bad>10':>6s} {'fails':>5s}"]
    for category in dict.fromkeys(r["category"] for r in rows):
        mine = [r for r in rows if r["category"] == category]
        lines.append(f"{category:8s} {len(mine):4d} {np.mean([r['rot_median_deg'] for r in mine]):7.2f} {np.mean([r['rot_p90_deg'] for r in mine]):6.2f} "
                     f"{max(r['rot_p90_deg'] for r in mine):6.2f} {np.mean([r['centre_median_mm'] for r in mine]):6.2f} {sum(r['flagged'] for r in mine):7d} "
                     f"{sum(r['unflagged_over_10deg'] for r in mine):6d} {sum(len(goal_failures(r)) for r in mine):5d}")
    lines.append(f"sums over {len(rows)} sequences: rot median {sum(r['rot_median_deg'] for r in rows):.2f}, p90 {sum(r['rot_p90_deg'] for r in rows):.2f} deg, "
                 f"centre {sum(r['centre_median_mm'] for r in rows):.2f} mm, flagged {sum(r['flagged'] for r in rows)}, "
                 f"unflagged > 10 deg {sum(r['unflagged_over_10deg'] for r in rows)}, goal checks failing {sum(len(goal_failures(r)) for r in rows)}")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=os.environ.get("BENCH_DATA", "/tmp/redwood-gt-bench"), help="cache of generated sequences")
    parser.add_argument("--categories", nargs="+", default=list(CATEGORIES))
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--seed", type=int, nargs="+", default=[0], help="one or more seeds; with several, a pooled summary "
                        "per category follows (single sequences' figures are partly chance: see above)")
    parser.add_argument("--manual", type=int, default=4, help="manual frames per sequence (3 or 4)")
    parser.add_argument("--manual-error", type=float, nargs=3, default=list(MANUAL_ERROR), metavar=("DEG", "M", "SHARE"),
                        help="how far the manual frames are off at most: rotation (deg), translation (m), extents (share); "
                             "0 0 0 separates the tracker's own errors from the placed boxes'")
    parser.add_argument("--no-facing", dest="facing", action="store_false", help="let points pair with model surfaces facing away from the camera too (annotate --track --no-facing)")
    parser.add_argument("--placement-sigma", type=float, nargs=2, metavar=("DEG", "MM"),
                        help="the tracker's placement sigma per axis (TrackingConfig.manual_rotation_sigma_deg, manual_translation_sigma; "
                             "default 1 deg, 2 mm: the issue's 3 deg / 5 mm placements)")
    parser.add_argument("--backends", nargs="*", default=[], help=f"also compare these backends ({', '.join(BACKENDS)})")
    parser.add_argument("--compare-on", nargs="+", default=["mug", "can"], help="categories for the backend comparison")
    parser.add_argument("--reconstruct", action="store_true", help="also run reconstruct-sequence and its F-score at 5 mm")
    parser.add_argument("--json", help="write the rows as JSON here")
    parser.add_argument("--poses", help="write every frame's pose and flag here (one JSON per category, seed and backend)")
    parser.add_argument("--compare-poses", help="compare every frame's pose with a run written by --poses to this folder")
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="print the N tracking entries with the most cumulative time (cProfile)")
    parser.add_argument("--repeat", type=int, default=1, metavar="N", help="track each sequence N times in a row: the time columns are "
                        "the medians of the N runs (their range printed), and the poses must repeat exactly (a shared machine's speed "
                        "drifts: one run's time is partly chance)")
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error("--repeat must be 1 or more")
    if args.placement_sigma is not None and not min(args.placement_sigma) > 0:
        parser.error("--placement-sigma must be two positive numbers (deg, mm)")
    data = Path(args.data)
    data.mkdir(parents=True, exist_ok=True)
    default = TrackingConfig().backend
    rows = []
    print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()}")
    header = f"{'category':8s} {'seed':>4s} {'backend':15s} {'rot med':>7s} {'rot p90':>7s} {'ctr mm':>7s} {'flagged':>7s} {'bad>10':>6s} {'ms/f':>6s} {'cpu ms/f':>8s} {'load':>5s}"
    print(header)
    for seed, category in [(seed, category) for seed in args.seed for category in args.categories]:
        root = sequence_for(data, category, args.frames, seed)
        backends = [default] + ([b for b in args.backends if b != default] if category in args.compare_on else [])
        for backend in backends:
            runs = [run_one(root, backend, args.manual, seed, args.profile, tuple(args.manual_error),
                            (args.placement_sigma[0], args.placement_sigma[1] / 1000) if args.placement_sigma else None, args.facing)
                    for _ in range(args.repeat)]
            row, tracked, truth = runs[0]
            ids = open_sequence(root).ids
            record = pose_record(tracked, ids)
            if args.repeat > 1:
                row.update(repeated_timing([r[0] for r in runs]))
                row["repeats_identical"] = all(pose_record(r[1], ids) == record for r in runs[1:])
            if args.poses or args.compare_poses:
                name = f"{category}-s{seed}-{backend}.json"
                if args.poses:
                    Path(args.poses).mkdir(parents=True, exist_ok=True)
                    (Path(args.poses) / name).write_text(json.dumps(record))
                if args.compare_poses:
                    previous = Path(args.compare_poses) / name
                    row.update(pose_changes(json.loads(previous.read_text()), record, truth.symmetry == "y") if previous.exists() else {"frames_changed": None})
            if args.reconstruct and backend == default:
                try:
                    row["fscore_5mm_median"] = reconstruction_fscore(root, tracked, truth)
                except Exception as error:  # the reconstruct step is another part: report, don't stop the benchmark
                    row["fscore_5mm_median"] = None
                    row["reconstruct_error"] = f"{error.__class__.__name__}: {error}"
            row["seed"] = seed
            rows.append(row)
            extra = f"  F@5mm {row['fscore_5mm_median']:.3f}" if row.get("fscore_5mm_median") is not None else ""
            if row.get("frames_changed") is not None:
                extra += f"  poses changed in {row['frames_changed']} frames (max {row['max_change_deg']:.3g} deg, {row['max_change_mm']:.3g} mm; {row['flags_changed']} flags)"
            elif args.compare_poses:
                extra += "  (no earlier poses to compare)"
            if args.repeat > 1:
                walls = row["ms_per_frame_wall_runs"]
                extra += f"  wall {min(walls):.0f}-{max(walls):.0f} ms/f over {len(walls)} runs" + ("" if row["repeats_identical"] else "  POSES DIFFER BETWEEN RUNS")
            print(
                f"{row['category']:8s} {seed:4d} {backend:15s} {row['rot_median_deg']:7.2f} {row['rot_p90_deg']:7.2f} {row['centre_median_mm']:7.2f} "
                f"{row['flagged']:7d} {row['unflagged_over_10deg']:6d} {row['ms_per_frame_wall']:6.0f} {row['ms_per_frame_cpu']:8.0f} {row['load_1min']:5.1f}{extra}",
                flush=True,
            )
    ok = [r for r in rows if r["backend"] == default]
    if len(args.seed) > 1:
        print(pooled_summary(ok))
    failures = sum(len(goal_failures(r)) for r in ok)
    print(f"goals (median <= 1.5 deg, p90 <= 3 deg, centre <= 3 mm, no unflagged > 10 deg, F@5mm >= 0.85 where measured) "
          f"met by the default backend on every sequence: {failures == 0} ({failures} of the checks fail)")
    print(speed_summary(ok, args.repeat))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
