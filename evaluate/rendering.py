"""Ray-casting a posed triangle mesh into a pinhole camera on the CPU (Open3D RaycastingScene, no OpenGL).

Depth is z in the OpenCV camera frame (metres), rays through pixel centres (integer coordinates);
0 where the mesh is missed. Shared by the dataset readers (instance masks) and reconstruct (masks,
previews).
"""

from __future__ import annotations

import numpy as np
import trimesh

from sequences.camera import Camera


#: Cells per axis of the mesh's bounding box that group its faces for the ray cover (see MeshRenderer). An
#: L-shaped object (a laptop) leaves about half its bounding box's rectangle empty; with 16 cells about 10 % more
#: rays are cast than the mesh hits, and finer cells cast hardly fewer.
COVER_CELLS = 16


class MeshRenderer:
    """Ray-casts one mesh (object frame) into posed pinhole cameras; the scene is built once.

    Only the pixels whose rays may hit the mesh are cast: the faces are grouped by centroid into
    ``cells`` per axis of the mesh's bounding box, and a ray that hits the mesh hits a face inside one
    of the groups' boxes, so its pixel lies in the rectangle of that box's projected corners (plus a
    pixel of rounding slack). The other pixels are misses without casting (an L-shaped laptop: about
    half of its bounding box's rectangle is background).
    """

    def __init__(self, mesh: trimesh.Trimesh, camera: Camera, cells: int = COVER_CELLS) -> None:
        import open3d as o3d  # slow import: only when something is rendered

        self.camera = camera
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)),
        )
        self._boxes = _face_cluster_boxes(np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)], cells)
        # camera-frame ray directions (x, y, 1) of the columns and rows; z = 1, so the hit distance is the depth
        self._columns = (np.arange(camera.width) - camera.cx) / camera.fx
        self._rows = (np.arange(camera.height) - camera.cy) / camera.fy

    def cover(self, pose: np.ndarray) -> np.ndarray:
        """(H, W) bool: the pixels whose rays may hit the mesh posed by ``pose`` (object to camera)."""
        pose = np.asarray(pose, dtype=np.float64)
        cam = self.camera
        points = self._boxes @ pose[:3, :3].T + pose[:3, 3]  # (boxes, 8, 3) camera frame
        ahead = points[..., 2] > 1e-6
        if np.any(ahead.any(axis=1) & ~ahead.all(axis=1)):  # a box straddles the camera plane: every pixel
            return np.ones(cam.shape, dtype=bool)
        points = points[ahead.all(axis=1)]  # boxes wholly behind the camera hold no visible face
        uv, _ = cam.project(points.reshape(-1, 3))
        uv = uv.reshape(-1, 8, 2)
        # one pixel beyond the corners' floor / ceil: rounding slack of the projection
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
        pose = np.asarray(pose, dtype=np.float64)
        R, t = pose[:3, :3], pose[:3, 3]
        out = np.zeros(self.camera.shape, dtype=np.float32)
        rows, cols = np.nonzero(self.cover(pose))
        if not rows.size:
            return out
        # cast in the object frame: camera centre -R^T t, directions R^T (x, y, 1) = column term + row term
        column_term = (self._columns[:, None] * R[0] + R[2]).astype(np.float32)  # (W, 3)
        row_term = (self._rows[:, None] * R[1]).astype(np.float32)  # (H, 3)
        rays = np.empty((rows.size, 6), dtype=np.float32)
        rays[:, :3] = -R.T @ t
        np.add(column_term[cols], row_term[rows], out=rays[:, 3:])
        hit = self.scene.cast_rays(self._o3d.core.Tensor(rays))["t_hit"].numpy()
        out[rows, cols] = np.where(np.isfinite(hit), hit, 0.0)
        return out


def _face_cluster_boxes(triangles: np.ndarray, cells: int) -> np.ndarray:
    """(boxes, 8, 3) corners of the boxes bounding the faces (triangles (F, 3, 3), object frame, m) grouped
    by centroid into ``cells`` per axis of their bounding box; (0, 8, 3) for an empty mesh."""
    if not len(triangles):
        return np.zeros((0, 8, 3))
    lo, hi = triangles.min(axis=(0, 1)), triangles.max(axis=(0, 1))
    cell = np.clip(((triangles.mean(axis=1) - lo) / np.maximum(hi - lo, 1e-12) * cells).astype(np.int64), 0, cells - 1)
    group = np.ravel_multi_index(cell.T, (cells,) * 3)
    order = np.argsort(group, kind="stable")
    starts = np.flatnonzero(np.r_[True, group[order][1:] != group[order][:-1]])
    box_lo = np.minimum.reduceat(triangles.min(axis=1)[order], starts, axis=0)  # (boxes, 3)
    box_hi = np.maximum.reduceat(triangles.max(axis=1)[order], starts, axis=0)
    corner = np.stack(np.unravel_index(np.arange(8), (2, 2, 2)), axis=1).astype(bool)  # (8, 3): hi where set
    return np.where(corner[None], box_hi[:, None, :], box_lo[:, None, :])


def visible_mask(rendered: np.ndarray, measured: np.ndarray | None, tolerance: float = 0.01) -> np.ndarray:
    """(H, W) bool: mesh pixels not occluded (measured depth in front by more than ``tolerance``, metres)."""
    mask = rendered > 0
    if measured is not None:
        occluded = (measured > 0) & (measured < rendered - tolerance)
        mask &= ~occluded
    return mask
