"""The pinhole RGB-D camera: intrinsics, depth scale, projection and back-projection.

Frames: OpenCV camera (x right, y down, z forward), metres. Pixel centres at integer
coordinates: pixel (u, v) covers [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5].
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .documents import load_mapping
from .errors import InputError


#: Plausible values of an RGB-D camera: focal length (pixels), image side (pixels), depth scale (metres per unit).
FOCAL_RANGE = (100.0, 5000.0)
SIZE_RANGE = (16, 8192)
DEPTH_SCALE_RANGE = (1e-5, 0.1)


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics (pixels) and depth scale (metres per depth unit). Defaults: Redwood's PrimeSense."""

    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    width: int = 640
    height: int = 480
    depth_scale: float = 0.001

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (height, width)."""
        return (self.height, self.width)

    def to_dict(self) -> dict:
        return asdict(self)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points (N, 3) to pixel coordinates (N, 2) (u, v) and depths z (N,)."""
        points = np.asarray(points, dtype=np.float64)
        z = points[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * points[..., 0] / z + self.cx
            v = self.fy * points[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1), z

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame ray directions with z = 1 through each pixel centre."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        rays = np.empty((self.height, self.width, 3))
        rays[..., 0] = u[None, :]
        rays[..., 1] = v[:, None]
        rays[..., 2] = 1.0
        return rays

    def window(self, points: np.ndarray, slack: int = 1) -> tuple[slice, slice]:
        """(rows, cols): the pixel rectangle that holds the projections of camera-frame ``points`` (N, 3, metres), with
        ``slack`` pixels beyond on every side, clipped to the image; the whole image when a point lies within 1 mm of
        the camera plane or behind it (its projection is no bound)."""
        points = np.asarray(points, dtype=np.float64)
        if not len(points) or points[:, 2].min() <= 1e-3:
            return slice(0, self.height), slice(0, self.width)
        u, v = self.project(points)[0].T
        cols = slice(int(np.clip(np.floor(u.min()) - slack, 0, self.width)), int(np.clip(np.ceil(u.max()) + slack + 1, 0, self.width)))
        rows = slice(int(np.clip(np.floor(v.min()) - slack, 0, self.height)), int(np.clip(np.ceil(v.max()) + slack + 1, 0, self.height)))
        return rows, cols

    def backproject(self, depth: np.ndarray, mask: np.ndarray | None = None, stride: int = 1,
                    window: tuple[slice, slice] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Back-project a depth image (H, W) in metres (0 or NaN = no measurement).

        Returns camera-frame points (N, 3) float64 and their flat pixel indices (N,) into the
        image, for the valid pixels where ``mask`` (H, W bool) is true. With ``stride`` only every
        ``stride``-th pixel of every ``stride``-th row counts (a decimated cloud; the indices stay
        those of the full image). With ``window`` ((rows, cols) slices, :meth:`window`) only its
        pixels count: the same points as without it, less those outside.
        """
        depth = np.asarray(depth)
        rows, cols = window if window is not None else (slice(0, depth.shape[0]), slice(0, depth.shape[1]))
        r0, c0 = rows.start + -rows.start % stride, cols.start + -cols.start % stride  # the window's first on the image's stride grid
        sub = depth[r0:rows.stop:stride, c0:cols.stop:stride]
        valid = np.isfinite(sub) & (sub > 0)
        if mask is not None:
            valid &= np.asarray(mask, dtype=bool)[r0:rows.stop:stride, c0:cols.stop:stride]
        v, u = np.nonzero(valid)  # row-major, as the flat indices
        z = sub[v, u].astype(np.float64)
        v, u = v * stride + r0, u * stride + c0
        points = np.empty((z.size, 3))
        points[:, 0] = (u - self.cx) / self.fx * z
        points[:, 1] = (v - self.cy) / self.fy * z
        points[:, 2] = z
        return points, v * depth.shape[1] + u

    def plausible(self, path: str | Path) -> "Camera":
        """This camera, or InputError naming ``path`` when a value is implausible for an RGB-D camera: focal lengths
        outside FOCAL_RANGE pixels, an image size outside SIZE_RANGE, a principal point outside the image, a depth
        scale outside DEPTH_SCALE_RANGE metres per unit."""
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not FOCAL_RANGE[0] <= value <= FOCAL_RANGE[1]:
                raise InputError(path, f"{name} = {value:g} px is outside {FOCAL_RANGE[0]}-{FOCAL_RANGE[1]} px (an RGB-D camera's focal length)")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not SIZE_RANGE[0] <= value <= SIZE_RANGE[1]:
                raise InputError(path, f"{name} = {value} px is outside {SIZE_RANGE[0]}-{SIZE_RANGE[1]} px")
        if not (0 <= self.cx <= self.width and 0 <= self.cy <= self.height):
            raise InputError(path, f"the principal point ({self.cx:g}, {self.cy:g}) lies outside the {self.width}x{self.height} image")
        if not DEPTH_SCALE_RANGE[0] <= self.depth_scale <= DEPTH_SCALE_RANGE[1]:
            raise InputError(path, f"depth_scale {self.depth_scale} m per unit is implausible (expected about 0.001 for millimetres)")
        return self

    @classmethod
    def from_matrix(cls, path: str | Path, K, depth_scale, width: int = 640, height: int = 480) -> "Camera":
        """The camera of a 3x3 intrinsic matrix ``K`` and a depth scale (metres per unit) that a dataset file
        (``path``, named in errors) gives; InputError when either is malformed."""
        try:
            K = np.asarray(K, dtype=np.float64).reshape(3, 3)
            depth_scale = float(depth_scale)
        except (TypeError, ValueError) as error:
            raise InputError(path, f"the intrinsic matrix or the depth scale is malformed ({error.__class__.__name__})") from error
        if not (np.all(np.isfinite(K)) and np.isfinite(depth_scale) and depth_scale > 0):
            raise InputError(path, "the intrinsic matrix must be finite and the depth scale positive")
        return cls(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]), width=width, height=height, depth_scale=depth_scale).plausible(path)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Camera":
        """Read ``camera.yaml`` (fx, fy, cx, cy, width, height, depth_scale; any subset overrides the defaults)."""
        path = Path(path)
        data = load_mapping(path, "camera", ("fx", "fy", "cx", "cy", "width", "height", "depth_scale"), as_yaml=True)
        values = {}
        for key, value in data.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                if key in ("cx", "cy") and isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                    values[key] = float(value)
                    continue
                raise InputError(path, f"{key} must be a positive finite number, got {value!r}")
            values[key] = int(value) if key in ("width", "height") else float(value)
        for key in ("width", "height"):
            if key in data and float(data[key]) != int(data[key]):
                raise InputError(path, f"{key} must be an integer, got {data[key]!r}")
        return cls(**values).plausible(path)
