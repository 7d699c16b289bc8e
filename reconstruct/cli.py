"""``reconstruct-sequence``: carve, mesh, smooth, tight box, masks and REDWOOD75 export."""

from __future__ import annotations

import argparse

from sequences.errors import run_cli


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="reconstruct-sequence", description="Reconstruct annotated sequences into REDWOOD75-format ground truth.")
    parser.add_argument("sequences", nargs="+", help="sequence folders")
    parser.add_argument("--annotation", help="annotation document (default: SEQ/annotation.yaml)")
    parser.add_argument("--out", required=True, help="output folder (annotations.json and meshes; added to if it exists)")
    parser.add_argument("--voxel-size", type=float, default=0.002, help="voxel size in metres (default 0.002)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    raise SystemExit("reconstruct-sequence: not implemented yet")


def entry() -> None:
    raise SystemExit(run_cli(main))
