"""``evaluate``: evaluate pose-and-shape methods against REDWOOD75-format ground truth."""

from __future__ import annotations

import argparse

from sequences.errors import run_cli


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="evaluate", description="Evaluate methods on a REDWOOD75-format dataset.")
    parser.add_argument("--dataset", help="folder with annotations.json and the meshes")
    parser.add_argument("--frames", help="root of the sequence folders (for methods run here)")
    parser.add_argument("--method", action="append", help="built-in name (box, template, oracle), NAME=predictions.jsonl or NAME=module:Class")
    parser.add_argument("--out", help="output folder")
    parser.add_argument("--config", help="YAML config; command-line options override it")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    raise SystemExit("evaluate: not implemented yet")


def entry() -> None:
    raise SystemExit(run_cli(main))
