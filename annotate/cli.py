"""``annotate``: serve the browser annotation tool, or track headless with ``--track``."""

from __future__ import annotations

import argparse

from sequences.errors import run_cli

from .engines import DEFAULT_ENGINE, ENGINES


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="annotate", description="Annotate an RGB-D sequence with oriented boxes in the browser, or track headless.")
    parser.add_argument("sequence", nargs="?", help="sequence folder (default: the bundled sample)")
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
                        help="with --track: processes for the independent work (the chains, the refinement's registrations); "
                             "default: the cores available, at most 4; the poses are the same for any N")
    parser.add_argument("--engine", choices=ENGINES, default=None,
                        help=f"with --track: the tracking engine (default {DEFAULT_ENGINE}, or $REDWOOD_GT_ENGINE; see docs/tracking.md)")
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
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers must be at least 1, got {args.workers}")
    if args.track:
        from .track_command import run_track  # owned by the tracking work (issue 5)

        return run_track(args)
    from .app_serve import serve  # owned by the browser app work (issue 7)

    return serve(args)


def entry() -> None:
    raise SystemExit(run_cli(main))


if __name__ == "__main__":
    entry()
