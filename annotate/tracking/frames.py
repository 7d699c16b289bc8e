"""Reading a frame's points once and cropping them by a box, for the tracker."""

from __future__ import annotations

from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import open3d as o3d

from evaluate.geometry import untransform
from sequences.errors import InputError
from sequences.reader import Sequence

from annotate.workers import ordered_map

#: a batch of crops forks workers only from this many crops to compute (a fork costs ~20 ms, a laptop crop 1-3 ms)
MIN_FORKED_CROPS = 16
#: a held crop (:meth:`FrameStore.hold`) reaches this far (m) beyond the box on each side: a later crop's box may move
#: about this far less its own margin (a registration's 1 cm, the slide check's 3 cm) and still be cut from it
HELD_MARGIN_M = 0.04


class FrameStore:
    """Caches each frame's depth (subsampled by ``stride``, metres) and colours; crops them by a box.

    A crop back-projects only the pixels inside the box's projected outline (its image rectangle),
    not the whole frame: a 10 cm object covers a few percent of the image. The last
    ``crop_cache`` crops are kept: the tracker crops the same frame at the same pose again (a
    model of the trusted poses is built twice between two pose updates, and the smoothing crops
    the frames its model was just built from).

    Once the poses are roughly known, :meth:`hold` keeps a wider voxelled crop per frame, and the later voxelled
    crops of that frame are cut from it: after the chains, a laptop frame is cropped some 15 more times at poses a
    few millimetres apart (the refinement's rounds and restarts, the models, the rechecks, the slide check).
    """

    def __init__(self, sequence: Sequence, stride: int = 2, cache: bool = True, colors: bool = True, crop_cache: int = 256) -> None:
        self.sequence = sequence
        self.colors = colors
        self.stride = int(stride)
        self.cache = cache
        self.crop_cache = int(crop_cache) if cache else 0
        self._frames: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        self._crops: OrderedDict[tuple, tuple[np.ndarray, np.ndarray | None]] = OrderedDict()
        self.errors: dict[str, str] = {}
        # (frame, voxel, extents) -> the pose a crop was held at, its half sides (m) and its points and colours
        self._held: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]] = {}
        # frames' voxels as models added them, kept for models that take them again (Tracker.add_frames_to_model)
        self.model_parts: OrderedDict[tuple, tuple] = OrderedDict()

    def image(self, frame_id: str) -> tuple[np.ndarray, np.ndarray | None]:
        """Subsampled depth (h, w) float32 metres (0 = none) and colours (h, w, 3) float32 0..1 or None."""
        if frame_id in self._frames:
            return self._frames[frame_id]
        return self._store(frame_id, self._read(frame_id))

    def preload(self, frame_ids: list[str], threads: int = 1) -> None:
        """Read and keep the frames not kept yet, decoding up to ``threads`` at a time: the image decoders release
        the GIL (two threads read a sequence in about two thirds of one's time, into the same arrays). The frames are kept, and their errors noted, in the order given."""
        if not self.cache:
            return  # nothing would be kept
        todo = list(dict.fromkeys(f for f in frame_ids if f not in self._frames))
        if threads <= 1 or len(todo) < 2:
            for frame_id in todo:
                self.image(frame_id)
            return
        # the threads end before this returns: none is left running when the tracker forks its workers
        with ThreadPoolExecutor(min(int(threads), len(todo))) as pool:
            for frame_id, read in zip(todo, pool.map(self._read, todo)):
                self._store(frame_id, read)

    def _read(self, frame_id: str) -> tuple[np.ndarray, np.ndarray | None, str | None]:
        """A frame's subsampled depth and colours (None without colours), and its read error (None if read)."""
        s = self.stride
        try:
            depth = np.ascontiguousarray(self.sequence.depth(frame_id)[::s, ::s])
            color = np.ascontiguousarray(self.sequence.color(frame_id)[::s, ::s]).astype(np.float32) / 255.0 if self.colors else None
            return depth, color, None
        except InputError as error:  # a corrupt or empty frame: no points, the frame gets flagged
            camera = self.sequence.camera
            return np.zeros(((camera.height + s - 1) // s, (camera.width + s - 1) // s), np.float32), None, str(error)

    def _store(self, frame_id: str, read: tuple[np.ndarray, np.ndarray | None, str | None]) -> tuple[np.ndarray, np.ndarray | None]:
        """Note a read's error and keep its images (with the cache on); the images."""
        depth, color, error = read
        if error is not None:
            self.errors[frame_id] = error
        out = (depth, color)
        if self.cache:
            self._frames[frame_id] = out
        return out

    def crop(self, frame_id: str, pose: np.ndarray, extents: np.ndarray, margin: float, voxel: float | None = None,
             keep: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 3) m camera frame and colours (N, 3) 0..1 of a frame inside the box at ``pose``
        (4x4 object to camera, full sides ``extents``) grown by ``margin`` (m); voxel-downsampled to ``voxel``.

        The arrays are the caller's own (a repeated crop returns copies of the kept one). ``keep=False``: the crop
        is neither looked up nor kept (a one-off crop at full resolution, ten times a voxel crop's size, would push
        the registrations' crops out of the cache).
        """
        if voxel and keep:
            held = self._from_held(frame_id, pose, extents, margin, voxel)
            if held is not None:
                return held
        if self.crop_cache <= 0 or not keep:
            points, colors = self._crop(frame_id, pose, extents, margin, voxel)
            return points, (colors if colors is not None else np.zeros_like(points))
        key = _crop_key(frame_id, pose, extents, margin, voxel)
        if key in self._crops:
            self._crops.move_to_end(key)
            return _owned(self._crops[key])
        return _owned(self._keep(key, self._crop(frame_id, pose, extents, margin, voxel)))

    def crops(self, requests: list[tuple[str, np.ndarray]], extents: np.ndarray, margin: float, voxel: float | None = None,
              workers: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`crop` of each (frame id, pose) in ``requests``: the same arrays, with the crops not kept computed on up
        to ``workers`` processes (workers.ordered_map) and then kept here (the cache's order of use may differ from a
        loop of :meth:`crop`'s: which crops stay kept, not what they hold). Without a cache, on this process: a frame
        read here and not kept would be read again on the worker.

        A model of 60 frames is 60 crops (a laptop: 1-3 ms each) that need nothing of each other.
        """
        held = [self._from_held(f, pose, extents, margin, voxel) if voxel else None for f, pose in requests]
        rest = [i for i, h in enumerate(held) if h is None]
        if rest:
            for i, crop in zip(rest, self._image_crops([requests[i] for i in rest], extents, margin, voxel, workers)):
                held[i] = crop
        return held

    def _image_crops(self, requests: list[tuple[str, np.ndarray]], extents: np.ndarray, margin: float, voxel: float | None,
                     workers: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`crops` of requests that no held crop serves."""
        if not self.cache:
            workers = 1
        keys = [_crop_key(f, pose, extents, margin, voxel) for f, pose in requests]
        kept = {key: self._crops[key] for key in keys if key in self._crops}  # before this batch's crops push any out
        todo, seen = [], set()
        for i, key in enumerate(keys):
            if key not in kept and key not in seen:
                seen.add(key)
                todo.append(i)
        for i in todo:  # read here: a frame read on a worker, and its read error, would be lost to this process
            self.image(requests[i][0])
        computed = dict(zip((keys[i] for i in todo), ordered_map(lambda i: self._crop(*requests[i], extents, margin, voxel), todo,
                                                                 workers if len(todo) >= MIN_FORKED_CROPS else 1)))
        out = []
        for key in keys:
            if key in computed:
                crop = self._keep(key, computed[key]) if self.crop_cache > 0 else computed[key]
            else:
                crop = kept[key]
                if key in self._crops:
                    self._crops.move_to_end(key)
            out.append(_owned(crop))
        return out

    def hold(self, requests: list[tuple[str, np.ndarray]], extents: np.ndarray, voxel: float, workers: int = 1) -> None:
        """Keep, for each (frame id, pose 4x4) of ``requests``, its crop by the box (full sides ``extents``, m) grown by
        ``HELD_MARGIN_M`` at that pose, voxel-downsampled to ``voxel``, computed on up to ``workers`` processes.

        Later crops of the frame at that voxel (:meth:`crop`, :meth:`crops`, with ``keep``) whose box (its margin
        included) lies inside the held one are cut from it: its voxels whose centre lies in the box. They differ from a
        crop of the image only along the box's faces: a voxel there is the mean of all its points, or left out, where
        the image's crop averages only the points inside (a voxel-wide seam, where the background and a hand lie). A
        frame held again replaces what was held.
        """
        half = np.asarray(extents, dtype=np.float64) / 2 + HELD_MARGIN_M
        for frame_id, _ in requests:  # read here: a frame read on a worker, and its read error, would be lost to this process
            self.image(frame_id)
        if not self.cache:
            workers = 1
        held = ordered_map(lambda r: self._crop(r[0], r[1], extents, HELD_MARGIN_M, voxel), requests, workers if len(requests) >= MIN_FORKED_CROPS else 1)
        for (frame_id, pose), (points, colors) in zip(requests, held):
            self._held[_held_key(frame_id, extents, voxel)] = (np.array(pose, dtype=np.float64), half, points, colors)

    def _from_held(self, frame_id: str, pose: np.ndarray, extents: np.ndarray, margin: float, voxel: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The crop cut from the frame's held crop (:meth:`hold`; points, colours as :meth:`crop` returns them), or None
        where none is held or the box grown by ``margin`` at ``pose`` reaches outside it."""
        held = self._held.get(_held_key(frame_id, extents, voxel))
        if held is None:
            return None
        at, reach, points, colors = held
        half = np.asarray(extents, dtype=np.float64) / 2 + margin
        if not np.all(np.abs(untransform(at, _corners(pose, half))) <= reach):
            return None
        local = np.abs(untransform(pose, points))
        inside = (local[:, 0] <= half[0]) & (local[:, 1] <= half[1]) & (local[:, 2] <= half[2])
        return points[inside], (colors[inside] if colors is not None else np.zeros((int(np.count_nonzero(inside)), 3)))

    def _keep(self, key: tuple, crop: tuple[np.ndarray, np.ndarray | None]) -> tuple[np.ndarray, np.ndarray | None]:
        """Keep ``crop`` (points, colours or None) under ``key``, the least recently used crop dropped beyond
        ``crop_cache``; ``crop`` itself."""
        self._crops[key] = crop
        if len(self._crops) > self.crop_cache:
            self._crops.popitem(last=False)
        return crop

    def _crop(self, frame_id: str, pose: np.ndarray, extents: np.ndarray, margin: float, voxel: float | None) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`crop`'s points and colours (None without colours)."""
        depth, color = self.image(frame_id)
        camera, s = self.sequence.camera, self.stride
        half = np.asarray(extents, dtype=np.float64) / 2 + margin
        corners = _corners(pose, half)
        empty = np.zeros((0, 3))
        if not np.all(np.isfinite(corners)) or np.all(corners[:, 2] <= 0):
            return empty, empty
        h, w = depth.shape
        if np.any(corners[:, 2] <= 1e-3):  # the box reaches behind the camera: search the whole image
            u0, v0, u1, v1 = 0, 0, w, h
        else:
            u = (camera.fx * corners[:, 0] / corners[:, 2] + camera.cx) / s
            v = (camera.fy * corners[:, 1] / corners[:, 2] + camera.cy) / s
            u0, u1 = int(np.clip(np.floor(u.min()), 0, w)), int(np.clip(np.ceil(u.max()) + 1, 0, w))
            v0, v1 = int(np.clip(np.floor(v.min()), 0, h)), int(np.clip(np.ceil(v.max()) + 1, 0, h))
        patch = depth[v0:v1, u0:u1]
        # a point inside the box lies within the depth range of its corners: the background behind a
        # large box (a laptop's rectangle is mostly table) is dropped before any back-projection
        near, far = max(corners[:, 2].min() - 1e-6, 1e-6), corners[:, 2].max() + 1e-6  # 1 um: rounding of the box test
        vv, uu = np.nonzero((patch >= near) & (patch <= far))
        z = patch[vv, uu].astype(np.float64)
        # back-projected per column and row once, then per pixel: the same values as per pixel throughout
        x = ((np.arange(u0, u1) * s - camera.cx) / camera.fx)[uu] * z
        y = ((np.arange(v0, v1) * s - camera.cy) / camera.fy)[vv] * z
        # the box test one coordinate at a time, before any (N, 3) array: most of a laptop's rectangle is table
        R, t = pose[:3, :3], pose[:3, 3]
        dx, dy, dz = x - t[0], y - t[1], z - t[2]
        keep = np.abs(dx * R[0, 0] + dy * R[1, 0] + dz * R[2, 0]) <= half[0]
        keep &= np.abs(dx * R[0, 1] + dy * R[1, 1] + dz * R[2, 1]) <= half[1]
        keep &= np.abs(dx * R[0, 2] + dy * R[1, 2] + dz * R[2, 2]) <= half[2]
        kept = np.flatnonzero(keep)
        points = np.stack([x[kept], y[kept], z[kept]], axis=1)
        colors = color[v0 + vv[kept], u0 + uu[kept]].astype(np.float64) if color is not None else None
        if voxel and len(points):
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            if colors is not None:
                cloud.colors = o3d.utility.Vector3dVector(colors)
            cloud = cloud.voxel_down_sample(voxel)
            points = np.asarray(cloud.points)
            colors = np.asarray(cloud.colors) if colors is not None else None
        return points, colors


def _owned(crop: tuple[np.ndarray, np.ndarray | None]) -> tuple[np.ndarray, np.ndarray]:
    """A kept crop's points and colours as the caller's own arrays (zeros for colours without colours)."""
    points, colors = crop
    return points.copy(), (colors.copy() if colors is not None else np.zeros_like(points))


def _corners(pose: np.ndarray, half: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) m, camera frame, of the box with half sides ``half`` (3,) at ``pose`` (4x4 object to camera)."""
    corners = (np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)]) * 2 - 1) * half
    return corners @ pose[:3, :3].T + pose[:3, 3]


def _held_key(frame_id: str, extents: np.ndarray, voxel: float) -> tuple:
    """The held crops' key: the frame, the box's sides to the last bit and the voxel."""
    return (frame_id, np.asarray(extents, dtype=np.float64).tobytes(), float(voxel))


def _crop_key(frame_id: str, pose: np.ndarray, extents: np.ndarray, margin: float, voxel: float | None) -> tuple:
    """The crop cache's key: the frame, the pose and extents to the last bit, the margin and the voxel."""
    return (frame_id, np.asarray(pose, dtype=np.float64).tobytes(), np.asarray(extents, dtype=np.float64).tobytes(), float(margin), voxel)
