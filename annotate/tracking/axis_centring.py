"""A round body's frames (a mug's), each moved across its axis onto the axis of the model of all frames.

Why: a mug's chains pair without the facing test (engine.py: with it they lost the spin where the handle was
hidden), so a frame's outer wall pairs in part with the model's inner wall behind it, and its inner far wall with
the outer wall behind that: each frame is pulled towards its camera by a millimetre or two. Once the chains have done
so, no later round undoes it: the model of all frames is then the mug with its wall thinned by twice the pull (every
frame seen from outside, each shifted along its own view), and each frame fits that model as well as the truth. The
data themselves do not lean: a frame's points at its true pose lie on the true mesh along the rays.

A mug's body is a surface of revolution: the normal lines of its wall, outer and inner, all meet its axis. So each
frame's own points place the axis in that frame's object frame (symmetry.fit_axis_point, the direction held at the
box's y), from the wall alone: the handle (the points within ``handle_clear_deg`` of its direction about the axis),
what lies off the wall (a hand's fingers, further than ``band_m`` from the body's radius), and the wall seen nearly
edge-on (normals more than ``max_view_deg`` from the direction to the camera) are left out. The last matters: depth
noise runs along the rays, which there run along the surface, and tilts those normals towards the camera, so that
their lines meet nearer the camera than the axis (tests/test_tracking_axis_centring.py). Each frame is moved by the
median of the offsets measured within ``window`` frames of it, square to the axis, so that its axis lands on the
reference's (the model of the trusted frames). Nothing is moved where the model's wall is no surface of revolution
about the axis its normal lines meet (estimator.model.is_revolution: a box that passed the roundness test). The step
runs before the common correction (engine step 5), which then moves all frames alike onto the placed boxes. Cost: a
crop and normals per frame, a few milliseconds.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import open3d as o3d

from evaluate.geometry import untransform

from .handle import handle_direction
from annotate.estimator.model import is_revolution
from annotate.symmetry_axis import fit_axis_point
from .tilt import windowed_medians
from .tracker import Tracker
from annotate.workers import ordered_map

Y = np.array([0.0, 1.0, 0.0])


class Body(NamedTuple):
    """A round body in its object frame (m): a point of its axis (along y), its wall's radius, and the unit direction
    (3,) of its handle square to the axis (None where none stands out)."""

    point: np.ndarray
    radius: float
    handle: np.ndarray | None


def wall_normals(points: np.ndarray, radius: float, camera: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) of ``points`` (N, 3) m, from up to 32 neighbours within ``radius`` m, turned towards
    ``camera`` (3,; the same frame)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=32))
    cloud.orient_normals_towards_camera_location(np.asarray(camera, dtype=np.float64))
    return np.asarray(cloud.normals)


def fit_body(points: np.ndarray, normals: np.ndarray) -> Body | None:
    """The body of the model ``points`` (N, 3) with ``normals`` (N, 3), object frame (m), its axis along y: where the
    normal lines meet, the median distance from there of the points whose normals lie across the axis (the wall),
    and the handle's direction (handle.handle_direction); None with too few points."""
    try:
        point, _ = fit_axis_point(points, normals, Y)
    except ValueError:
        return None
    across = np.abs(normals @ Y) < 0.5
    radial = (points - point)[:, [0, 2]]
    if across.sum() < 20:
        return None
    radius = float(np.median(np.linalg.norm(radial[across], axis=1)))
    return Body(point, radius, handle_direction(points, Y, point))


def wall(points: np.ndarray, normals: np.ndarray, body: Body, band_m: float, handle_clear_deg: float, height: float) -> np.ndarray:
    """Mask (N,) of the points of the body's wall: normals across the axis (within 30 deg of square to it), within
    ``band_m`` of the body's radius, more than ``handle_clear_deg`` from the handle's direction about the axis, and
    within ``height`` / 2 less a margin of ``band_m`` of the axis point along it (the rim and foot curve away)."""
    relative = points - body.point
    radial = relative.copy()
    radial[:, 1] = 0.0
    distance = np.linalg.norm(radial, axis=1)
    keep = (np.abs(normals @ Y) < np.sin(np.radians(30.0))) & (np.abs(distance - body.radius) < band_m)
    keep &= np.abs(relative[:, 1]) < height / 2 - band_m
    if body.handle is not None:
        cosine = (radial @ body.handle) / np.maximum(distance, 1e-12)
        keep &= cosine < np.cos(np.radians(handle_clear_deg))
    return keep


def frame_offset(points_obj: np.ndarray, camera: np.ndarray, body: Body, normal_radius: float, band_m: float, handle_clear_deg: float,
                 height: float, min_points: int, max_view_deg: float) -> np.ndarray | None:
    """Where a frame's own wall puts the axis, less where ``body`` has it: (3,) m, object frame, square to y; None
    where fewer than ``min_points`` of its points ``points_obj`` (N, 3; object frame, m, seen from ``camera`` (3,))
    lie on the wall and face the camera within ``max_view_deg``."""
    if len(points_obj) < min_points:
        return None
    normals = wall_normals(points_obj, normal_radius, camera)
    rays = points_obj - camera
    facing = -np.sum(normals * rays, axis=1) / np.maximum(np.linalg.norm(rays, axis=1), 1e-12)
    keep = wall(points_obj, normals, body, band_m, handle_clear_deg, height) & (facing > np.cos(np.radians(max_view_deg)))
    if keep.sum() < min_points:
        return None
    try:
        point, _ = fit_axis_point(points_obj[keep], normals[keep], Y)
    except ValueError:
        return None
    offset = point - body.point
    offset[1] = 0.0
    return offset


def shifted_onto_axis(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``pose`` (4x4, object to camera) with its object frame moved by ``offset`` (3,) m: a point the frame saw at
    ``p`` (object frame) is then at ``p - offset``."""
    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, 3] += out[:3, :3] @ offset
    return out


def each_frame_on_axis(tracker: Tracker, ids: list[str], poses: dict[str, np.ndarray], model_points: np.ndarray,
                       model_normals: np.ndarray) -> dict[str, np.ndarray]:
    """``poses`` (frame id -> 4x4, frames ``ids`` in order), each moved square to the box's y so that its wall's axis
    lands on that of the model of all frames (``model_points``, ``model_normals``: (N, 3), the same object frame);
    frames with too few wall points near them keep their pose, and so do all where the model gives no body."""
    config = tracker.config
    body = fit_body(model_points, model_normals)
    if body is None or not is_revolution(model_points, model_normals, config.voxel_size, np.array([0.0, 0.0, body.point[0], body.point[2]])):
        return poses  # no body, or no wall of revolution about it (a box that passed the roundness test): no axis to centre on
    height = float(tracker.extents[1])

    def measure(frame_id: str) -> np.ndarray | None:
        pose = poses[frame_id]
        points, _ = tracker.crop(frame_id, pose, margin=0.0)
        camera = untransform(pose, np.zeros((1, 3)))[0]
        return frame_offset(untransform(pose, points), camera, body, 4 * config.voxel_size, config.axis_band_m, config.axis_handle_clear_deg,
                            height, config.min_axis_points, config.axis_max_view_deg)

    measured = [f for f in ids if f not in tracker.store.errors]
    offsets = {f: o for f, o in zip(measured, ordered_map(measure, measured, config.worker_count())) if o is not None}
    windowed = windowed_medians(ids, offsets, config.axis_window, config.min_axis_frames)
    limit = config.max_axis_offset_m
    return {f: shifted_onto_axis(p, windowed[f]) if f in windowed and np.linalg.norm(windowed[f]) <= limit else p for f, p in poses.items()}
