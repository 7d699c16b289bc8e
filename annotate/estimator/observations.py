"""A frame's measured points near a box: camera frame, metres, with normals that face the camera.

Each depth image is read once and kept subsampled (``stride``); a crop back-projects only the pixels inside the
image rectangle of the box's corners, keeps the points inside the grown box, leaves out the scene's planes where the
object moves (scene.py), thins them on a voxel grid and estimates normals with Open3D (a k-nearest-neighbour plane
fit, oriented towards the camera at the origin).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from sequences.reader import Sequence
from sequences.sensor_noise import depth_sigma

from .scene import (BEYOND, BEYOND_SHARE, DROP_SIGMAS, MAX_CROP_SHARE, PLANE_PIXEL_STEP, STILL_SHARE, STILL_SHIFT,
                    STILL_TURN, changed_share, scene_planes)

#: neighbours of a point's plane fit: 16 at a 4 mm spacing spans about 1.5 cm, wide enough to average the sensor's
#: quantisation steps, narrow enough to keep a mug's rim and a box's edges
NORMAL_NEIGHBOURS = 16


def _same_plane(normal: np.ndarray, d: float, other: np.ndarray, e: float) -> bool:
    """Whether planes (unit normal, offset; either orientation) lie within STILL_TURN and STILL_SHIFT of each other."""
    cos = normal @ other
    return bool(np.degrees(np.arccos(min(abs(cos), 1.0))) <= STILL_TURN and abs(d - np.sign(cos) * e) <= STILL_SHIFT)


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
        self._planes: dict[str, list] = {}
        self._order = {f: k for k, f in enumerate(sequence.ids)}
        camera = sequence.camera
        self.fx, self.fy, self.cx, self.cy = camera.fx, camera.fy, camera.cx, camera.cy

    def depth(self, frame_id: str) -> np.ndarray:
        """The frame's depth (h, w) float32 metres at every ``stride``-th pixel; 0 = none."""
        if frame_id not in self._depth:
            self._depth[frame_id] = np.ascontiguousarray(self.sequence.depth(frame_id)[:: self.stride, :: self.stride])
        return self._depth[frame_id]

    def planes(self, frame_id: str) -> list[tuple[np.ndarray, float, np.ndarray]]:
        """The frame's scene planes (:func:`scene_planes`), camera frame; found once."""
        if frame_id not in self._planes:
            z = self.depth(frame_id)[::PLANE_PIXEL_STEP, ::PLANE_PIXEL_STEP].astype(np.float64)
            v, u = np.mgrid[: z.shape[0], : z.shape[1]] * (PLANE_PIXEL_STEP * self.stride)
            grid = self._backproject(u, v, z)
            self._planes[frame_id] = scene_planes(grid, np.random.default_rng(zlib.crc32(frame_id.encode())))
        return self._planes[frame_id]

    def keep_planes(self, planes: dict[str, list]) -> None:
        """Scene planes of these frames (:meth:`planes`), found elsewhere (by worker processes)."""
        self._planes.update(planes)

    def moving(self, frame_id: str, pose: np.ndarray, half: np.ndarray) -> bool:
        """Whether the depth around the box (at ``pose``) changed from the frame before or to the frame after."""
        return self._moves(frame_id, self._window(frame_id, pose, half))

    def _moves(self, frame_id: str, window: tuple[slice, slice, float, float] | None) -> bool:
        """:meth:`moving` for the box's ``window`` (:meth:`_window`)."""
        return window is None or self._changed(frame_id, window)  # inside or behind the box: nothing says it rests

    def _window(self, frame_id: str, pose: np.ndarray, half: np.ndarray) -> tuple[slice, slice, float, float] | None:
        """The rectangle (rows, columns) of the frame's subsampled depth that the box projects into, and the box's depth
        range (m); None where the camera is inside or behind the box."""
        corners = box_corners(pose, half)
        if np.any(corners[:, 2] <= 1e-3):
            return None
        rows, cols, z = self.project(corners)
        h, w = self.depth(frame_id).shape
        rows = slice(max(rows.min(), 0), min(rows.max() + 1, h))
        return rows, slice(max(cols.min(), 0), min(cols.max() + 1, w)), z.min(), z.max()

    def _changed(self, frame_id: str, window: tuple[slice, slice, float, float]) -> bool:
        """Whether the depth in ``window`` (:meth:`_window`) changed from the frame before or to the frame after."""
        rows, cols, z_near, z_far = window
        ids, k = self.sequence.ids, self._order[frame_id]
        here = self.depth(frame_id)[rows, cols]
        return any(changed_share(here, self.depth(ids[j])[rows, cols], z_near, z_far) >= STILL_SHARE
                   for j in (k - 1, k + 1) if 0 <= j < len(ids))

    def still(self, frame_id: str, normal: np.ndarray, d: float) -> bool:
        """Whether the frame before and the frame after hold the same plane (unit ``normal``, offset ``d``; camera
        frame) within STILL_TURN and STILL_SHIFT: the camera did not move against it."""
        ids, k = self.sequence.ids, self._order[frame_id]
        for j in (k - 1, k + 1):
            if 0 <= j < len(ids) and not any(_same_plane(normal, d, n, e) for n, e, _ in self.planes(ids[j])):
                return False
        return True

    def _backproject(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) of full-resolution pixel columns ``u``, rows ``v`` and depths ``z`` (m)."""
        return np.stack([(u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z], axis=-1)

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
        window = self._window(frame_id, pose, half)
        # the camera inside or behind the box: every pixel may hold a point of it
        rows, cols = (slice(0, depth.shape[0]), slice(0, depth.shape[1])) if window is None else window[:2]
        seen = depth[rows, cols]
        v, u = np.nonzero(seen > 0)
        z = seen[v, u].astype(np.float64)
        points = self._backproject((u + cols.start) * self.stride, (v + rows.start) * self.stride, z)
        local = (points - pose[:3, 3]) @ pose[:3, :3]
        points = points[np.all(np.abs(local) <= half, axis=1)]
        # a plane that goes on beyond the box (a table, a wall) and stands still is the scene's: where the object moves,
        # its points in the box would hold the object's pose to where it stood; where the camera moves, the plane
        # moves too (and may hold an object standing on it)
        beyond = lambda inliers: np.mean(np.any(np.abs((inliers - pose[:3, 3]) @ pose[:3, :3]) > half + BEYOND, axis=1))
        scene = [(normal, d) for normal, d, inliers in self.planes(frame_id)
                 if beyond(inliers) >= BEYOND_SHARE and self.still(frame_id, normal, d)]
        if not scene:
            return points
        reach = DROP_SIGMAS * depth_sigma(points[:, 2])
        on = [np.abs(points @ normal + d) < reach for normal, d in scene]
        if not any(plane.any() for plane in on) or not self._moves(frame_id, window):
            return points  # nothing on the planes, or the object rests: what it rests on moves with it, and holds it
        dropped = np.zeros(len(points), dtype=bool)
        for plane in on:  # in turn: each plane's share is of the points the planes before left
            if plane[~dropped].mean() < MAX_CROP_SHARE:
                dropped |= plane
        return points[~dropped]

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
