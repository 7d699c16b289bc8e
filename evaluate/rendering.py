"""Ray-casting a posed triangle mesh into a pinhole camera on the CPU (Open3D RaycastingScene, no OpenGL).

Depth is z in the OpenCV camera frame (metres), rays through pixel centres (integer coordinates);
0 where the mesh is missed. Shared by the dataset readers (instance masks) and reconstruct (masks,
previews).
"""

from __future__ import annotations

import numpy as np
import trimesh

from sequences.camera import Camera


class MeshRenderer:
    """Ray-casts one mesh (object frame) into posed pinhole cameras; the scene is built once."""

    def __init__(self, mesh: trimesh.Trimesh, camera: Camera) -> None:
        import open3d as o3d  # slow import: only when something is rendered

        self.camera = camera
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)),
        )
        # camera-frame directions with z = 1, so the hit distance along a ray is the depth z
        self._directions = camera.pixel_rays()
        lo, hi = mesh.bounds
        self._corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    def depth(self, pose: np.ndarray) -> np.ndarray:
        """(H, W) float32 depth (metres) of the mesh posed by ``pose`` (object to camera); 0 where missed.

        Only the pixels inside the projection of the mesh's bounding box are cast (a tenth of the
        image for a typical object), the rest are misses by construction.
        """
        pose = np.asarray(pose, dtype=np.float64)
        R, t = pose[:3, :3], pose[:3, 3]
        cam = self.camera
        out = np.zeros(cam.shape, dtype=np.float32)
        corners = self._corners @ R.T + t
        if np.all(corners[:, 2] <= 1e-6):
            return out
        if np.any(corners[:, 2] <= 1e-6):  # the box straddles the camera plane: cast everything
            u0, v0, u1, v1 = 0, 0, cam.width - 1, cam.height - 1
        else:
            uv, _ = cam.project(corners)
            u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
            u1 = min(int(np.ceil(uv[:, 0].max())) + 1, cam.width - 1)
            v1 = min(int(np.ceil(uv[:, 1].max())) + 1, cam.height - 1)
            if u0 > u1 or v0 > v1:
                return out
        directions = self._directions[v0 : v1 + 1, u0 : u1 + 1].reshape(-1, 3)
        # cast in the object frame: camera centre -R^T t, directions R^T d (same lengths)
        rays = np.empty((directions.shape[0], 6), dtype=np.float32)
        rays[:, :3] = -R.T @ t
        rays[:, 3:] = directions @ R
        hit = self.scene.cast_rays(self._o3d.core.Tensor(rays))["t_hit"].numpy()
        hit[~np.isfinite(hit)] = 0.0
        out[v0 : v1 + 1, u0 : u1 + 1] = hit.reshape(v1 - v0 + 1, u1 - u0 + 1)
        return out


def visible_mask(rendered: np.ndarray, measured: np.ndarray | None, tolerance: float = 0.01) -> np.ndarray:
    """(H, W) bool: mesh pixels not occluded (measured depth in front by more than ``tolerance``, metres)."""
    mask = rendered > 0
    if measured is not None:
        occluded = (measured > 0) & (measured < rendered - tolerance)
        mask &= ~occluded
    return mask
