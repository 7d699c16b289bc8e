"""``python -m sequences.synth OUT --category C [--frames N] [--seed S] [--mesh FILE] [--mesh-axes shapenet|redwood75]``.

Writes a synthetic Redwood-layout RGB-D sequence to OUT (a new or empty folder) with its truth in
OUT/truth/ (mesh.obj, truth.json, masks/). Bad input ends with a one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import time

from ..errors import run_cli
from .options import MESH_AXES, check_arguments


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sequences.synth", description=__doc__.split("\n\n")[1])
    parser.add_argument("out", help="output sequence folder (must not exist, or be empty)")
    parser.add_argument("--category", required=True, help="bottle, bowl, mug, can, camera, laptop (or any category with --mesh)")
    parser.add_argument("--frames", type=int, default=100, help="number of frames (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="random seed: shape, motion, scene and noise (default 0)")
    parser.add_argument("--mesh", help="use this mesh file (metres) instead of a procedural shape")
    parser.add_argument("--mesh-axes", choices=MESH_AXES, default="shapenet",
                        help="the mesh's axes: shapenet (y up) or redwood75 (REDWOOD75 raw: x = ShapeNet z, y = -ShapeNet y, z = ShapeNet x)")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    args = parser.parse_args(argv)
    # reject bad input before importing the renderer (open3d takes seconds to import)
    check_arguments(args.out, args.category, args.frames, args.mesh, args.mesh_axes)
    if args.mesh is not None:
        from .shapes import load_mesh

        load_mesh(args.mesh, args.mesh_axes)
    from .generate import generate_sequence

    started = time.perf_counter()
    out = generate_sequence(args.out, args.category, args.frames, args.seed, args.mesh, args.mesh_axes, progress=not args.quiet)
    elapsed = time.perf_counter() - started
    print(f"{out}: {args.frames} frames of a {args.category} (seed {args.seed}) in {elapsed:.1f} s ({elapsed / args.frames:.2f} s/frame)")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
