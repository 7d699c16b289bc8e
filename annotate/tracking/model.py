"""The accumulated object model: a voxel grid in the object frame (metres), fed frame by frame.

Each voxel keeps the sum of the points and colours that fell in it and the number of frames
that hit it. A frame counts once per voxel, so ``hits`` says in how many frames a surface was
seen: the object's surface is seen again and again, while a hand that regrasps moves relative
to the object and leaves voxels with few hits. :meth:`ObjectModel.target` keeps voxels seen
in at least ``min_hits`` frames (falling back to all voxels while the model is young).
"""

from __future__ import annotations

import numpy as np

from evaluate.geometry import transform

from .registration import ModelTarget

_OFFSET = 1 << 20  # voxel indices are packed into one int64 key, 21 bits per axis


class ObjectModel:
    """Voxel-downsampled point model of one object in its own frame (ShapeNet axes, box-centred)."""

    def __init__(self, voxel_size: float, extents: np.ndarray | None = None, margin: float = 0.01) -> None:
        self.voxel_size = float(voxel_size)
        self.half = None if extents is None else np.asarray(extents, dtype=np.float64) / 2 + margin
        self.keys = np.zeros(0, dtype=np.int64)
        self.sum_xyz = np.zeros((0, 3))
        self.sum_rgb = np.zeros((0, 3))
        self.sum_view = np.zeros((0, 3))  # unit vectors from the points towards the camera that saw them, object frame
        self.count = np.zeros(0, dtype=np.int64)
        self.hits = np.zeros(0, dtype=np.int64)
        self.frames = 0
        self._target: ModelTarget | None = None
        self._target_key: tuple | None = None
        self._adds_since_target = 0

    def copy(self) -> "ObjectModel":
        other = ObjectModel(self.voxel_size)
        other.half = self.half
        other.keys, other.sum_xyz, other.sum_rgb = self.keys.copy(), self.sum_xyz.copy(), self.sum_rgb.copy()
        other.sum_view = self.sum_view.copy()
        other.count, other.hits, other.frames = self.count.copy(), self.hits.copy(), self.frames
        return other

    def __len__(self) -> int:
        return len(self.keys)

    def _keys(self, points: np.ndarray) -> np.ndarray:
        idx = np.floor(points / self.voxel_size).astype(np.int64) + _OFFSET
        return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]

    def add(self, points_obj: np.ndarray, colors: np.ndarray | None = None, weight: int = 1, views: np.ndarray | None = None) -> None:
        """Add one frame's points (N, 3), already in the object frame, with colours (N, 3) in 0..1 and
        the unit directions (N, 3) from each point towards the camera, object frame (None: unknown).

        ``weight`` counts the frame as that many sightings (a trusted frame, e.g. a manual one).
        """
        self._merge([self._frame_voxels(points_obj, colors, views, weight)])

    def add_frame(self, points_cam: np.ndarray, colors: np.ndarray | None, pose: np.ndarray, weight: int = 1) -> None:
        """Add camera-frame points seen at ``pose`` (4x4 object to camera)."""
        self.add_frames([(points_cam, colors, pose, weight)])

    def add_frames(self, frames: list[tuple[np.ndarray, np.ndarray | None, np.ndarray, int]]) -> None:
        """Add several frames at once, each (camera-frame points (N, 3), colours or None, pose 4x4 object to camera,
        weight): the same model as adding them one by one in that order, bit for bit, with one merge instead of one
        per frame (a model of 60 laptop frames merged 60 times its growing voxel list)."""
        self.add_parts([self.frame_part(*frame) for frame in frames])

    def frame_part(self, points_cam: np.ndarray, colors: np.ndarray | None, pose: np.ndarray, weight: int = 1) -> tuple:
        """A frame's voxels in this model's grid (camera-frame points (N, 3) seen at ``pose``, 4x4 object to camera), to
        add with :meth:`add_parts`: the same for any model of the same voxel size and box."""
        points_obj, views = _object_frame(points_cam, pose)
        return self._frame_voxels(points_obj, colors, views, weight)

    def grid_key(self) -> tuple:
        """What a frame's part depends on besides the frame: the voxel size and the box's half sides."""
        return (self.voxel_size, None if self.half is None else self.half.tobytes())

    def add_parts(self, parts: list[tuple]) -> None:
        """Add frames' parts (:meth:`frame_part`, in frame order): as :meth:`add_frames` would add those frames."""
        self._merge(parts)

    def _frame_voxels(self, points_obj: np.ndarray, colors: np.ndarray | None = None, views: np.ndarray | None = None, weight: int = 1):
        """One frame's voxels: (sorted keys, their sums of points, colours and view directions, point counts, weight)."""
        points_obj = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3)
        colors = np.zeros_like(points_obj) if colors is None else np.asarray(colors, dtype=np.float64).reshape(-1, 3)
        views = np.zeros_like(points_obj) if views is None else np.asarray(views, dtype=np.float64).reshape(-1, 3)
        keep = np.all(np.isfinite(points_obj), axis=1)
        if self.half is not None:
            keep &= np.all(np.abs(points_obj) <= self.half, axis=1)
        points_obj, colors, views = points_obj[keep], colors[keep], views[keep]
        keys, inverse = np.unique(self._keys(points_obj), return_inverse=True)
        n = len(keys)
        return keys, _sum_rows(inverse, points_obj, n), _sum_rows(inverse, colors, n), _sum_rows(inverse, views, n), np.bincount(inverse, minlength=n), weight

    def _merge(self, parts: list[tuple]) -> None:
        """Add frames' voxels (:meth:`_frame_voxels`, in frame order) to the model.

        Each voxel's sums are summed in frame order, the model's own first (bincount adds its rows in order), as one
        merge per frame would: ``((model + frame 1) + frame 2) + ...``.
        """
        self.frames += len(parts)
        self._adds_since_target += len(parts)
        parts = [part for part in parts if len(part[0])]
        if not parts:
            return
        merged, inv = np.unique(np.concatenate([self.keys] + [part[0] for part in parts]), return_inverse=True)
        m = len(merged)
        self.sum_xyz = _sum_rows(inv, np.concatenate([self.sum_xyz] + [part[1] for part in parts]), m)
        self.sum_rgb = _sum_rows(inv, np.concatenate([self.sum_rgb] + [part[2] for part in parts]), m)
        self.sum_view = _sum_rows(inv, np.concatenate([self.sum_view] + [part[3] for part in parts]), m)
        self.count = np.bincount(inv, weights=np.concatenate([self.count] + [part[4] for part in parts]), minlength=m).astype(np.int64)
        hits = np.concatenate([self.hits] + [np.full(len(part[0]), part[5]) for part in parts])
        self.hits = np.bincount(inv, weights=hits, minlength=m).astype(np.int64)
        self.keys = merged

    def keep(self, mask: np.ndarray) -> None:
        """Drop the voxels where ``mask`` (len(self),) is False (e.g. seen through by other frames)."""
        mask = np.asarray(mask, dtype=bool)
        self.keys, self.sum_xyz, self.sum_rgb = self.keys[mask], self.sum_xyz[mask], self.sum_rgb[mask]
        self.sum_view = self.sum_view[mask]
        self.count, self.hits = self.count[mask], self.hits[mask]
        self._target, self._target_key = None, None

    def points(self, min_hits: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Voxel centroids (M, 3) in the object frame and mean colours (M, 3), of voxels hit in >= ``min_hits`` frames."""
        keep = self.hits >= min_hits
        count = self.count[keep][:, None].astype(np.float64)
        return self.sum_xyz[keep] / count, self.sum_rgb[keep] / count

    def target(self, min_hits: int = 1, min_share: float = 0.5, refresh_every: int = 1) -> ModelTarget:
        """The registration target, cached until the model changes (or ``refresh_every`` frames were added).

        Uses voxels hit in >= ``min_hits`` frames unless that would keep less than ``min_share``
        of the voxels (a young model, seen from few frames), then all of them. Rebuilding costs
        a normal estimation, so a growing chain model refreshes it only every few frames.
        """
        key = (len(self.keys), int(self.hits.sum()), min_hits)
        stale = self._target_key != key and self._adds_since_target >= refresh_every
        if self._target is None or stale or (self._target_key is not None and self._target_key[2] != min_hits):
            hits = min_hits if np.count_nonzero(self.hits >= min_hits) >= min_share * len(self.hits) else 1
            points, colors = self.points(hits)
            keep = self.hits >= hits
            # the mean of the unit view directions: short where the voxel was seen from both sides (a thin wall)
            self._target = ModelTarget(points, colors, self.voxel_size, self.sum_view[keep] / self.count[keep][:, None])
            self._target_key = key
            self._adds_since_target = 0
        return self._target

    def prepare(self, min_hits: int = 1) -> ModelTarget:
        """The registration target (:meth:`target`) with its normals and search grid built now: before the work forks,
        so the workers inherit them instead of each building its own."""
        target = self.target(min_hits)
        target.grid()
        return target


def _sum_rows(index: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """Sums (count, 3) of the rows of ``values`` (N, 3) by ``index`` (N,): np.add.at's result, one bincount per column (faster)."""
    return np.stack([np.bincount(index, weights=values[:, k], minlength=count) for k in range(3)], axis=1)


def _object_frame(points_cam: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) seen at ``pose`` (4x4 object to camera) in the object frame, and the unit directions
    from them towards the camera, object frame."""
    R, t = pose[:3, :3], pose[:3, 3]
    points_cam = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    towards = -points_cam / np.maximum(np.linalg.norm(points_cam, axis=1, keepdims=True), 1e-12)
    return (points_cam - t) @ R, towards @ R


def object_points(points_cam: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) to the object frame of ``pose`` (4x4 object to camera)."""
    return transform(np.linalg.inv(pose), points_cam)
