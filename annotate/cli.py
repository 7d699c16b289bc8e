"""``annotate``: serve the browser annotation tool, or track headless with ``--track``."""

from __future__ import annotations

import argparse

from sequences.errors import run_cli

from .engines import DEFAULT_ENGINE, ENGINES, TRACK_PRELOAD


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="annotate", description="Annotate an RGB-D sequence with oriented boxes in the browser, or track headless.")
    parser.add_argument("sequences", nargs="*", metavar="SEQ", help="sequence folder (default: the bundled sample); with --track, several are a batch")
    parser.add_argument("--annotation", help="annotation document (default: SEQ/annotation.yaml)")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    parser.add_argument("--track", action="store_true", help="no server: refine the manual frames, track every frame, write the document")
    parser.add_argument("--placement-sigma", type=float, nargs=2, metavar=("DEG", "MM"), default=None,
                        help="with --track: how far the placed boxes are off, per axis (default 1 deg 2 mm, boxes placed within "
                             "about 3 deg and 5 mm; raise it for rougher boxes, so that the tracking chains count for more)")
    parser.add_argument("--no-facing", dest="facing", action="store_false",
                        help="with --track: let a frame's points pair with model surfaces facing away from its camera too (by "
                             "default they do not: the two sides of a thin slab, such as a laptop's base, are told apart)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="with --track: processes for the independent work (the chains, the refinement's registrations; with several "
                             "SEQ, the sequences at once, each on one process); default: the cores available (at most 4 for one SEQ); "
                             "the poses are the same for any N")
    parser.add_argument("--engine", choices=ENGINES, default=None,
                        help=f"with --track: the tracking engine (default {DEFAULT_ENGINE}, or $REDWOOD_GT_ENGINE; see docs/tracking.md)")
    parser.add_argument("--cluster", metavar="ADDRESS", help="with --track: track the sequences on the Dask cluster whose scheduler is at "
                        "ADDRESS (tcp://HOST:8786; the workers must see the sequences at the same paths)")
    parser.add_argument("--redo", action="store_true", help="with --track and several SEQ: also track the sequences an earlier batch "
                        "finished (by default a sequence whose document is as the batch wrote it is skipped)")
    parser.add_argument("--json", action="store_true", help="with --track: print the report as JSON on stdout (and nothing else there)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.placement_sigma is not None and not args.track:
        parser.error("--placement-sigma applies to --track only")
    if not args.facing and not args.track:
        parser.error("--no-facing applies to --track only")
    if args.engine is not None and not args.track:
        parser.error("--engine applies to --track only")
    if args.workers is not None and not args.track:
        parser.error("--workers applies to --track only")
    if args.workers is not None or args.cluster:  # only then: the browser tool's start does not load the batch engine
        from batch.options import engine_problem

        problem = engine_problem(args.workers, args.cluster)
        if problem:
            parser.error(problem)
    for option in ("cluster", "redo", "json"):
        if getattr(args, option) and not args.track:
            parser.error(f"--{option} applies to --track only")
    if len(args.sequences) > 1 and not args.track:
        parser.error("the browser tool opens one sequence: several SEQ apply to --track only")
    if len(args.sequences) > 1 and args.annotation:
        parser.error("--annotation names one document: give a single SEQ with it")
    if args.cluster and not args.sequences:
        parser.error("--cluster needs the sequence folders (SEQ...): the bundled sample lives on this machine only")
    args.sequence = args.sequences[0] if args.sequences else None
    if args.track:
        return _track(args)
    from .app_serve import serve  # owned by the browser app work (issue 7)

    return serve(args)


def _track(args) -> int:
    """``--track``: one SEQ here as ever, several (or --cluster) as a batch; ``--json`` prints the report."""
    from batch.report import json_report, write_json

    if len(args.sequences) > 1 and not args.cluster:  # the local processes' server imports while this process does
        from batch.local import start_server

        start_server(TRACK_PRELOAD)
    from .track_command import run_track, run_track_batch, track_line, track_one

    with json_report("annotate --track", args.json) as stdout:
        if len(args.sequences) > 1 or args.cluster:
            code, report = run_track_batch(args)
        elif not args.json:
            return run_track(args)
        else:
            summary = track_one(args)
            print(track_line(summary))  # on stderr: stdout holds the report
            unit = {"unit": args.sequence or summary["sequence"], "status": "done", "seconds": round(summary["seconds"], 3), "error": None,
                    **{k: v for k, v in summary.items() if k not in ("state", "seconds")}}
            code, report = 0, {"command": "annotate --track", "engine": "this process", "done": 1, "skipped": 0, "failed": 0, "units": [unit]}
        if args.json:
            write_json(report, stdout)
        return code


def entry() -> None:
    raise SystemExit(run_cli(main))


if __name__ == "__main__":
    entry()
