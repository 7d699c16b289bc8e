"""Tracking alone, old engine against new, on a split of the suite (and the real frames): the A/B of the tracking issue.

    .venv/bin/python benchmarks/compare_engines.py --split dev [--engines chains graph] [--only NAME ...] [--settings boxes4]
    .venv/bin/python benchmarks/compare_engines.py --real

Per sequence and setting: rotation median and p90 (deg), centre median (mm), flagged share, unflagged frames more
than 5 deg or 10 mm off, ms per frame; and per category the medians. No reconstruction (run_suite.py does that).
Results are cached per engine and sequence in build/engines/ (the old engine does not change), ``--fresh`` reruns.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.suite.run import manual_frames  # noqa: E402
from benchmarks.suite.spec import build, load_suite  # noqa: E402
from evaluate.annotation_quality import pose_scores  # noqa: E402
from sequences.reader import open_sequence  # noqa: E402
from sequences.sample import cache_dir  # noqa: E402
from sequences.synth.truth import truth_annotation  # noqa: E402
from sequences.truth import open_truth  # noqa: E402

ENGINES = ("chains", "graph")
COLUMNS = (("rot_median_deg", "rot med°", "{:.2f}"), ("rot_p90_deg", "p90°", "{:.2f}"), ("centre_median_mm", "ctr mm", "{:.1f}"),
           ("flagged_share", "flagged", "{:.0%}"), ("unflagged_over_5deg", ">5° unfl.", "{:d}"), ("unflagged_over_10mm", ">10mm unfl.", "{:d}"),
           ("ms_per_frame", "ms/f", "{:.0f}"), ("cpu_ms_per_frame", "cpu ms/f", "{:.0f}"))


def tracker(engine: str):
    if engine == "chains":
        from annotate.tracking import track_sequence
    else:
        from annotate.estimator import track_sequence
    return track_sequence


def run(engine: str, root: Path, placed, truth) -> dict:
    start, cpu = time.perf_counter(), time.process_time()
    tracked = tracker(engine)(open_sequence(root), placed)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    poses = {f: p.matrix for f, p in tracked.frames.items()}
    flagged = {f: bool(p.extra.get("flagged")) for f, p in tracked.frames.items()}
    return {**pose_scores(poses, flagged, truth.poses, truth.symmetry), "ms_per_frame": 1000 * wall / len(poses),
            "cpu_ms_per_frame": 1000 * cpu / len(poses)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=("dev", "heldout"), default="dev")
    parser.add_argument("--only", nargs="+")
    parser.add_argument("--settings", nargs="+", default=["boxes4"])
    parser.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES))
    parser.add_argument("--data", default=str(cache_dir() / "suite"))
    parser.add_argument("--fresh", action="store_true", help="rerun cached results")
    args = parser.parse_args(argv)
    suite = load_suite()
    try:
        entries = suite.named(args.split, args.only)
    except ValueError as error:
        parser.error(str(error))
    cache = REPO / "build" / "engines"
    cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for entry in entries:
        root = build(entry, suite.frames, Path(args.data))
        truth = open_truth(root)
        sequence = open_sequence(root)
        for setting in (s for s in suite.settings if s.name in args.settings):
            placed = truth_annotation(truth, manual_frames(sequence.ids, setting.boxes), setting.degrees, setting.metres, setting.extents, seed=entry.seed)
            for engine in args.engines:
                stored = cache / f"{engine}-{root.name}-{setting.name}.json"
                if stored.is_file() and not args.fresh and engine == "chains":
                    row = json.loads(stored.read_text())
                else:
                    row = {"sequence": entry.name, "category": entry.category, "setting": setting.name, "engine": engine, **run(engine, root, placed, truth)}
                    stored.write_text(json.dumps(row))
                rows.append(row)
                print(" | ".join([f"{entry.name:24s}", setting.name, f"{engine:6s}"] + [fmt.format(row.get(key, np.nan)) if fmt != "{:d}" else fmt.format(row[key]) for key, _, fmt in COLUMNS]), flush=True)
    print()
    print("| category | setting | engine | seqs | " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("|" + "---|" * (4 + len(COLUMNS)))
    for category in sorted({r["category"] for r in rows}) + ["all"]:
        for setting in args.settings:
            for engine in args.engines:
                chosen = [r for r in rows if r["engine"] == engine and r["setting"] == setting and category in (r["category"], "all")]
                if not chosen:
                    continue
                cells = []
                for key, _, fmt in COLUMNS:
                    values = [r.get(key, np.nan) for r in chosen]
                    value = int(np.sum(values)) if fmt == "{:d}" else float(np.median(values))
                    cells.append(fmt.format(value))
                print(f"| {category} | {setting} | {engine} | {len(chosen)} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
