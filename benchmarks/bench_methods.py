"""Accuracy and time per sample of the ``box`` and ``template`` methods on clean renders of the built-in templates.

    .venv/bin/python benchmarks/bench_methods.py [--samples 12] [--categories bottle bowl mug can]

Each sample: a built-in template at a uniformly random rotation (all of SO(3)) and a random
position 0.5-1.0 m in front of the camera, ray-cast into depth and mask (no noise, no occluder).
Prints, per category and method, the share of samples within (10 deg, 1 cm) and (5 deg, 1 cm), the
median errors, and the median and 90th-percentile inference wall time and the median CPU time
(the process's own, which a busy shared machine inflates less), with the machine's load. The first
``template`` call per category also builds the template's tables (printed separately).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluate.geometry import quat_to_matrix  # noqa: E402
from evaluate.metrics import rotation_error  # noqa: E402
from evaluate.methods.box import BoxMethod  # noqa: E402
from evaluate.methods.template import TemplateMethod  # noqa: E402
from evaluate.methods.templates import builtin_template  # noqa: E402
from evaluate.rendering import MeshRenderer  # noqa: E402
from sequences.camera import Camera  # noqa: E402


def render(mesh, rotation: np.ndarray, position: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) float32 m (0 = miss) and mask (H, W) bool of ``mesh`` posed object->camera."""
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, position
    depth = MeshRenderer(mesh, camera).depth(pose)
    return depth, depth > 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=12)
    parser.add_argument("--categories", nargs="+", default=["bottle", "bowl", "mug", "can"])
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--template-config", default="{}", help='TemplateMethod config as JSON, e.g. \'{"hypotheses": 1000, "refine": 5}\'')
    args = parser.parse_args()
    camera = Camera()
    methods = {"box": BoxMethod(), "template": TemplateMethod(json.loads(args.template_config))}
    print(f"load average at start: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    for category in args.categories:
        mesh = builtin_template(category)
        start = time.perf_counter()
        methods["template"].template(category)
        print(f"{category}: template tables built in {time.perf_counter() - start:.2f} s")
        rng = np.random.default_rng(args.seed)
        cases = []
        for _ in range(args.samples):
            rotation = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
            position = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.5, 1.0)])
            cases.append((rotation, position, *render(mesh, rotation, position, camera)))
        symmetric = category != "mug"
        for name, method in methods.items():
            degrees, metres, seconds, cpu = [], [], [], []
            for rotation, position, depth, mask in cases:
                start, start_cpu = time.perf_counter(), time.process_time()
                prediction = method.inference(None, depth, mask, category, camera)
                seconds.append(time.perf_counter() - start)
                cpu.append(time.process_time() - start_cpu)
                degrees.append(rotation_error(rotation, quat_to_matrix(prediction.orientation), "y" if symmetric else "none"))
                metres.append(float(np.linalg.norm(prediction.position - position)))
            degrees, metres, seconds = map(np.asarray, (degrees, metres, seconds))
            print(
                f"  {name:8s} (10 deg, 1 cm) {np.mean((degrees < 10) & (metres < 0.01)):5.0%}  (5 deg, 1 cm) "
                f"{np.mean((degrees < 5) & (metres < 0.01)):5.0%}  median {np.median(degrees):6.1f} deg {100 * np.median(metres):5.2f} cm  "
                f"wall median {np.median(seconds):.3f} s, p90 {np.percentile(seconds, 90):.3f} s; CPU median {np.median(cpu):.3f} s"
            )
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
