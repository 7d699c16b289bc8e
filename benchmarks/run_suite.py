"""Run the benchmark suite (benchmarks/suite.yaml) on one split and print and write its tables.

    .venv/bin/python benchmarks/run_suite.py --split dev|heldout [--quick] [--only NAME ...] [--settings boxes4 boxes3]
        [--data DIR] [--out DIR] [--shared DIR] [--workers N] [--surface carving|tsdf]

Generates each sequence once into DIR (default ``$REDWOOD_GT_CACHE/suite``, else ``~/.cache/redwood-gt/suite``),
then per sequence: reconstructs from the true poses; and per setting places its boxes (4 off by up to 3 deg / 5 mm /
8 %, 3 off by up to 5 deg), tracks every frame, reconstructs, and scores poses, flags, the posed mesh, the shape
(overall and on the observed surface), the extents and the time per frame (see benchmarks/suite/run.py).
Writes OUT/results.json and OUT/README.md (default ``build/suite/<split>``): a table per sequence and per category.

``--quick`` runs the split's quick subset at the suite's quick frame count with the boxes4 setting only (under
5 minutes on 2 cores once its sequences are generated). Tune on dev; run heldout only to report.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))

from sequences.errors import run_cli  # noqa: E402
from annotate.engines import ENGINES  # noqa: E402
from reconstruct.pipeline import SURFACES  # noqa: E402
from sequences.sample import cache_dir  # noqa: E402
from suite.run import category_table, run_sequence, sequence_table  # noqa: E402
from suite.spec import SHARED, SPLITS, SUITE, Setting, build, load_suite  # noqa: E402


def markdown(split: str, quick: bool, sequences: int, frames: int, settings, rows: list[dict]) -> str:
    """The run's Markdown: the settings, a table per category and one per sequence."""
    described = "".join(f", {s.name} ({s.boxes} boxes off by up to {s.degrees:g} deg / {1000 * s.metres:g} mm / {100 * s.extents:g} %)" for s in settings)
    return (f"# Benchmark suite, {split} split{' (quick)' if quick else ''}\n\n{sequences} sequences of {frames} frames; settings: truth "
            f"(reconstruction from the true poses){described}.\n\n## Per category (medians; counts summed)\n\n{category_table(rows)}\n\n"
            f"## Per sequence\n\n{sequence_table(rows)}\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=SPLITS, required=True)
    parser.add_argument("--quick", action="store_true", help="the split's quick subset, fewer frames, boxes4 only")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="these sequences of the split only")
    parser.add_argument("--settings", nargs="+", help="tracked settings to run (default: all of the suite's)")
    parser.add_argument("--suite", default=str(SUITE), help="the suite file")
    parser.add_argument("--data", default=str(cache_dir() / "suite"), help="cache of generated sequences")
    parser.add_argument("--out", help="where to write results.json and README.md (default build/suite/<split>[-quick])")
    parser.add_argument("--shared", default=str(SHARED), help="../shared/data (the real meshes and REDWOOD75's orientations)")
    parser.add_argument("--workers", type=int, help="tracking worker processes (default: the tracker's; the chains engine)")
    parser.add_argument("--engine", choices=ENGINES, help="tracking engine (default: annotate.engines' default)")
    parser.add_argument("--surface", choices=SURFACES, help="the reconstruction's surface (default: reconstruct.pipeline's default)")
    parser.add_argument("--tables", metavar="RESULTS", help="print the tables of an earlier run's results.json (runs nothing)")
    args = parser.parse_args(argv)
    if args.tables:
        data = json.loads(Path(args.tables).read_text())
        settings = [Setting(**values) for values in data.get("settings", [])]
        print(markdown(data["split"], data["quick"], len({r["sequence"] for r in data["rows"]}), data["frames"], settings, data["rows"]))
        return 0
    suite = load_suite(args.suite)
    try:
        entries = suite.named(args.split, args.only, args.quick)
    except ValueError as error:
        parser.error(str(error))
    settings = [s for s in suite.settings if s.name == "boxes4"] if args.quick else suite.settings
    if args.settings:
        settings = [s for s in suite.settings if s.name in args.settings]
    frames = suite.quick_frames if args.quick else suite.frames
    out = Path(args.out) if args.out else REPO / "build" / "suite" / f"{args.split}{'-quick' if args.quick else ''}"
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    rows = []
    for k, entry in enumerate(entries, start=1):  # one sequence at a time; the tracker uses the cores
        t0 = time.perf_counter()
        root = build(entry, frames, Path(args.data), Path(args.shared))
        built = time.perf_counter() - t0
        new = run_sequence(root, settings, entry.name, entry.seed, args.workers, args.engine, args.surface)
        for row in new:
            row.update(split=entry.split, shape=entry.shape, coverage=entry.coverage, texture=entry.texture, sensor=entry.sensor)
        rows.extend(new)
        summary = ", ".join(f"{r['setting']}: " + ("ok" if not r["goals_missed"] and "reconstruct_error" not in r else f"{len(r['goals_missed'])} missed")
                            for r in new)
        print(f"[{k}/{len(entries)}] {entry.name}: {summary} ({built:.0f} s to build, {time.perf_counter() - t0:.0f} s in all)", flush=True)
        (out / "results.json").write_text(json.dumps({"split": args.split, "quick": args.quick, "frames": frames,
                                                      "settings": [dataclasses.asdict(s) for s in settings], "rows": rows}, indent=1))
    tables = markdown(args.split, args.quick, len(entries), frames, settings, rows)
    (out / "README.md").write_text(tables)
    print(tables)
    print(f"{len(entries)} sequences in {time.perf_counter() - started:.0f} s; wrote {out / 'results.json'} and {out / 'README.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
