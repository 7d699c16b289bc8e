"""Frames ready for display: decimated coloured points and the colour image, cached with look-ahead.

Switching frames must feel instant, so each frame is read and back-projected once at a pixel
stride (a 640x480 frame at stride 2 is at most 76,800 points), kept in a small LRU cache, and
the neighbours of the frame being shown are loaded in a background thread.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from sequences.reader import Sequence


@dataclass
class DisplayFrame:
    """One frame for the scene: camera-frame points (N, 3) float32 m, colours (N, 3) uint8, image (H, W, 3) uint8, and
    its depth (H, W) m (0: none) for placing by a click."""

    index: int
    points: np.ndarray
    colors: np.ndarray
    image: np.ndarray
    median_depth: float
    origin: np.ndarray  # (3,) float64 m: a point near the cloud's middle; positions are sent relative to it
    depth: np.ndarray | None = None


def load_display_frame(sequence: Sequence, index: int, stride: int = 2) -> DisplayFrame:
    """Read frame ``index`` and back-project every ``stride``-th pixel (rows and columns)."""
    image = sequence.color(index)
    depth = sequence.depth(index)
    cloud, pixels = sequence.camera.backproject(depth, stride=stride)
    points = cloud.astype(np.float32)  # back-projected in float64: sub-millimetre positions before the cast
    z = cloud[:, 2]
    colors = image.reshape(-1, image.shape[-1])[pixels]
    median = float(np.median(z)) if z.size else 1.0
    origin = np.array([0.0, 0.0, median])
    if z.size:
        origin[:2] = points[points.shape[0] // 2, :2]  # the middle pixel row's point: near the data, cheap
    return DisplayFrame(index, points, np.ascontiguousarray(colors, dtype=np.uint8), image, median, origin, np.asarray(depth, dtype=np.float32))


class FrameCache:
    """LRU cache of :class:`DisplayFrame` with background look-ahead of the neighbouring frames."""

    def __init__(self, sequence: Sequence, stride: int = 2, size: int = 12, lookahead: int = 2) -> None:
        self.sequence = sequence
        self.stride = stride
        self.size = size
        self.lookahead = lookahead
        self._frames: OrderedDict[int, DisplayFrame] = OrderedDict()
        self._pending: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-prefetch")

    def _store(self, frame: DisplayFrame) -> None:
        with self._lock:
            self._frames[frame.index] = frame
            self._frames.move_to_end(frame.index)
            while len(self._frames) > self.size:
                self._frames.popitem(last=False)
            self._pending.pop(frame.index, None)

    def get(self, index: int, prefetch: bool = True) -> DisplayFrame:
        """The display frame ``index`` (read now unless cached or being read), then prefetch its neighbours."""
        with self._lock:
            frame = self._frames.get(index)
            if frame is not None:
                self._frames.move_to_end(index)
            pending = self._pending.get(index)
        if frame is None:
            if pending is not None:
                frame = pending.result()
            else:
                frame = load_display_frame(self.sequence, index, self.stride)
                self._store(frame)
        if prefetch:
            self.prefetch(index)
        return frame

    def prefetch(self, index: int) -> None:
        """Start reading the frames around ``index`` that are not cached yet."""
        n = len(self.sequence)
        for k in range(1, self.lookahead + 1):
            for j in (index + k, index - k):
                if 0 <= j < n:
                    with self._lock:
                        if j in self._frames or j in self._pending:
                            continue
                        self._pending[j] = self._pool.submit(self._load, j)

    def _load(self, index: int) -> DisplayFrame:
        try:
            frame = load_display_frame(self.sequence, index, self.stride)
        except Exception:
            with self._lock:
                self._pending.pop(index, None)
            raise
        self._store(frame)
        return frame

    def cached(self, index: int) -> bool:
        with self._lock:
            return index in self._frames

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
