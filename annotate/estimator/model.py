"""The object model fused from posed frames: a voxel grid of surface points with facing normals (object frame, m).

Points of all frames, moved into the object frame, are averaged per voxel and per normal direction (the six
signed axes of the normal's largest component), so the two sides of a thin wall stay apart. A voxel that the
frames see through more often than ``max_free_share`` of the time they see it is dropped: a hand that held the
object and let go is measured where, in the other frames, the camera sees the background.

For symmetry y the model can be made a surface of revolution about its own axis (:func:`revolution_axis`,
:func:`revolved`), where the data agree: its sides, seen by different frames, then share one axis.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from annotate.depth_agreement import depth_votes

from .observations import FrameCrops
from .registration import Model

#: the axis fit's pull of its tilt towards y: a tilt of 1 rad costs as much as one point this many voxels off
AXIS_RIDGE = 0.1
#: fits of the axis, each to the profile bins of the axis before
AXIS_PASSES = 3
#: a model whose walls (points with radial normals) lie further from their profile than this many voxels (median) is
#: no body of revolution; a face square to the axis fits every shape
MAX_PROFILE_DEVIATION = 0.5
#: the axis is fitted to at most this many of the model's points (every n-th): its four parameters need few
AXIS_FIT_POINTS = 6000
#: the axis parameters' typical sizes (rad, rad, m, m), which scale the fit's steps
AXIS_SCALES = (0.01, 0.01, 0.002, 0.002)
#: Cauchy reweightings of a profile bin's mean
PROFILE_PASSES = 4
#: a profile point near the axis is still spun to this many points
MIN_SPINS = 6


def _keys(points: np.ndarray, normals: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key per point: its voxel and the signed axis its normal points along most."""
    cell = np.floor(points / voxel).astype(np.int64) + (1 << 19)
    axis = np.argmax(np.abs(normals), axis=1)
    sign = np.take_along_axis(normals, axis[:, None], axis=1)[:, 0] > 0
    bucket = 2 * axis + sign
    return ((cell[:, 0] << 43) | (cell[:, 1] << 23) | (cell[:, 2] << 3)) + bucket


def fuse(parts: list[tuple[np.ndarray, np.ndarray]], voxel: float) -> Model:
    """A model from per-frame (points, normals) already in the object frame: one averaged point per voxel and facing."""
    parts = [p for p in parts if len(p[0])]
    if not parts:
        return Model(np.empty((0, 3)), np.empty((0, 3)))
    points = np.concatenate([p[0] for p in parts])
    normals = np.concatenate([p[1] for p in parts])
    _, inverse = np.unique(_keys(points, normals, voxel), return_inverse=True)
    count = np.bincount(inverse).astype(np.float64)
    mean = np.stack([np.bincount(inverse, points[:, k]) for k in range(3)], axis=1) / count[:, None]
    normal = np.stack([np.bincount(inverse, normals[:, k]) for k in range(3)], axis=1)
    length = np.linalg.norm(normal, axis=1)
    keep = length > 0.5 * count  # normals in one voxel that disagree (a corner, noise) give no plane to pair with
    return Model(mean[keep], normal[keep] / length[keep, None])


def seen_through(model: Model, crops: FrameCrops, poses: dict[str, np.ndarray], tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Per model point: in how many of the frames ``poses`` (object to camera) the camera measured beyond it by more
    than ``tolerance`` (m; free there), and in how many it measured it (within ``tolerance``)."""
    free = np.zeros(len(model), dtype=np.int64)
    seen = np.zeros(len(model), dtype=np.int64)
    for frame_id, pose in poses.items():
        depth = crops.depth(frame_id)
        camera = model.points @ pose[:3, :3].T + pose[:3, 3]
        frame_free, frame_seen = depth_votes(depth, *crops.project(camera), tolerance)
        free += frame_free
        seen += frame_seen
    return free, seen


def fused_model(crops: FrameCrops, poses: dict[str, np.ndarray], parts: dict[str, tuple[np.ndarray, np.ndarray]], tolerance: float, max_free_share: float) -> Model:
    """The model of ``parts`` (frame -> camera-frame points and normals) at ``poses``, without the voxels the
    frames of ``poses`` (all of them, not only the parts') see through in more than ``max_free_share`` of the frames
    that see them."""
    moved = []
    for frame_id, (points, normals) in parts.items():
        pose = poses[frame_id]  # noqa: the parts' own poses; the free-space test reads every frame of ``poses``
        moved.append(((points - pose[:3, 3]) @ pose[:3, :3], normals @ pose[:3, :3]))
    model = fuse(moved, crops.voxel)
    free, seen = seen_through(model, crops, poses, tolerance)
    keep = free <= max_free_share * np.maximum(free + seen, 1)
    return Model(model.points[keep], model.normals[keep])


def _profile_bins(points: np.ndarray, normals: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per point (axis frame: the axis is y through the origin): its profile bin (an inverse index), whether its
    normal is mostly radial (the bin then averages its radius, in bins of height; else its height, in bins of radius),
    its radius and its normal's radial part. Each sign of the normal has bins of its own (a wall's two sides)."""
    x, y, z = points.T
    r = np.hypot(x, z)
    n_r = (normals[:, 0] * x + normals[:, 2] * z) / np.maximum(r, 1e-9)
    radial = np.abs(n_r) >= np.abs(normals[:, 1])
    facing = np.where(radial, np.where(n_r > 0, 0, 1), np.where(normals[:, 1] > 0, 2, 3))
    along = np.floor(np.where(radial, y, r) / voxel).astype(np.int64)
    _, inverse = np.unique(facing * (1 << 40) + along + (1 << 30), return_inverse=True)
    return inverse, radial, r, n_r


def _axis_frame(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axis (rotation R turning y onto it, a point c on it) of parameters (tilt about x, tilt about z (rad), c_x, c_z (m))."""
    return Rotation.from_rotvec([params[0], 0.0, params[1]]).as_matrix(), np.array([params[2], 0.0, params[3]])


def revolution_axis(points: np.ndarray, normals: np.ndarray, voxel: float, max_tilt_deg: float, max_shift: float,
                    start: np.ndarray | None = None) -> np.ndarray | None:
    """The axis (:func:`_axis_frame`'s parameters) about which a model's ``points`` (object frame, with their unit
    ``normals``) lie closest to their profile
    (:func:`_profile_bins`; Cauchy-robust least squares, SciPy, from ``start`` or the object's y), or None where it
    lies more than ``max_tilt_deg`` / ``max_shift`` (m) from the object's y through the origin (the boxes are not that
    far off). Fitted to every n-th point, at most AXIS_FIT_POINTS."""
    step = -(-len(points) // AXIS_FIT_POINTS)
    points, normals = points[::step], normals[::step]
    if len(points) < 20:
        return None

    def deviation(params: np.ndarray, inverse: np.ndarray, radial: np.ndarray, count: np.ndarray) -> np.ndarray:
        R, c = _axis_frame(params)
        p = (points - c) @ R
        value = np.where(radial, np.hypot(p[:, 0], p[:, 2]), p[:, 1])
        # a weak pull of the tilt towards y: a sphere's axis is free (a bowl's dome), its rim and foot hold it
        return np.concatenate([value - (np.bincount(inverse, value) / count)[inverse], AXIS_RIDGE * voxel * params[:2]])

    params = np.zeros(4) if start is None else np.asarray(start, dtype=np.float64)
    for _ in range(AXIS_PASSES):  # the points' bins at the last axis, then the axis that fits them best
        R, c = _axis_frame(params)
        inverse, radial, _, _ = _profile_bins((points - c) @ R, normals @ R, voxel)
        count = np.bincount(inverse).astype(np.float64)
        params = least_squares(deviation, params, loss="cauchy", f_scale=voxel / 2, x_scale=AXIS_SCALES,
                               args=(inverse, radial, count)).x
    if np.degrees(np.hypot(params[0], params[1])) > max_tilt_deg or np.hypot(params[2], params[3]) > max_shift:
        return None
    return params


def _profile(p: np.ndarray, n: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Points ``p`` with unit normals ``n`` (axis frame) in their profile bins (:func:`_profile_bins`: inverse index,
    radial, radius, radial part of the normal), each point's Cauchy weight about its bin's mean, and the median
    distance (m) of the walls (radial normals) from their profile (inf without walls)."""
    inverse, radial, r, n_r = _profile_bins(p, n, voxel)
    value = np.where(radial, r, p[:, 1])
    weight = np.ones(len(value))
    for _ in range(PROFILE_PASSES):
        mean = np.bincount(inverse, weight * value) / np.maximum(np.bincount(inverse, weight), 1e-12)
        weight = 1.0 / (1.0 + ((value - mean[inverse]) / (voxel / 2)) ** 2)
    deviation = float(np.median(np.abs(value - mean[inverse])[radial])) if radial.any() else np.inf
    return inverse, radial, r, n_r, weight, deviation


def is_revolution(points: np.ndarray, normals: np.ndarray, voxel: float, axis: np.ndarray) -> bool:
    """Whether ``points`` (object frame, m) with unit ``normals`` lie on a surface of revolution about ``axis``
    (:func:`_axis_frame`'s parameters): their walls within MAX_PROFILE_DEVIATION voxels of their profile at the
    median. A round bowl or can is; a flattened bottle or a square bowl is not."""
    R, c = _axis_frame(axis)
    return _profile((points - c) @ R, normals @ R, voxel)[5] <= MAX_PROFILE_DEVIATION * voxel


def revolved(model: Model, voxel: float, axis: np.ndarray) -> Model | None:
    """The model made a surface of revolution about ``axis`` (:func:`revolution_axis`), or None where its walls (points
    whose normals are mostly radial) lie further from their profile than MAX_PROFILE_DEVIATION voxels at the median
    (a flattened bottle, a square dish).

    The profile: per facing bin (:func:`_profile_bins`, ``voxel`` wide) the Cauchy-weighted mean radius and height
    (a hand's points on one side do not bulge the whole ring), each spun about the axis every ``voxel`` of its circle."""
    R, c = _axis_frame(axis)
    p, n = (model.points - c) @ R, model.normals @ R
    inverse, radial, r, n_r, weight, deviation = _profile(p, n, voxel)
    if deviation > MAX_PROFILE_DEVIATION * voxel:
        return None
    total = np.maximum(np.bincount(inverse, weight), 1e-12)
    pr, py, nr, ny = (np.bincount(inverse, weight * a) / total for a in (r, p[:, 1], n_r, n[:, 1]))
    length = np.hypot(nr, ny)
    keep = (np.bincount(inverse) >= 2) & (length > 0.5)  # normals that disagree in a bin give no plane to pair with
    pr, py, nr, ny = pr[keep], py[keep], nr[keep] / length[keep], ny[keep] / length[keep]
    spins = np.maximum(MIN_SPINS, np.ceil(2 * np.pi * pr / voxel)).astype(np.int64)
    which = np.repeat(np.arange(len(pr)), spins)
    angle = 2 * np.pi * (np.arange(len(which)) - (np.cumsum(spins) - spins)[which]) / spins[which]
    cos, sin = np.cos(angle), np.sin(angle)
    spun = np.stack([pr[which] * cos, py[which], pr[which] * sin], axis=1)
    spun_normals = np.stack([nr[which] * cos, ny[which], nr[which] * sin], axis=1)
    return Model(spun @ R.T + c, spun_normals @ R.T)
