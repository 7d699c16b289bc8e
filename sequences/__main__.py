"""``python -m sequences SEQ [--check]``: summarise a sequence (frames, pairing, camera); ``--check`` reads every frame."""

from __future__ import annotations

import argparse

from .errors import run_cli
from .reader import open_sequence


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sequences", description=__doc__)
    parser.add_argument("sequence", help="sequence folder (Redwood layout: rgb/, depth/, optional camera.yaml)")
    parser.add_argument("--check", action="store_true", help="read every frame and report the first bad one")
    args = parser.parse_args(argv)
    sequence = open_sequence(args.sequence)
    if args.check:
        sequence.check()
    cam = sequence.camera
    print(f"{sequence.root}: {len(sequence)} frames ({sequence.frames[0].id} .. {sequence.frames[-1].id}), "
          f"camera {cam.width}x{cam.height} fx={cam.fx} fy={cam.fy} cx={cam.cx} cy={cam.cy} depth_scale={cam.depth_scale}")
    for label, files in (("colour", sequence.unpaired_color), ("depth", sequence.unpaired_depth)):
        if files:
            print(f"  {len(files)} unpaired {label} file(s): {', '.join(p.name for p in files[:5])}{' ...' if len(files) > 5 else ''}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
