"""A frame's measured points near a box: camera frame, metres, with normals that face the camera.

Each depth image is read once and kept subsampled (``stride``); a crop back-projects only the pixels inside the
image rectangle of the box's corners, keeps the points inside the grown box, thins them on a voxel grid and
estimates normals with Open3D (a k-nearest-neighbour plane fit, oriented towards the camera at the origin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from sequences.reader import Sequence

#: neighbours of a point's plane fit: 16 at a 4 mm spacing spans about 1.5 cm, wide enough to average the sensor's
#: quantisation steps, narrow enough to keep a mug's rim and a box's edges
NORMAL_NEIGHBOURS = 16


@dataclass
class Crop:
    """Points (N, 3) and unit normals (N, 3) in the camera frame (m), normals facing the camera."""

    points: np.ndarray
    normals: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def box_corners(pose: np.ndarray, half: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3), camera frame, of a box with half sides ``half`` (m) at ``pose`` (object to camera)."""
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    return (signs * half) @ pose[:3, :3].T + pose[:3, 3]


class FrameCrops:
    """Crops of a sequence's frames by oriented boxes, the depth images read once."""

    def __init__(self, sequence: Sequence, stride: int, voxel: float) -> None:
        self.sequence, self.stride, self.voxel = sequence, int(stride), float(voxel)
        self._depth: dict[str, np.ndarray] = {}
        camera = sequence.camera
        self.fx, self.fy, self.cx, self.cy = camera.fx, camera.fy, camera.cx, camera.cy

    def depth(self, frame_id: str) -> np.ndarray:
        """The frame's depth (h, w) float32 metres at every ``stride``-th pixel; 0 = none."""
        if frame_id not in self._depth:
            self._depth[frame_id] = np.ascontiguousarray(self.sequence.depth(frame_id)[:: self.stride, :: self.stride])
        return self._depth[frame_id]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Subsampled pixel rows, columns (int) and depths (m) of camera-frame points (N, 3)."""
        z = points[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (points[:, 0] * self.fx / z + self.cx) / self.stride
            v = (points[:, 1] * self.fy / z + self.cy) / self.stride
        return np.round(np.nan_to_num(v, nan=-1)).astype(np.int64), np.round(np.nan_to_num(u, nan=-1)).astype(np.int64), z

    def points_in_box(self, frame_id: str, pose: np.ndarray, half: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) of the frame inside the box (half sides ``half``, m) at ``pose``."""
        depth = self.depth(frame_id)
        h, w = depth.shape
        corners = box_corners(pose, half)
        if np.all(corners[:, 2] > 1e-3):
            rows, cols, _ = self.project(corners)
            r0, r1 = np.clip([rows.min(), rows.max() + 1], 0, h)
            c0, c1 = np.clip([cols.min(), cols.max() + 1], 0, w)
        else:  # the camera is inside or behind the box: every pixel may hold a point of it
            r0, r1, c0, c1 = 0, h, 0, w
        window = depth[r0:r1, c0:c1]
        v, u = np.nonzero(window > 0)
        z = window[v, u].astype(np.float64)
        u_full, v_full = (u + c0) * self.stride, (v + r0) * self.stride
        points = np.stack([(u_full - self.cx) / self.fx * z, (v_full - self.cy) / self.fy * z, z], axis=1)
        local = (points - pose[:3, 3]) @ pose[:3, :3]
        return points[np.all(np.abs(local) <= half, axis=1)]

    def crop(self, frame_id: str, pose: np.ndarray, half: np.ndarray, max_points: int = 0, seed: int = 0) -> Crop:
        """The frame's points in the box, thinned to the voxel grid, with normals facing the camera; at most
        ``max_points`` of them (a seeded subset; 0: all)."""
        points = self.points_in_box(frame_id, pose, half)
        if len(points) < 3:
            return Crop(np.empty((0, 3)), np.empty((0, 3)))
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(self.voxel)
        if len(cloud.points) >= 3:
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
            cloud.orient_normals_towards_camera_location(np.zeros(3))
        points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
        if len(normals) != len(points):
            return Crop(np.empty((0, 3)), np.empty((0, 3)))
        if max_points and len(points) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))
            points, normals = points[keep], normals[keep]
        return Crop(points, normals)
