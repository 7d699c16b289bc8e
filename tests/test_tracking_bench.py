"""bench_tracking's frame-by-frame pose comparison: against poses changed by known amounts."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_tracking import pose_changes, repeated_timing, speed_summary, surface_samples  # noqa: E402


def _record(poses: list[np.ndarray], flagged: list[bool]) -> dict:
    return {"frames": [f"{i:06d}" for i in range(len(poses))], "poses": [p.ravel().tolist() for p in poses], "flagged": flagged}


def test_pose_changes_counts_frames_and_measures_the_largest_change():
    rng = np.random.default_rng(0)
    poses = []
    for _ in range(5):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        T[:3, 3] = rng.normal(size=3) * 0.1 + [0, 0, 0.6]
        poses.append(T)
    moved = [p.copy() for p in poses]
    moved[1][:3, :3] = moved[1][:3, :3] @ Rotation.from_rotvec([0, 0, np.radians(2.0)]).as_matrix()  # 2 deg about the box's z
    moved[3][:3, 3] += [0.003, 0.0, 0.004]  # 5 mm
    moved[4][0, 3] = np.nextafter(moved[4][0, 3], 1.0)  # one ulp: changed, by nothing measurable
    same = pose_changes(_record(poses, [False] * 5), _record(poses, [False] * 5), symmetric=False)
    assert same["frames_changed"] == 0 and same["flags_changed"] == 0 and same["max_change_mm"] == 0.0
    assert same["max_change_deg"] < 1e-9
    changes = pose_changes(_record(poses, [False] * 5), _record(moved, [False, True, False, False, False]), symmetric=False)
    assert changes["frames_changed"] == 3 and changes["flags_changed"] == 1
    assert abs(changes["max_change_deg"] - 2.0) < 1e-9
    assert abs(changes["max_change_mm"] - 5.0) < 1e-9
    # symmetric about y: a tilt of the y axis counts
    tilted = [p.copy() for p in poses]
    tilted[0][:3, :3] = tilted[0][:3, :3] @ Rotation.from_rotvec([np.radians(3.0), 0, 0]).as_matrix()
    assert abs(pose_changes(_record(poses, [False] * 5), _record(tilted, [False] * 5), symmetric=True)["max_change_deg"] - 3.0) < 1e-9
    # symmetric about y: a turn about the box's y axis is no change of the pose
    spun = [p.copy() for p in poses]
    spun[2][:3, :3] = spun[2][:3, :3] @ Rotation.from_rotvec([0, np.radians(40.0), 0]).as_matrix()
    assert pose_changes(_record(poses, [False] * 5), _record(spun, [False] * 5), symmetric=True)["max_change_deg"] < 1e-9


def test_surface_samples_are_dense_enough_for_a_large_flat_object_to_match_itself():
    """A laptop-sized slab scored against a second sampling of itself: 5000 points (about 7 mm apart)
    lose points at 5 mm; the density rule (at most half the threshold apart) scores 1."""
    import trimesh

    from evaluate.metrics.sampling import ShapeIndex, sample_surface

    slab = trimesh.creation.box([0.35, 0.02, 0.25])  # 2070 cm^2
    n = surface_samples(slab, 0.005)
    assert n == int(np.ceil(slab.area / 0.0025**2))
    assert ShapeIndex.from_mesh(slab, n=n, seed=0).fscore(sample_surface(slab, n, seed=1), 0.005).fscore == 1.0
    assert ShapeIndex.from_mesh(slab, n=5000, seed=0).fscore(sample_surface(slab, 5000, seed=1), 0.005).fscore < 0.95
    assert surface_samples(trimesh.creation.box([0.02, 0.02, 0.02]), 0.005) == 5000  # the floor for small objects


def test_goal_failures_and_the_pooled_summary_count_the_checks():
    from bench_tracking import goal_failures, pooled_summary

    good = {"category": "mug", "seed": 0, "rot_median_deg": 1.2, "rot_p90_deg": 2.9, "centre_median_mm": 2.0, "flagged": 3,
            "unflagged_over_10deg": 0}
    assert goal_failures(good) == []
    assert goal_failures(dict(good, fscore_5mm_median=0.9)) == []
    bad = dict(good, seed=1, rot_median_deg=1.6, rot_p90_deg=4.0, unflagged_over_10deg=2, fscore_5mm_median=0.5)
    assert [f.split()[0] for f in goal_failures(bad)] == ["rot_median_deg", "rot_p90_deg", "unflagged_over_10deg", "fscore_5mm_median"]
    assert goal_failures(dict(good, rot_p90_deg=3.0, centre_median_mm=3.0)) == []  # the limits themselves pass
    summary = pooled_summary([good, bad, dict(good, category="can", seed=0)])
    mug = next(line for line in summary.splitlines() if line.startswith("mug"))
    # 2 sequences, mean median 1.40, mean p90 3.45, worst 4.00, centre 2.00, 6 flagged, 2 unflagged, 4 checks failing
    assert mug.split() == ["mug", "2", "1.40", "3.45", "4.00", "2.00", "6", "2", "4"]
    assert summary.splitlines()[-1].endswith("goal checks failing 4")


def test_repeated_runs_report_the_median_time_and_the_speed_line_names_the_slowest_sequence():
    runs = [{"ms_per_frame_wall": w, "ms_per_frame_cpu": c} for w, c in ((210.0, 330.0), (140.0, 250.0), (150.0, 240.0))]
    timing = repeated_timing(runs)
    assert timing["ms_per_frame_wall"] == 150.0 and timing["ms_per_frame_cpu"] == 250.0
    assert timing["ms_per_frame_wall_runs"] == [210.0, 140.0, 150.0]
    rows = [{"category": "mug", "seed": 1, "ms_per_frame_wall": 90.0}, {"category": "laptop", "seed": 2, **timing},
            {"category": "laptop", "seed": 3, "ms_per_frame_wall": 151.0}]
    line = speed_summary(rows, repeat=3)
    assert "met on 2 of 3 sequences" in line and "slowest laptop seed 3 at 151 ms" in line and "medians of 3 runs" in line
    assert speed_summary([]) == "speed: no sequence run"
