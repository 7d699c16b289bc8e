"""Speed and coverage of the synthetic generator.

    python benchmarks/bench_synth.py [--frames 100] [--category mug] [--seed 0]
    python benchmarks/bench_synth.py --coverage [--frames 100] [--categories mug bowl ...] [--seeds 0 1 2 3]

Goal (issue 2): a 100-frame sequence in under 60 s on 2 cores (0.6 s per frame). Prints wall-clock
and CPU time per frame, the machine's load, and a per-stage breakdown measured on a few extra frames.

With --coverage, no sequence is rendered: per category and seed it prints what the capture shows
(sequences.synth.coverage, from the scene's geometry): the smallest angle of the object's +y axis
to the camera (into the opening) and away from it (the bottom), and per grasp the share of its
contact patch seen unobstructed while another grasp holds the object, and the share of the hand's
space next to the surface seen free in some frame where that grasp does not hold it; and the share
of the whole surface no frame shows unobstructed (facing within 75 deg).
"""

from __future__ import annotations

import argparse
import io
import os
import tempfile
import time
from pathlib import Path

from PIL import Image

from sequences.camera import Camera
from sequences.synth import generate as g
from sequences.synth.png16 import encode_png16
from sequences.synth.shapes import procedural_mesh


def stages(category: str, seed: int, frames: int = 10) -> dict[str, float]:
    """Mean wall-clock milliseconds per frame of each stage of the frame loop (generate.render_frame + encoding)."""
    scene = g.build_scene(procedural_mesh(category, g._rng(seed, g.SHAPE)), frames, seed, Camera())
    totals: dict[str, float] = {}
    last = [time.perf_counter()]

    def lap(name: str) -> None:
        now = time.perf_counter()
        totals[name] = totals.get(name, 0.0) + (now - last[0]) * 1000 / frames
        last[0] = now

    for i in range(frames):
        last[0] = time.perf_counter()
        colour, depth, mask = g.render_frame(scene, i, lap)
        Image.fromarray(colour).save(io.BytesIO(), format="JPEG", quality=g.JPEG_QUALITY)
        encode_png16(depth)
        Image.fromarray(mask.astype("uint8") * 255).save(io.BytesIO(), format="PNG", compress_level=1)
        lap("encoding")
    return totals


def coverage(category: str, frames: int, seed: int) -> str:
    """One line of coverage figures for a sequence's scene (drawn as generate.build_scene draws it, not rendered)."""
    from sequences.synth.coverage import measure
    from sequences.synth.motion import GraspPlanner, grasp_schedule, hand_states, held_frames, object_trajectory, plan_grasps
    from sequences.synth.scene import grasp_hand, make_layout

    obj = procedural_mesh(category, g._rng(seed, g.SHAPE))
    schedule = grasp_schedule(frames)
    trajectory = object_trajectory(frames, g._rng(seed, g.MOTION), held_frames(frames, schedule))
    layout = make_layout(trajectory.positions.mean(axis=0), g._rng(seed, g.LAYOUT))
    grasps = plan_grasps(schedule, trajectory, GraspPlanner(obj, g._rng(seed, g.GRASPS), grasp_hand), layout.elbow)
    c = measure(obj, trajectory, hand_states(frames, grasps), layout)
    shares = lambda values: " ".join(f"{v:.2f}" for v in values)  # noqa: E731
    return (f"{category:7} seed {seed}: opening {c.opening_deg:5.1f} deg, bottom {c.bottom_deg:5.1f} deg; "
            f"contact seen in another grasp {shares(c.contact_seen)}; hand space seen free {shares(c.hand_space_free)}; "
            f"surface never seen {c.unseen:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--category", default="mug")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--coverage", action="store_true", help="print coverage figures instead of timing")
    parser.add_argument("--categories", nargs="+", default=["mug", "bowl", "bottle", "can", "camera", "laptop"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    args = parser.parse_args()
    if args.coverage:
        for category in args.categories:
            for seed in args.seeds:
                print(coverage(category, args.frames, seed), flush=True)
        return
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
