"""``python -m sequences.synth OUT --category C [--frames N] [--seed S] [--shape NAME | --mesh FILE [--mesh-axes AXES]]
[--coverage every_side|key_orientations|table] [--keys FILE:ID] [--turn-speed F] [--texture pattern|label|plain]
[--ideal-sensor | --no-quantisation --flying-pixels P --depth-offset F --registration-px PX]``.

Writes a synthetic Redwood-layout RGB-D sequence to OUT (a new or empty folder) with its truth in
OUT/truth/ (mesh.obj, truth.json, masks/). Bad input ends with a one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import time

from ..axes import MESH_AXES
from ..errors import run_cli
from .options import COVERAGES, PROCEDURAL_SHAPES, TEXTURES, CaptureOptions, SensorOptions, check_arguments, check_capture


def capture_from(args: argparse.Namespace) -> CaptureOptions:
    """The capture options of the command line (defaults: :class:`CaptureOptions`, Redwood-like)."""
    defaults = SensorOptions()
    if args.ideal_sensor:
        sensor = SensorOptions.ideal()
    else:
        sensor = SensorOptions(
            quantisation=not args.no_quantisation,
            flying_pixels=defaults.flying_pixels if args.flying_pixels is None else args.flying_pixels,
            depth_offset_frames=defaults.depth_offset_frames if args.depth_offset is None else args.depth_offset,
            registration_px=defaults.registration_px if args.registration_px is None else args.registration_px,
        )
    return CaptureOptions(coverage=args.coverage, keys=args.keys, turn_speed=args.turn_speed, texture=args.texture, sensor=sensor)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sequences.synth", description=__doc__.split("\n\n")[1])
    parser.add_argument("out", help="output sequence folder (must not exist, or be empty)")
    parser.add_argument("--category", help="bottle, bowl, mug, can, camera, laptop (or any category with --mesh); "
                        "with --shape, defaults to the shape's category")
    parser.add_argument("--frames", type=int, default=100, help="number of frames (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="random seed: shape, motion, scene and noise (default 0)")
    parser.add_argument("--shape", choices=list(PROCEDURAL_SHAPES), help="a procedural shape: a category's plain shape or a variant "
                        "(square_bowl, oval_bowl, flat_bottle, fluted_bottle, mug_d_handle, mug_ring_handle)")
    parser.add_argument("--mesh", help="use this mesh file (metres; or a point file .xyz, meshed) instead of a procedural shape")
    parser.add_argument("--mesh-axes", choices=MESH_AXES, default="shapenet",
                        help="the mesh's axes: shapenet (y up), redwood75 (raw: x = ShapeNet z, y = -ShapeNet y, z = ShapeNet x), "
                             "nocs (ShapeNet x = NOCS z, z = -NOCS x) or ycb (z up)")
    parser.add_argument("--coverage", choices=COVERAGES, default="every_side",
                        help="every_side (default), key_orientations (a few only: the bottom or the opening may never be seen), "
                             "table (rests on a table, picked up, put down, picked up again)")
    parser.add_argument("--keys", help="for key_orientations: FILE:ID, a REDWOOD75 annotations.json and a sequence whose "
                        "annotated orientations to pass through (default: a few drawn as people show objects)")
    parser.add_argument("--turn-speed", type=float, default=1.0, help="times the default pace of turning (0.25-4; default 1)")
    parser.add_argument("--texture", choices=TEXTURES, default="pattern", help="the object's look (default pattern)")
    parser.add_argument("--ideal-sensor", action="store_true", help="noise and holes only: no quantisation, flying pixels, "
                        "colour-depth time offset or registration error")
    parser.add_argument("--no-quantisation", action="store_true", help="no disparity quantisation")
    parser.add_argument("--flying-pixels", type=float, help=f"chance of a flying pixel at a depth edge (default {SensorOptions().flying_pixels})")
    parser.add_argument("--depth-offset", type=float, help="largest time offset of depth from colour, in frame periods "
                        f"(default {SensorOptions().depth_offset_frames})")
    parser.add_argument("--registration-px", type=float, help=f"colour-to-depth registration error, pixels (default {SensorOptions().registration_px})")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    args = parser.parse_args(argv)
    category = args.category or (PROCEDURAL_SHAPES.get(args.shape) if args.shape else None)
    if category is None:
        parser.error("--category is required (or --shape, whose category it takes)")
    capture = capture_from(args)
    # reject bad input before importing the renderer (open3d takes seconds to import)
    check_arguments(args.out, category, args.frames, args.mesh, args.mesh_axes, args.shape)
    check_capture(args.out, capture, args.frames)
    if args.mesh is not None:
        from .shapes import load_mesh

        load_mesh(args.mesh, args.mesh_axes)
    if capture.keys is not None:
        from .capture import redwood75_keys

        redwood75_keys(capture.keys)
    from .generate import generate_sequence

    started = time.perf_counter()
    out = generate_sequence(args.out, category, args.frames, args.seed, args.mesh, args.mesh_axes, progress=not args.quiet,
                            shape=args.shape, capture=capture)
    elapsed = time.perf_counter() - started
    print(f"{out}: {args.frames} frames of a {args.shape or category} (seed {args.seed}) in {elapsed:.1f} s ({elapsed / args.frames:.2f} s/frame)")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
