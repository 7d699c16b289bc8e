"""Speed of the synthetic generator: ``python benchmarks/bench_synth.py [--frames 100] [--category mug] [--seed 0]``.

Goal (issue 2): a 100-frame sequence in under 60 s on 2 cores (0.6 s per frame). Prints wall-clock
and CPU time per frame, the machine's load, and a per-stage breakdown measured on a few extra frames.
"""

from __future__ import annotations

import argparse
import io
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from sequences.camera import Camera
from sequences.synth import generate as g
from sequences.synth.motion import GraspPlanner, hand_states, object_trajectory, plan_grasps
from sequences.synth.png16 import encode_png16
from sequences.synth.primitives import Part, vertex_normals
from sequences.synth.render import projected_window, render
from sequences.synth.scene import OBJECT, background_parts, elbow_at, hand_parts, make_layout, person_parts, upper_arm_part
from sequences.synth.sensor import color_image, depth_measurement, object_style, scene_albedo
from sequences.synth.shapes import procedural_mesh


def stages(category: str, seed: int, frames: int = 10) -> dict[str, float]:
    """Mean wall-clock milliseconds per frame of each stage of the frame loop."""
    camera = Camera()
    obj = procedural_mesh(category, g._rng(seed, g.SHAPE))
    trajectory = object_trajectory(frames, g._rng(seed, g.MOTION))
    layout = make_layout(trajectory.positions.mean(axis=0), g._rng(seed, g.LAYOUT))
    hands = hand_states(frames, plan_grasps(frames, trajectory, GraspPlanner(obj, g._rng(seed, g.GRASPS)), layout.elbow))
    style = object_style(g._rng(seed, g.STYLE), float(obj.extents[1]))
    part = Part(np.asarray(obj.vertices), np.asarray(obj.faces), vertex_normals(np.asarray(obj.vertices), np.asarray(obj.faces)), OBJECT)
    still_parts = [*background_parts(layout), *person_parts(layout)]
    still = render(still_parts, camera)
    static = (still.label, scene_albedo(still, np.eye(4), style, layout))
    totals: dict[str, float] = {}

    def lap(name: str, start: float) -> float:
        now = time.perf_counter()
        totals[name] = totals.get(name, 0.0) + (now - start) * 1000 / frames
        return now

    for i in range(frames):
        t = time.perf_counter()
        T = trajectory.pose(i)
        elbow = elbow_at(layout, T[:3, 3])
        moving = [part.transformed(T), hand_parts(hands[i], T, elbow), upper_arm_part(layout, elbow)]
        t = lap("geometry", t)
        result = render(moving + still_parts, camera, still, projected_window(moving, camera))
        t = lap("ray casting", t)
        rng = g._rng(seed, g.FRAME_STREAM + i)
        depth = depth_measurement(result, rng)
        t = lap("depth sensor", t)
        colour = color_image(result, scene_albedo(result, T, style, layout, static), layout.light, rng)
        t = lap("colour", t)
        Image.fromarray(colour).save(io.BytesIO(), format="JPEG", quality=g.JPEG_QUALITY)
        encode_png16(depth)
        Image.fromarray((result.label == OBJECT).astype(np.uint8) * 255).save(io.BytesIO(), format="PNG", compress_level=1)
        lap("encoding", t)
    return totals


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--category", default="mug")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as folder:
        wall, cpu = time.perf_counter(), time.process_time()
        g.generate_sequence(Path(folder) / "seq", args.category, frames=args.frames, seed=args.seed)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(f"{args.frames}-frame {args.category}: {wall:.1f} s wall ({wall / args.frames:.3f} s/frame), "
          f"{cpu:.1f} s CPU ({cpu / args.frames:.3f} s/frame, all threads); goal < 60 s wall per 100 frames")
    print("stages (ms/frame, wall):", ", ".join(f"{k} {v:.0f}" for k, v in stages(args.category, args.seed).items()))
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
