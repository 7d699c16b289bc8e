"""An object's tilt, frame by frame, from its own faces: a shallow bowl's across its axis, a laptop's whole rotation.

A shallow bowl is close to a sphere: a frame's points pin its tilt (the direction of its axis) only through the
few flat faces across the axis, its foot and its inner bottom, which point-to-plane registration weighs no more
than the curved wall. The axis fit to the model is refused for such a shape (engine._usable_axis), so every frame
would keep the tilt the chains and the smoothing gave it, off by a few degrees over whole stretches. A frame that
sees a flat face measures its tilt directly: the normals of its own points within ``cone_deg`` of the object's y are
turned onto y (faces.tilt_onto_axis, about x and z only; the spin is free), by at most ``max_deg`` (half the cone: a
curved patch seen from one side walks the cone's mean towards its edge). One frame's normals are noisy (a few
hundred, estimated from 1-2 mm depth noise), so each frame takes the median of the tilts measured within
``half_window`` frames of it, where there are at least ``min_count`` of them: a hand-held object's tilt error changes
slowly.

A mug (not symmetric, its body a surface of revolution) after the body's axis snap, or where that is refused: its
foot and inner bottom measure the tilt the same way. Not for cans and bottles, whose side pins the tilt in every frame
and whose axis fit the engine accepts.

A laptop (``hinged``): the hinge snap turns all frames alike onto the model's faces, but the frames that see the base
from above and those that see it from below share no face, and each group keeps the rotation its manual frames
gave it. Each frame's base (normals onto +-y) and lid (normals into the y-z plane, which fixes the spin) measure all
three angles (faces.hinge_rotation on the frame's own normals), and each frame takes the median over the same window,
turned about the box centre (the centres stay). A laptop frame's crop and normals cost ~30 ms of CPU, so they are
measured on every ``TrackingConfig.hinge_tilt_every``-th frame only. For box-like bodies (cameras) the per-frame
faces measured worse than the snap onto the model's faces alone.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from evaluate.geometry import untransform

from .faces import hinge_rotation, tilt_onto_axis
from .tracker import Tracker
from annotate.workers import ordered_map


def frame_tilt(points_obj: np.ndarray, normal_radius: float, cone_deg: float, min_normals: int, max_deg: float, max_nn: int = 32,
               plane_deg: float | None = None) -> np.ndarray | None:
    """The rotation vector (3,; rad, object frame, about x and z) that turns the normals of a frame's points
    ``points_obj`` (N, 3; object frame, m) lying within ``cone_deg`` of +-y onto y, or None where fewer than
    ``min_normals`` lie there or the turn exceeds ``max_deg`` (a hand's palm, or a curved patch seen from one side
    whose normals pull the cone's mean towards its edge: not a face of the object).

    With ``plane_deg`` (a hinged body, a laptop), the whole rotation of faces.hinge_rotation instead: the base's
    normals onto +-y and those within ``plane_deg`` of the y-z plane (the lid's, the base's front and back edges')
    into it, which also fixes the spin about y; None where fewer than ``min_normals`` lie in the cone or the plane.

    The frame's pose is corrected by :func:`untilted` (``pose @ R(w)^T``): its object frame turns by the inverse.
    """
    points_obj = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3)
    if len(points_obj) < min_normals:
        return None
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_obj))
    # normals from up to ``max_nn`` points within a few voxels: one frame's depth noise (1-2 mm on 4 mm voxels)
    # spreads 16-point normals by several degrees, and the cone then keeps a lopsided share of them
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=max_nn))
    normals = np.asarray(cloud.normals)
    if plane_deg is None:
        rotation, _ = tilt_onto_axis(normals, cone_deg, min_points=min_normals)
    else:
        rotation, _ = hinge_rotation(normals, cone_deg, plane_deg, min_points=min_normals)
    if rotation is None:
        return None
    turn = Rotation.from_matrix(rotation).as_rotvec()
    return turn if np.degrees(np.linalg.norm(turn)) <= max_deg else None


def frame_tilts(tracker: Tracker, poses: dict[str, np.ndarray], hinged: bool = False, every: int = 1, skip: frozenset = frozenset()) -> dict[str, np.ndarray]:
    """Per frame whose points measure it (:func:`frame_tilt`, with the tracker's configuration): its tilt (3,);
    ``hinged``: a laptop's whole rotation (the hinge's cone and plane). One crop and normal estimate per frame, on
    the tracker's workers; with ``every`` k > 1, only every k-th frame of ``poses`` (in its order) is measured, and
    never the frames in ``skip`` (suspect ones: a frame far off its object measures a tilt that is not the object's)."""
    config = tracker.config
    plane = config.hinge_plane_deg if hinged else None
    cone = config.hinge_cone_deg if hinged else config.flat_cone_deg

    def measure(frame_id: str) -> np.ndarray | None:
        pose = poses[frame_id]
        points, _ = tracker.crop(frame_id, pose, margin=0.0)
        return frame_tilt(untransform(pose, points), 4 * config.voxel_size, cone, config.min_tilt_normals, config.max_frame_tilt_deg, plane_deg=plane)

    ids = [f for f in list(poses)[:: max(int(every), 1)] if f not in tracker.store.errors and f not in skip]
    return {f: tilt for f, tilt in zip(ids, ordered_map(measure, ids, config.worker_count())) if tilt is not None}


def windowed_medians(ids: list[str], measured: dict[str, np.ndarray], half_window: int, min_count: int = 1) -> dict[str, np.ndarray]:
    """Per frame of ``ids`` (in order) with at least ``min_count`` measurements (``measured``: frame id -> (3,), a
    tilt in rad or an offset in m) within ``half_window`` frames: the median (per component) of those. Other frames
    are absent from the result (they keep their pose)."""
    values = np.full((len(ids), 3), np.nan)
    for i, frame_id in enumerate(ids):
        if frame_id in measured:
            values[i] = measured[frame_id]
    out = {}
    for i, frame_id in enumerate(ids):
        window = values[max(0, i - half_window) : i + half_window + 1]
        window = window[np.isfinite(window[:, 0])]
        if len(window) >= max(min_count, 1):
            out[frame_id] = np.median(window, axis=0)
    return out


def each_frame_untilted(tracker: Tracker, ids: list[str], poses: dict[str, np.ndarray], hinged: bool = False, every: int = 1,
                        skip: frozenset = frozenset()) -> dict[str, np.ndarray]:
    """``poses`` (frame id -> 4x4, frames ``ids`` in order) each turned by the median of the tilts measured within
    ``tilt_window`` frames of it (:func:`frame_tilts`, :func:`windowed_medians`, :func:`untilted`); a frame with fewer
    than ``min_tilt_frames`` measured near it keeps its pose; the frames in ``skip`` are turned but measure nothing."""
    config = tracker.config
    tilts = windowed_medians(ids, frame_tilts(tracker, poses, hinged=hinged, every=every, skip=skip), config.tilt_window, config.min_tilt_frames)
    return {f: untilted(p, tilts[f]) if f in tilts else p for f, p in poses.items()}


def untilted(pose: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """``pose`` (4x4) with its object frame turned by the inverse of ``tilt`` (3,; rad) about the box centre."""
    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3] @ Rotation.from_rotvec(tilt).as_matrix().T
    return out
