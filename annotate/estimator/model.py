"""The object model fused from posed frames: a voxel grid of surface points with facing normals (object frame, m).

Points of all frames, moved into the object frame, are averaged per voxel and per normal direction (the six
signed axes of the normal's largest component), so the two sides of a thin wall stay apart. A voxel that the
frames see through more often than ``max_free_share`` of the time they see it is dropped: a hand that held the
object and let go is measured where, in the other frames, the camera sees the background.
"""

from __future__ import annotations

import numpy as np

from .observations import FrameCrops
from .registration import Model


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
        rows, cols, z = crops.project(camera)
        inside = (rows >= 0) & (rows < depth.shape[0]) & (cols >= 0) & (cols < depth.shape[1]) & (z > 0)
        measured = np.zeros(len(model), dtype=np.float32)
        measured[inside] = depth[rows[inside], cols[inside]]
        valid = inside & (measured > 0)
        free += valid & (measured > z + tolerance)
        seen += valid & (np.abs(measured - z) <= tolerance)
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
