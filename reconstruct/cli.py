"""``reconstruct-sequence``: carve, mesh, smooth, tight box, masks and export (REDWOOD75, BOP or NOCS).

    reconstruct-sequence SEQ [SEQ ...] [--annotation FILE] --out DIR [--voxel-size M] [--format redwood75|bop|nocs]
        [--surface carving|tsdf]

Each sequence is reconstructed and exported in turn (see :mod:`reconstruct.export`, :mod:`reconstruct.export_bop`
and :mod:`reconstruct.export_nocs` for what lands in DIR; one DIR holds one format). A sequence that fails writes
nothing; its error is one line on stderr naming the file and the problem, the others go on, and the exit code
is 2 if any failed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from sequences.annotation import annotation_path, load_annotation
from sequences.errors import EXIT_BAD_INPUT, InputError, run_cli
from sequences.reader import open_sequence

from .export_index import FORMATS, check_folder_format
from .pipeline import SURFACE, SURFACES


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
    return parser


def reconstruct_one(root: str, annotation_file: str | None, out: Path, voxel_size: float, smoothing: str, masks: bool, bar: tqdm | None = None,
                    include_flagged: bool = False, fmt: str = FORMATS[0], surface: str = SURFACE) -> Path:
    """Reconstruct and export one sequence in format ``fmt``; returns the annotations.json path (REDWOOD75's file,
    or the BOP or NOCS export's index)."""
    from .pipeline import reconstruct_sequence

    sequence = open_sequence(root)
    sequence.check()  # every frame decodes and the depth scale is plausible: before any work starts
    annotation = load_annotation(annotation_path(root, annotation_file), default_sequence=sequence.name)
    if fmt == "nocs":  # before any work: NOCS's format holds its six categories only
        from .export_nocs import CLASS_IDS

        if annotation.category not in CLASS_IDS:
            raise InputError(annotation_path(root, annotation_file), f"category {annotation.category!r} has no NOCS class id (NOCS knows {', '.join(CLASS_IDS)})")

    def progress(stage: str, done: int, total: int) -> None:
        if bar is not None:
            bar.set_postfix_str(f"{sequence.name}: {stage} {done}/{total}", refresh=False)

    reconstruction = reconstruct_sequence(sequence, annotation, voxel_size, progress=progress, smoothing=smoothing, include_flagged=include_flagged,
                                          surface=surface)
    progress("export", 0, 1)
    if fmt == "bop":
        from .export_bop import export_bop

        path = export_bop(reconstruction, sequence, out, masks=masks, progress=progress)
    elif fmt == "nocs":
        from .export_nocs import export_nocs

        path = export_nocs(reconstruction, sequence, out, progress=progress)
    else:
        from .export import export_redwood

        path = export_redwood(reconstruction, sequence, annotation, out, masks=masks)
    if reconstruction.surface is not None:
        unmeasured = reconstruction.surface.unmeasured_faces()
        if unmeasured:  # the box there rests on surface no frame measured: its extent is a guess
            faces = ", ".join(face for face, _ in unmeasured)
            tqdm.write(f"warning: {reconstruction.sequence}: the tight box's {faces} face{'s' if len(unmeasured) > 1 else ''} rest on surface "
                       f"no frame measured; {unmeasured[0][1]}", file=sys.stderr)
    return path


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.annotation and len(args.sequences) > 1:
        raise InputError(args.annotation, "--annotation names one document: give a single SEQ with it")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "--out exists and is not a folder")
    if args.format == "nocs" and args.no_masks:
        raise InputError(out, "--no-masks does not apply to --format nocs (NOCS's layout needs its masks)")
    check_folder_format(out, args.format)  # one folder, one format
    failed = 0
    bar = tqdm(args.sequences, desc="reconstruct", unit="seq", file=sys.stderr, disable=None)
    for root in bar:
        try:
            reconstruct_one(root, args.annotation, out, args.voxel_size, args.smoothing, not args.no_masks, bar, args.include_flagged, args.format,
                            args.surface)
        except InputError as error:
            failed += 1
            tqdm.write(f"error: {error}", file=sys.stderr)
        except Exception as error:  # one bad sequence must not stop the others; say which one
            failed += 1
            tqdm.write(f"error: {root}: {error.__class__.__name__}: {' '.join(str(error).split())}", file=sys.stderr)
    bar.close()
    done = len(args.sequences) - failed
    print(f"{done} of {len(args.sequences)} sequence(s) written to {out}", file=sys.stderr)
    return EXIT_BAD_INPUT if failed else 0


def entry() -> None:
    raise SystemExit(run_cli(main))
