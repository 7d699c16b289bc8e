"""Writing a whole synthetic sequence: object, trajectory, hand, scene, sensor, truth; atomically.

Everything is drawn from ``seed`` through named random streams (shape, motion, layout, grasps,
appearance, timing, and one per frame), so a sequence is byte-for-byte reproducible and a frame's
noise does not depend on the others. The sequence is written to a hidden temporary folder next to
``out`` and renamed onto ``out`` at the end: ``out`` is never half-written.
"""

from __future__ import annotations

import os
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
import yaml
from PIL import Image

from ..annotation import default_symmetry
from ..camera import Camera
from ..errors import InputError
from .motion import Grasp, GraspPlanner, HandState, Trajectory, grasp_schedule, hand_states, held_frames, object_trajectory, plan_grasps
from .options import GENERATOR_VERSION, check_arguments
from .png16 import write_png16
from .primitives import Part, vertex_normals
from .render import Render, crop, projected_window, render
from .scene import OBJECT, Layout, background_parts, elbow_at, hand_parts, make_layout, person_parts, upper_arm_part
from .sensor import PROJECTOR, ObjectStyle, add_color_noise, depth_measurement, object_style, scene_albedo, shade
from .shapes import load_mesh, procedural_mesh
from .truth import TRUTH_DIR, write_mask, write_truth

#: Colour frame period (29.97 Hz) and the depth frame's lag behind colour (Redwood: a few ms), microseconds.
FRAME_PERIOD_US = 33_367
DEPTH_LAG_US = (1_500, 4_500)
JPEG_QUALITY = 92
# Named random streams: np.random.default_rng([seed, STREAM]) (frames use FRAME_STREAM + index)
SHAPE, MOTION, LAYOUT, GRASPS, STYLE, TIMING, FRAME_STREAM = 1, 2, 3, 4, 5, 6, 1000


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, stream])


def frame_names(frames: int, seed: int) -> list[tuple[str, str, str]]:
    """(frame id, colour file stem, depth file stem) per frame: Redwood names, depth numbered one ahead, a few ms later."""
    rng = _rng(seed, TIMING)
    start = int(rng.integers(1_000_000, 9_000_000))
    colour_time = start + np.arange(frames) * FRAME_PERIOD_US + rng.integers(-400, 400, frames)
    depth_time = colour_time + rng.integers(*DEPTH_LAG_US, frames)
    return [(f"{i + 1:07d}", f"{i + 1:07d}-{tc:012d}", f"{i + 2:07d}-{td:012d}") for i, (tc, td) in enumerate(zip(colour_time, depth_time))]


@dataclass
class Scene:
    """Everything drawn once per sequence: the object, its trajectory, the hand, the still scene and its render."""

    camera: Camera
    seed: int
    mesh: trimesh.Trimesh  # object frame (ShapeNet axes, box-centred)
    trajectory: Trajectory
    layout: Layout
    grasps: list[Grasp]
    hands: list[HandState]
    style: ObjectStyle
    object_part: Part
    still_parts: list[Part]
    still: Render  # the still scene (wall, table, torso, head) rendered once
    still_colour: np.ndarray  # its noise-free shading (H, W, 3) float32


def build_scene(obj: trimesh.Trimesh, frames: int, seed: int, camera: Camera) -> Scene:
    """Draw the trajectory, layout, grasps and appearance of a sequence of ``obj`` from ``seed``."""
    schedule = grasp_schedule(frames)
    trajectory = object_trajectory(frames, _rng(seed, MOTION), held_frames(frames, schedule))
    layout = make_layout(trajectory.positions.mean(axis=0), _rng(seed, LAYOUT))
    grasps = plan_grasps(schedule, trajectory, GraspPlanner(obj, _rng(seed, GRASPS)), layout.elbow)
    style = object_style(_rng(seed, STYLE), float(obj.extents[1]))
    vertices, faces = np.asarray(obj.vertices), np.asarray(obj.faces)
    still_parts = [*background_parts(layout), *person_parts(layout)]
    still = render(still_parts, camera, projector=PROJECTOR)
    still_colour = shade(still, scene_albedo(still, np.eye(4), style, layout), layout.light)
    return Scene(camera, seed, obj, trajectory, layout, grasps, hand_states(frames, grasps), style,
                 Part(vertices, faces, vertex_normals(vertices, faces), OBJECT), still_parts, still, still_colour)


def render_frame(scene: Scene, i: int, lap: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``i``: colour (H, W, 3) uint8, depth (H, W) uint16 mm, object mask (H, W) bool. ``lap(stage)`` times stages."""
    lap = lap or (lambda stage: None)
    camera, layout = scene.camera, scene.layout
    T = scene.trajectory.pose(i)
    elbow = elbow_at(layout, T[:3, 3])
    moving = [scene.object_part.transformed(T), hand_parts(scene.hands[i], T, elbow), upper_arm_part(layout, elbow)]
    lap("geometry")
    # only the window holding the moving parts (and their projector shadows) is cast again
    window = projected_window(moving, camera, projector=PROJECTOR) or (0, camera.height, 0, camera.width)
    result = render(moving + scene.still_parts, camera, scene.still, window, PROJECTOR)
    lap("ray casting")
    rng = _rng(scene.seed, FRAME_STREAM + i)
    depth = depth_measurement(result, rng)
    lap("depth sensor")
    clean = scene.still_colour.copy()
    inside = crop(result, window)
    clean[window[0] : window[1], window[2] : window[3]] = shade(inside, scene_albedo(inside, T, scene.style, layout), layout.light)
    colour = add_color_noise(clean, rng)
    lap("colour")
    return colour, depth, result.label == OBJECT


def generate_sequence(out: str | Path, category: str, frames: int = 100, seed: int = 0, mesh: str | Path | None = None,
                      mesh_axes: str = "shapenet", camera: Camera | None = None, progress: bool = False) -> Path:
    """Write a synthetic Redwood-layout sequence with its truth to ``out``; returns ``out``.

    ``mesh`` (any file trimesh reads; REDWOOD75 raw axes with ``mesh_axes="redwood75"``) replaces
    the procedural shape of ``category``. Raises InputError for an existing non-empty ``out``, an
    unknown category, a bad frame count, or an unreadable mesh.
    """
    out = Path(out)
    camera = camera or Camera()
    check_arguments(out, category, frames, mesh, mesh_axes)
    obj = load_mesh(mesh, mesh_axes) if mesh is not None else procedural_mesh(category, _rng(seed, SHAPE))
    obj = trimesh.Trimesh(np.asarray(obj.vertices, np.float64), np.asarray(obj.faces, np.int64), process=False)
    scene = build_scene(obj, frames, seed, camera)
    names = frame_names(frames, seed)

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        for sub in ("rgb", "depth", f"{TRUTH_DIR}/masks"):
            (tmp / sub).mkdir(parents=True)
        poses: dict[str, np.ndarray] = {}
        started = time.perf_counter()
        for i, (frame_id, colour_stem, depth_stem) in enumerate(names):  # one render per frame
            colour, depth, mask = render_frame(scene, i)
            Image.fromarray(colour).save(tmp / "rgb" / f"{colour_stem}.jpg", quality=JPEG_QUALITY)
            write_png16(tmp / "depth" / f"{depth_stem}.png", depth)
            write_mask(tmp, frame_id, mask)
            poses[frame_id] = scene.trajectory.pose(i)
            if progress:
                print(f"\rframe {i + 1}/{frames} ({(time.perf_counter() - started) / (i + 1):.2f} s/frame)", end="", flush=True)
        if progress:
            print()
        notes = {
            "generator": f"sequences.synth v{GENERATOR_VERSION}",
            "seed": int(seed),
            "mesh_source": str(mesh) if mesh is not None else f"procedural {category}",
            "camera": camera.to_dict(),
            "sensor": {"depth_sigma_m": "0.0012 + 0.0019 (z - 0.4)^2", "projector_m": PROJECTOR.tolist(),
                       "note": "colour and depth are rendered at the colour frame's instant; their timestamps differ by a few ms"},
            "hand": {frame_id: {"holding": bool(h.holding), "grasp": int(h.grasp)} for (frame_id, _, _), h in zip(names, scene.hands)},
            "grasps": [{"contact": [float(x) for x in g.contact], "first": names[g.first][0], "last": names[g.last][0]} for g in scene.grasps],
        }
        write_truth(tmp, category, default_symmetry(category), obj, poses, notes)
        if camera != Camera():  # the reader assumes Redwood's camera unless camera.yaml says otherwise
            (tmp / "camera.yaml").write_text(yaml.safe_dump(camera.to_dict(), sort_keys=False))
        try:
            os.rename(tmp, out)  # onto a missing or empty folder; atomic
        except OSError as error:
            raise InputError(out, f"output appeared while generating and is not empty ({error.strerror}); nothing was written") from error
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
