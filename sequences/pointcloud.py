"""Back-projection of a frame to a coloured point cloud, optionally masked or cropped by an oriented box."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .reader import Sequence


@dataclass
class PointCloud:
    """Camera-frame points (N, 3) in metres, colours (N, 3) uint8 RGB and flat pixel indices (N,)."""

    points: np.ndarray
    colors: np.ndarray
    pixels: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def select(self, keep: np.ndarray) -> "PointCloud":
        return PointCloud(self.points[keep], self.colors[keep], self.pixels[keep])


def in_oriented_box(points: np.ndarray, position, orientation, extents, margin: float = 0.0) -> np.ndarray:
    """Boolean (N,) of camera-frame points inside a box.

    The box is centred at ``position`` (camera frame, m), rotated by ``orientation`` (object to
    camera quaternion x, y, z, w), with full side lengths ``extents`` (m) grown by ``margin`` on each side.
    """
    rotation = Rotation.from_quat(np.asarray(orientation, dtype=np.float64)).as_matrix()
    local = (np.asarray(points, dtype=np.float64) - np.asarray(position, dtype=np.float64)) @ rotation
    half = np.asarray(extents, dtype=np.float64) / 2 + margin
    return np.all(np.abs(local) <= half, axis=1)


def frame_points(
    sequence: Sequence,
    frame: int | str,
    mask: np.ndarray | None = None,
    box: tuple | None = None,
    margin: float = 0.0,
    stride: int = 1,
) -> PointCloud:
    """The coloured point cloud of one frame (camera frame, metres).

    ``mask`` (H, W bool) keeps masked pixels; ``box`` = (position, orientation, extents) keeps
    points inside that oriented box grown by ``margin``; ``stride`` subsamples pixels on a grid.
    """
    depth = sequence.depth(frame)
    color = sequence.color(frame)
    keep = np.ones(depth.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).copy()
    if stride > 1:
        grid = np.zeros_like(keep)
        grid[::stride, ::stride] = True
        keep &= grid
    points, pixels = sequence.camera.backproject(depth, keep)
    cloud = PointCloud(points, color.reshape(-1, 3)[pixels], pixels)
    if box is not None:
        cloud = cloud.select(in_oriented_box(cloud.points, *box, margin=margin))
    return cloud
