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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
import yaml
from PIL import Image

from ..annotation import default_symmetry
from ..camera import Camera
from ..errors import InputError
from .capture import capture_plan
from .motion import Grasp, GraspPlanner, HandState, Trajectory, plan_grasps, hand_states
from .options import GENERATOR_VERSION, CaptureOptions, check_arguments, check_capture
from .png16 import write_png16
from .primitives import Part, vertex_normals
from .render import Render, crop, projected_window, render
from .scene import OBJECT, Layout, background_parts, elbow_at, grasp_hand, hand_parts, make_layout, person_parts, upper_arm_part
from .sensor import PROJECTOR, ObjectStyle, add_color_noise, depth_measurement, object_style, scene_albedo, shade
from .shapes import load_mesh, procedural_mesh
from .truth import TRUTH_DIR, write_mask, write_truth

#: Colour frame period (29.97 Hz), microseconds.
FRAME_PERIOD_US = 33_367
#: Jitter of the depth frame's time offset from frame to frame, microseconds (the offset itself is per sequence).
DEPTH_JITTER_US = 1_000
JPEG_QUALITY = 92
# Named random streams: np.random.default_rng([seed, STREAM]) (frames use FRAME_STREAM + index)
SHAPE, MOTION, LAYOUT, GRASPS, STYLE, TIMING, SENSOR, FRAME_STREAM = 1, 2, 3, 4, 5, 6, 7, 1000


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, stream])


@dataclass
class FrameTimes:
    """Per frame: the colour and depth timestamps (microseconds) and the depth's offset from its colour frame in frame periods."""

    colour_us: np.ndarray
    depth_us: np.ndarray

    @property
    def depth_offset(self) -> np.ndarray:
        return (self.depth_us - self.colour_us) / FRAME_PERIOD_US


def frame_times(frames: int, seed: int, offset_frames: float) -> FrameTimes:
    """Colour frames every FRAME_PERIOD_US (jitter +-0.4 ms); depth offset from colour by a per-sequence amount
    uniform within +-``offset_frames`` periods plus DEPTH_JITTER_US of jitter, kept within half a period (the reader
    pairs by nearest time)."""
    rng = _rng(seed, TIMING)
    start = int(rng.integers(1_000_000, 9_000_000))
    colour = start + np.arange(frames) * FRAME_PERIOD_US + rng.integers(-400, 400, frames)
    base = rng.uniform(-offset_frames, offset_frames) * FRAME_PERIOD_US
    jitter = rng.uniform(-DEPTH_JITTER_US, DEPTH_JITTER_US, frames) if offset_frames > 0 else np.zeros(frames)
    offset = np.clip(np.rint(base + jitter), -0.45 * FRAME_PERIOD_US, 0.45 * FRAME_PERIOD_US).astype(np.int64)
    return FrameTimes(colour.astype(np.int64), colour + offset)


def frame_names(times: FrameTimes) -> list[tuple[str, str, str]]:
    """(frame id, colour file stem, depth file stem) per frame: Redwood names, depth numbered one ahead."""
    return [(f"{i + 1:07d}", f"{i + 1:07d}-{tc:012d}", f"{i + 2:07d}-{td:012d}") for i, (tc, td) in enumerate(zip(times.colour_us, times.depth_us))]


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
    capture: CaptureOptions = field(default_factory=CaptureOptions)
    times: FrameTimes | None = None
    depth_camera: Camera | None = None  # the depth camera as misregistered against colour (None: the colour camera)
    depth_still: Render | None = None  # the still scene seen by the depth camera


def depth_camera_for(camera: Camera, registration_px: float, rng: np.random.Generator) -> Camera:
    """The depth camera, its image shifted against colour by ``registration_px`` in a random direction (a registration
    error of the sensor's factory calibration: the depth image is not quite aligned with the colour image)."""
    angle = rng.uniform(0, 2 * np.pi)
    return replace(camera, cx=camera.cx + registration_px * np.cos(angle), cy=camera.cy + registration_px * np.sin(angle))


def build_scene(obj: trimesh.Trimesh, frames: int, seed: int, camera: Camera, capture: CaptureOptions | None = None) -> Scene:
    """Draw the trajectory, layout, grasps, appearance and sensor timing of a sequence of ``obj`` from ``seed``."""
    capture = capture or CaptureOptions()
    plan = capture_plan(capture.coverage, frames, np.asarray(obj.convex_hull.vertices), _rng(seed, MOTION), capture.keys, capture.turn_speed)
    trajectory = plan.trajectory
    layout = make_layout(trajectory.positions.mean(axis=0), _rng(seed, LAYOUT), plan.table)
    grasps = plan_grasps(plan.schedule, trajectory, GraspPlanner(obj, _rng(seed, GRASPS), grasp_hand), layout.elbow, plan.resting)
    style = object_style(_rng(seed, STYLE), float(obj.extents[1]), capture.texture)
    vertices, faces = np.asarray(obj.vertices), np.asarray(obj.faces)
    still_parts = [*background_parts(layout), *person_parts(layout)]
    still = render(still_parts, camera, projector=PROJECTOR)
    still_colour = shade(still, scene_albedo(still, np.eye(4), style, layout), layout.light)
    sensor = capture.sensor
    depth_camera = depth_camera_for(camera, sensor.registration_px, _rng(seed, SENSOR)) if sensor.registration_px > 0 else None
    depth_still = render(still_parts, depth_camera, projector=PROJECTOR) if depth_camera is not None else None
    return Scene(camera, seed, obj, trajectory, layout, grasps, hand_states(frames, grasps, plan.resting), style,
                 Part(vertices, faces, vertex_normals(vertices, faces), OBJECT), still_parts, still, still_colour,
                 capture, frame_times(frames, seed, sensor.depth_offset_frames), depth_camera, depth_still)


def _moving_parts(scene: Scene, i: int, T: np.ndarray) -> list[Part]:
    """The object at pose ``T`` and, where present, frame ``i``'s hand and arm (camera frame)."""
    hand = scene.hands[i]
    if not hand.present:
        return [scene.object_part.transformed(T)]
    elbow = elbow_at(scene.layout, T[:3, 3])
    return [scene.object_part.transformed(T), hand_parts(hand, T, elbow), upper_arm_part(scene.layout, elbow)]


def _cast(moving: list[Part], scene: Scene, camera: Camera, still: Render) -> tuple[Render, tuple[int, int, int, int]]:
    # only the window holding the moving parts (and their projector shadows) is cast again
    window = projected_window(moving, camera, projector=PROJECTOR) or (0, camera.height, 0, camera.width)
    return render(moving + scene.still_parts, camera, still, window, PROJECTOR), window


def render_frame(scene: Scene, i: int, lap: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``i``: colour (H, W, 3) uint8, depth (H, W) uint16 mm, object mask (H, W) bool. ``lap(stage)`` times stages.

    Colour and the mask show the object at frame ``i``'s colour instant (its true pose); depth is taken at the
    depth frame's own instant, by the depth camera (misregistered by the sensor options), where they differ.
    """
    lap = lap or (lambda stage: None)
    camera, layout = scene.camera, scene.layout
    T = scene.trajectory.pose(i)
    moving = _moving_parts(scene, i, T)
    lap("geometry")
    result, window = _cast(moving, scene, camera, scene.still)
    offset = 0.0 if scene.times is None else float(scene.times.depth_offset[i])
    if offset != 0.0 or scene.depth_camera is not None:
        depth_camera = scene.depth_camera or camera
        seen, _ = _cast(_moving_parts(scene, i, scene.trajectory.pose_at(i + offset)), scene, depth_camera, scene.depth_still or scene.still)
    else:
        seen = result
    lap("ray casting")
    rng = _rng(scene.seed, FRAME_STREAM + i)
    depth = depth_measurement(seen, rng, scene.capture.sensor)
    lap("depth sensor")
    clean = scene.still_colour.copy()
    inside = crop(result, window)
    clean[window[0] : window[1], window[2] : window[3]] = shade(inside, scene_albedo(inside, T, scene.style, layout), layout.light)
    colour = add_color_noise(clean, rng)
    lap("colour")
    return colour, depth, result.label == OBJECT


def object_mesh(category: str, seed: int, mesh: str | Path | None = None, mesh_axes: str = "shapenet", shape: str | None = None) -> trimesh.Trimesh:
    """The sequence's object (ShapeNet axes, metres, box-centred): the mesh file's, or the procedural ``shape``
    (default: the category's plain shape) drawn from ``seed``."""
    obj = load_mesh(mesh, mesh_axes) if mesh is not None else procedural_mesh(shape or category, _rng(seed, SHAPE))
    return trimesh.Trimesh(np.asarray(obj.vertices, np.float64), np.asarray(obj.faces, np.int64), process=False)


def generate_sequence(out: str | Path, category: str, frames: int = 100, seed: int = 0, mesh: str | Path | None = None,
                      mesh_axes: str = "shapenet", camera: Camera | None = None, progress: bool = False, shape: str | None = None,
                      capture: CaptureOptions | None = None) -> Path:
    """Write a synthetic Redwood-layout sequence with its truth to ``out``; returns ``out``.

    ``mesh`` (any file trimesh reads, or a point file; axes :data:`sequences.axes.MESH_AXES`) replaces the
    procedural shape; ``shape`` picks a procedural variant of ``category`` (:data:`.options.PROCEDURAL_SHAPES`);
    ``capture`` sets the coverage, texture and sensor (:class:`.options.CaptureOptions`; its defaults look like
    Redwood's captures). Raises InputError for an existing non-empty ``out``, an unknown category or shape, a bad
    frame count or option, or an unreadable mesh.
    """
    out = Path(out)
    camera = camera or Camera()
    capture = capture or CaptureOptions()
    check_arguments(out, category, frames, mesh, mesh_axes, shape)
    check_capture(out, capture, frames)
    obj = object_mesh(category, seed, mesh, mesh_axes, shape)
    scene = build_scene(obj, frames, seed, camera, capture)
    names = frame_names(scene.times)

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
            "mesh_source": str(mesh) if mesh is not None else f"procedural {shape or category}",
            "camera": camera.to_dict(),
            "capture": capture.to_dict(),
            "sensor": {"depth_sigma_m": "0.0012 + 0.0019 (z - 0.4)^2", "projector_m": PROJECTOR.tolist(),
                       "depth_camera": (scene.depth_camera or camera).to_dict(),
                       "note": "poses are the colour frames' instants; depth is taken at its own timestamp by the depth camera"},
            "hand": {frame_id: {"holding": bool(h.holding), "grasp": int(h.grasp), "present": bool(h.present)}
                     for (frame_id, _, _), h in zip(names, scene.hands)},
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
