"""Free-space evidence against model voxels: a hand that regrasps is seen through once it has moved.

A voxel of the object model is a surface rigidly attached to the object only if no frame, at its
pose, measures depth clearly *behind* that voxel along the voxel's pixel ray. A hand holding the
object during one grasp is rigid with it for tens of frames (so the model's hit counts cannot tell
it from the object), but after a regrasp the camera looks through the place where it was. Such
voxels are left out of the registration target: kept, a hand seen only in one stretch of frames
pins those frames to whatever poses they had when the model was built (measured on a mug: a
stretch of 30 frames held 3.5 deg off about the mug's axis by its own hand).
"""

from __future__ import annotations

import numpy as np

from annotate.depth_agreement import depth_votes

from .frames import FrameStore


def free_space_votes(
    points_obj: np.ndarray,
    poses: dict[str, np.ndarray],
    store: FrameStore,
    tolerance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per model point (M, 3) in the object frame (m): (frames seeing through it, frames seeing it), both (M,) int.

    ``poses``: frame id -> 4x4 object-to-camera pose. A frame sees through a point when the depth
    at the point's pixel is more than ``tolerance`` (m) behind the point; it sees the point when
    the depth is within ``tolerance`` of it. Pixels without depth, outside the image, or in front
    of the point (an occluder) give no vote.
    """
    points_obj = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3)
    through = np.zeros(len(points_obj), dtype=np.int64)
    seen = np.zeros(len(points_obj), dtype=np.int64)
    if len(points_obj) == 0:
        return through, seen
    camera, s = store.sequence.camera, store.stride
    for frame_id, pose in poses.items():  # one vectorised projection per frame (tens of frames)
        if frame_id in store.errors:
            continue
        depth, _ = store.image(frame_id)
        if frame_id in store.errors:
            continue
        p = points_obj @ pose[:3, :3].T + pose[:3, 3]
        z = p[:, 2]
        front = z > 1e-3
        u = np.full(len(p), -1, dtype=np.int64)
        v = np.full(len(p), -1, dtype=np.int64)
        u[front] = np.round((camera.fx * p[front, 0] / z[front] + camera.cx) / s).astype(np.int64)
        v[front] = np.round((camera.fy * p[front, 1] / z[front] + camera.cy) / s).astype(np.int64)
        frame_through, frame_seen = depth_votes(depth, v, u, z, tolerance)
        through += frame_through
        seen += frame_seen
    return through, seen
