"""Per-frame instance masks of the visible object: the posed mesh ray-cast headless (Open3D RaycastingScene).

A pixel is in the mask where the mesh is hit and the measured depth does not lie in front of the
mesh by more than ``tolerance`` (a hand or another object occluding it); missing depth keeps the
pixel (nothing says it is occluded). The default tolerance, 1 cm, is cpas_toolbox's own for
REDWOOD75. Masks are written by :mod:`reconstruct.export` as ``OUT/masks/<sequence>/<frame id>.png``
(uint8, 0 = background, 255 = object).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import trimesh

from evaluate.rendering import MeshRenderer, visible_mask
from sequences.camera import Camera

DEFAULT_TOLERANCE = 0.01

#: Cells per axis of the mesh's bounding box that group its faces for the ray cover (see ClusterRenderer).
#: Measured on the v5 laptop, seed 0 (its 2 mm reconstruction, 209k faces, 100 frames, 62k pixels hit a
#: frame): the whole box's rectangle casts 139k rays a frame; 4 cells 78k, 8: 72k, 16: 69k, 32: 67k.
#: CPU for the 100 frames (load 5 on 2 cores): 6.9 s -> 2.1-2.4 s whatever the cells (the box's rays
#: were also built by a float64 matmul); one pixel of the 100 frames differs (a ray grazing an edge).
COVER_CELLS = 16

__all__ = ["COVER_CELLS", "DEFAULT_TOLERANCE", "ClusterRenderer", "MeshRenderer", "mask_png_bytes", "render_masks", "visible_mask"]


class ClusterRenderer(MeshRenderer):
    """A :class:`MeshRenderer` that casts only the pixels inside the projections of its face clusters' boxes.

    The faces are grouped by centroid into ``cells`` per axis of the mesh's bounding box; each group's
    box (object frame, metres) bounds its faces. A ray that hits the mesh hits a face inside one of those
    boxes, so its pixel lies in the rectangle of that box's projected corners (plus a pixel of rounding
    slack): the other pixels are misses without casting. Same depth as the whole box's rectangle cast,
    on fewer rays (an L-shaped laptop: about half of its box's rectangle is background).
    """

    def __init__(self, mesh: trimesh.Trimesh, camera: Camera, cells: int = COVER_CELLS) -> None:
        super().__init__(mesh, camera)
        triangles = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]  # (F, 3 vertices, 3)
        lo, hi = mesh.bounds
        cell = np.clip(((triangles.mean(axis=1) - lo) / np.maximum(hi - lo, 1e-12) * cells).astype(np.int64), 0, cells - 1)
        group = np.ravel_multi_index(cell.T, (cells,) * 3)
        order = np.argsort(group, kind="stable")
        starts = np.flatnonzero(np.r_[True, group[order][1:] != group[order][:-1]])
        box_lo = np.minimum.reduceat(triangles.min(axis=1)[order], starts, axis=0)  # (boxes, 3)
        box_hi = np.maximum.reduceat(triangles.max(axis=1)[order], starts, axis=0)
        corner = np.stack(np.unravel_index(np.arange(8), (2, 2, 2)), axis=1).astype(bool)  # (8, 3): hi where set
        self._boxes = np.where(corner[None], box_hi[:, None, :], box_lo[:, None, :])  # (boxes, 8, 3)
        # object-frame ray directions of the camera's columns and rows: R^T d = column term + row term
        self._columns = (np.arange(camera.width) - camera.cx) / camera.fx
        self._rows = (np.arange(camera.height) - camera.cy) / camera.fy

    def cover(self, pose: np.ndarray) -> np.ndarray | None:
        """(H, W) bool: the pixels whose rays may hit the mesh at ``pose``; None when a box reaches behind the camera."""
        pose = np.asarray(pose, dtype=np.float64)
        cam = self.camera
        points = self._boxes @ pose[:3, :3].T + pose[:3, 3]  # (boxes, 8, 3) camera frame
        if np.any(points[..., 2] <= 1e-6):
            return None
        uv, _ = cam.project(points.reshape(-1, 3))
        uv = uv.reshape(-1, 8, 2)
        # the same slack as MeshRenderer's rectangle: one pixel beyond the corners' floor / ceil
        x0 = np.clip(np.floor(uv[..., 0].min(axis=1)).astype(np.int64) - 1, 0, cam.width)
        y0 = np.clip(np.floor(uv[..., 1].min(axis=1)).astype(np.int64) - 1, 0, cam.height)
        x1 = np.clip(np.ceil(uv[..., 0].max(axis=1)).astype(np.int64) + 2, 0, cam.width)  # exclusive
        y1 = np.clip(np.ceil(uv[..., 1].max(axis=1)).astype(np.int64) + 2, 0, cam.height)
        keep = (x0 < x1) & (y0 < y1)
        x0, y0, x1, y1 = x0[keep], y0[keep], x1[keep], y1[keep]
        # union of rectangles: +1 / -1 at their corners, summed along both axes
        marks = np.zeros((cam.height + 1, cam.width + 1), dtype=np.int32)
        np.add.at(marks, (y0, x0), 1)
        np.add.at(marks, (y0, x1), -1)
        np.add.at(marks, (y1, x0), -1)
        np.add.at(marks, (y1, x1), 1)
        return np.cumsum(np.cumsum(marks, axis=0), axis=1)[: cam.height, : cam.width] > 0

    def depth(self, pose: np.ndarray) -> np.ndarray:
        """(H, W) float32 depth (metres) of the mesh posed by ``pose`` (object to camera); 0 where missed."""
        cover = self.cover(pose)
        if cover is None:  # a box straddles the camera plane: the whole rectangle
            return super().depth(pose)
        pose = np.asarray(pose, dtype=np.float64)
        R, t = pose[:3, :3], pose[:3, 3]
        out = np.zeros(self.camera.shape, dtype=np.float32)
        rows, cols = np.nonzero(cover)
        if not rows.size:
            return out
        # cast in the object frame: camera centre -R^T t, directions R^T (x, y, 1) (z = 1: the hit distance is the depth)
        column_term = (self._columns[:, None] * R[0] + R[2]).astype(np.float32)  # (W, 3)
        row_term = (self._rows[:, None] * R[1]).astype(np.float32)  # (H, 3)
        rays = np.empty((rows.size, 6), dtype=np.float32)
        rays[:, :3] = -R.T @ t
        np.add(column_term[cols], row_term[rows], out=rays[:, 3:])
        hit = self.scene.cast_rays(self._o3d.core.Tensor(rays))["t_hit"].numpy()
        out[rows, cols] = np.where(np.isfinite(hit), hit, 0.0)
        return out


def render_masks(
    mesh: trimesh.Trimesh,
    poses: Mapping[str, np.ndarray],
    camera: Camera,
    depth: Mapping[str, np.ndarray] | Callable[[str], np.ndarray] | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
) -> dict[str, np.ndarray]:
    """Masks (H, W) bool per frame id for ``mesh`` (object frame) at ``poses`` (object to camera).

    ``depth`` gives the measured depth (metres, 0 = none) per frame id, as a mapping or a function
    (e.g. ``sequence.depth``); without it the masks are the full silhouettes.
    """
    renderer = ClusterRenderer(mesh, camera)
    out = {}
    for frame_id, pose in poses.items():  # loop over frames; pixels are vectorised
        measured = None
        if depth is not None:
            measured = depth(frame_id) if callable(depth) else depth[frame_id]
        out[frame_id] = visible_mask(renderer.depth(pose), measured, tolerance)
    return out


def mask_png_bytes(mask: np.ndarray) -> bytes:
    """PNG bytes of a mask: uint8, 0 = background, 255 = object."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(buffer, format="PNG")
    return buffer.getvalue()
