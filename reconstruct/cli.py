"""``reconstruct-sequence``: carve, mesh, smooth, tight box, masks and export (REDWOOD75, BOP or NOCS).

    reconstruct-sequence SEQ [SEQ ...] [--annotation FILE] --out DIR [--voxel-size M] [--format redwood75|bop|nocs]
        [--surface carving|tsdf] [--workers N | --cluster ADDRESS] [--redo] [--json]

One SEQ is reconstructed and exported here (see :mod:`reconstruct.export`, :mod:`reconstruct.export_bop` and
:mod:`reconstruct.export_nocs` for what lands in DIR; one DIR holds one format). Several, or any with
``--cluster``, are a batch (:mod:`reconstruct.units`): one unit per sequence on N local processes or a Dask
cluster, the sequences finished by an earlier batch skipped, the outputs the same for any worker count. A
sequence that fails writes nothing; its error is one line on stderr naming the file and the problem, the others
go on, and the exit code is 2 if any failed. ``--json`` prints the report on stdout.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from batch.options import engine_problem
from batch.report import json_report, write_json
from sequences.errors import EXIT_BAD_INPUT, InputError, run_cli

from . import SURFACE, SURFACES
from .export_index import FORMATS, check_folder_format, read_index

#: What a batch's local processes import once (batch.local's server): the reconstruction and its exports.
PRELOAD = ("numpy", "scipy.spatial", "trimesh", "open3d", "reconstruct.pipeline", "reconstruct.export", "reconstruct.export_bop", "reconstruct.export_nocs")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="reconstruct-sequence", description="Reconstruct annotated sequences into REDWOOD75-, BOP- or NOCS-format ground truth.")
    parser.add_argument("sequences", nargs="+", help="sequence folders")
    parser.add_argument("--annotation", help="annotation document (default: SEQ/annotation.yaml; only with one SEQ)")
    parser.add_argument("--out", required=True, help="output folder (annotations.json and meshes; added to if it exists)")
    parser.add_argument("--voxel-size", type=float, default=0.002, help="voxel size in metres (default 0.002)")
    parser.add_argument("--smoothing", choices=("taubin", "laplacian", "none"), default="taubin", help="mesh smoothing (default taubin: does not shrink)")
    parser.add_argument("--format", choices=FORMATS, default=FORMATS[0], help="export format (default redwood75: annotations.json and meshes; "
                        "bop: bop_toolkit's scene layout, millimetres; nocs: REAL275's layout with NOCS maps and gts pickles)")
    parser.add_argument("--no-masks", action="store_true", help="do not render and write the per-frame masks (redwood75 and bop; NOCS's layout needs them)")
    parser.add_argument("--surface", choices=SURFACES, default=SURFACE, help=f"the surface meshed (default {SURFACE}): carving, the carved "
                        "occupancy; tsdf, the depth fused where frames measured the surface and the carved hull elsewhere")
    parser.add_argument("--include-flagged", action="store_true",
                        help="also carve with frames flagged for review (by default they are posed and exported but do not carve)")
    batch = parser.add_argument_group("batches (several SEQ, or --cluster)")
    batch.add_argument("--workers", type=int, default=None, metavar="N", help="sequences at once on local processes (default: the cores available)")
    batch.add_argument("--cluster", metavar="ADDRESS", help="run the sequences on the Dask cluster whose scheduler is at ADDRESS "
                       "(tcp://HOST:8786; the workers must see SEQ and DIR at the same paths)")
    batch.add_argument("--redo", action="store_true", help="also run the sequences an earlier batch finished (by default they are skipped)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON on stdout (and nothing else there)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def options_of(args) -> dict:
    """The options that make a sequence's output (a unit's state records them)."""
    return {"voxel_size": float(args.voxel_size), "smoothing": args.smoothing, "format": args.format, "masks": not args.no_masks,
            "include_flagged": bool(args.include_flagged), "surface": args.surface}


class StageBar:
    """One sequence's progress on a terminal: a bar per stage (carve, export, ...) with its counts and time left
    (none in a log: one sequence's stages are seconds long)."""

    def __init__(self, name: str, quiet: bool) -> None:
        from batch.runner import progress_bar

        self.name, self.stage = name, None
        self.bar = progress_bar(1, f"{name}: open", "step", quiet, log=False)

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage != self.stage:
            self.stage = stage
            self.bar.reset(total=max(total, 1))
            self.bar.set_description_str(f"{self.name}: {stage}", refresh=False)
        self.bar.update(max(done - self.bar.n, 0))

    def close(self) -> None:
        self.bar.close()


def reconstruct_one(root: str, annotation_file: str | None, out: Path, options: dict, quiet: bool = False) -> dict:
    """Reconstruct and export one sequence here, with a progress bar; returns its summary (the index's path in ``index``)."""
    from . import units

    bar = StageBar(Path(root).name, quiet)
    try:
        reconstruction, sequence, annotation, _ = units.reconstruct(root, options, annotation_file, progress=bar)
        bar("export", 0, 1)
        path = units.export(reconstruction, sequence, annotation, out, options, progress=bar)
    finally:
        bar.close()
    summary = units.summary_of(reconstruction, path, "")
    del summary["state"]
    return summary


def _single(args, out: Path, options: dict) -> list[dict]:
    """One SEQ, here, as before batches: no markers, nothing skipped."""
    from tqdm import tqdm

    from . import units

    start = time.perf_counter()
    root = args.sequences[0]
    try:
        summary = reconstruct_one(root, args.annotation, out, options, args.quiet)
    except InputError as error:
        tqdm.write(f"error: {error}", file=sys.stderr)
        return [{"unit": root, "status": "failed", "seconds": round(time.perf_counter() - start, 3), "error": str(error)}]
    except Exception as error:  # say which sequence, in one line
        line = f"{root}: {error.__class__.__name__}: {' '.join(str(error).split())}"
        tqdm.write(f"error: {line}", file=sys.stderr)
        return [{"unit": root, "status": "failed", "seconds": round(time.perf_counter() - start, 3), "error": line}]
    units.print_warnings(summary)
    return [{"unit": root, "status": "done", "seconds": round(time.perf_counter() - start, 3), "error": None, **summary}]


def _batch(args, out: Path, options: dict) -> tuple[list[dict], str]:
    """Several SEQ (or --cluster): one unit per sequence (reconstruct.units)."""
    from batch import Unit, run_batch
    from batch.local import available_cores

    from . import units

    batch_units = []
    document = args.annotation  # one SEQ only
    names = [units.sequence_name(root, document) for root in args.sequences]  # None: its document does not load (its unit says why)
    twice = sorted({n for n in names if n is not None and names.count(n) > 1})
    if twice:
        raise InputError(None, f"two SEQ export under the name {twice[0]!r} (their documents' sequence, else their folders'): one would replace the other")
    reserved = units.reserve(out, args.format, [n for n in names if n is not None])  # scene numbers in the command line's order
    for root, name in zip(args.sequences, names):
        marker = None if name is None else units.marker_path(out, name)
        state = None if name is None else (lambda root=root, name=name: units.state_now(root, document, out, options, name))
        batch_units.append(Unit(root, units.whole_unit, (root, document, str(out), options, reserved.get(name)), marker, state))
    before = list(read_index(out)) if out.is_dir() else []

    def describe(outcome) -> str:
        units.print_warnings(outcome.summary)
        return f"{outcome.summary.get('sequence', outcome.key)}: {outcome.summary.get('frames', '?')} frames reconstructed and exported in {outcome.seconds:.1f} s"

    workers = args.workers or available_cores()
    batch = run_batch(batch_units, workers=workers, cluster=args.cluster, redo=args.redo, desc="reconstruct", noun="seq", quiet=args.quiet,
                      preload=PRELOAD, describe=describe)
    names = [o.summary["sequence"] for o in batch.outcomes if o.status in ("done", "skipped") and "sequence" in o.summary]
    units.order_index(out, before, names)
    return [o.as_dict() for o in batch.outcomes], batch.engine


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with json_report("reconstruct-sequence", args.json) as stdout:
        return _main(args, stdout)


def _main(args, stdout) -> int:
    if args.annotation and len(args.sequences) > 1:
        raise InputError(args.annotation, "--annotation names one document: give a single SEQ with it")
    problem = engine_problem(args.workers, args.cluster)
    if problem:
        raise InputError(None, problem)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "--out exists and is not a folder")
    if args.format == "nocs" and args.no_masks:
        raise InputError(out, "--no-masks does not apply to --format nocs (NOCS's layout needs its masks)")
    batch = len(args.sequences) > 1 or args.cluster
    if batch and not args.cluster:  # the local processes' server imports PRELOAD while this process imports and checks
        from batch.local import start_server

        start_server(PRELOAD)
    check_folder_format(out, args.format)  # one folder, one format
    options = options_of(args)
    start = time.perf_counter()
    if batch:
        report, engine = _batch(args, out, options)
    else:
        report, engine = _single(args, out, options), "this process"
    failed = sum(entry["status"] == "failed" for entry in report)
    written = sum(entry["status"] == "done" for entry in report)
    skipped = sum(entry["status"] == "skipped" for entry in report)
    print(f"{written} of {len(report)} sequence(s) written to {out}" + (f", {skipped} finished before" if skipped else ""), file=sys.stderr)
    if args.json:
        write_json({"command": "reconstruct-sequence", "out": str(out), "format": args.format, "options": options, "engine": engine,
                    "seconds": round(time.perf_counter() - start, 3), "done": written, "skipped": skipped, "failed": failed, "units": report}, stdout)
    return EXIT_BAD_INPUT if failed else 0


def entry() -> None:
    raise SystemExit(run_cli(main))
