"""Reading a frame's points once and cropping them by a box, for the tracker."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from sequences.errors import InputError
from sequences.pointcloud import frame_points
from sequences.reader import Sequence


def _backproject_strided(camera, depth: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a depth image subsampled by ``stride`` (pixel (i, j) is full-resolution (stride i, stride j))."""
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u].astype(np.float64)
    points = np.stack([(u * stride - camera.cx) / camera.fx * z, (v * stride - camera.cy) / camera.fy * z, z], axis=1)
    return points, v * stride * camera.width + u * stride


class FrameStore:
    """Caches each frame's back-projected points (camera frame, m) and colours (0..1), subsampled by ``stride``."""

    def __init__(self, sequence: Sequence, stride: int = 2, cache: bool = True, colors: bool = True) -> None:
        self.sequence = sequence
        self.colors = colors
        self.stride = int(stride)
        self.cache = cache
        self._frames: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.errors: dict[str, str] = {}

    def raw(self, frame_id: str) -> tuple[np.ndarray, np.ndarray]:
        """All valid points (N, 3) float32 and colours (N, 3) float32 of a frame; empty when it cannot be read."""
        if frame_id in self._frames:
            return self._frames[frame_id]
        try:
            if self.colors:
                cloud = frame_points(self.sequence, frame_id, stride=self.stride)
                out = (cloud.points.astype(np.float32), cloud.colors.astype(np.float32) / 255.0)
            else:  # geometry only: decoding the colour image would cost a third of the read
                depth = self.sequence.depth(frame_id)[:: self.stride, :: self.stride]
                points, _ = _backproject_strided(self.sequence.camera, depth, self.stride)
                out = (points.astype(np.float32), np.zeros((len(points), 3), np.float32))
        except InputError as error:  # a corrupt or empty frame: no points, the frame gets flagged
            self.errors[frame_id] = str(error)
            out = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
        if self.cache:
            self._frames[frame_id] = out
        return out

    def crop(self, frame_id: str, pose: np.ndarray, extents: np.ndarray, margin: float, voxel: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Points and colours of a frame inside the box at ``pose`` (4x4 object to camera) grown by ``margin`` (m).

        Voxel-downsampled to ``voxel`` when given.
        """
        points, colors = self.raw(frame_id)
        if len(points) == 0:
            return points.astype(np.float64), colors.astype(np.float64)
        R, t = pose[:3, :3], pose[:3, 3]
        local = (points - t) @ R
        keep = np.all(np.abs(local) <= np.asarray(extents) / 2 + margin, axis=1)
        points, colors = points[keep].astype(np.float64), colors[keep].astype(np.float64)
        if voxel and len(points):
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            cloud.colors = o3d.utility.Vector3dVector(colors)
            cloud = cloud.voxel_down_sample(voxel)
            points, colors = np.asarray(cloud.points), np.asarray(cloud.colors)
        return points, colors
