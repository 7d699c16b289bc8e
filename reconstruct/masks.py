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
import open3d as o3d
import trimesh

from sequences.camera import Camera

DEFAULT_TOLERANCE = 0.01


class MeshRenderer:
    """Ray-casts one mesh (object frame) into posed pinhole cameras; the scene is built once."""

    def __init__(self, mesh: trimesh.Trimesh, camera: Camera) -> None:
        self.camera = camera
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
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        hit[~np.isfinite(hit)] = 0.0
        out[v0 : v1 + 1, u0 : u1 + 1] = hit.reshape(v1 - v0 + 1, u1 - u0 + 1)
        return out


def visible_mask(rendered: np.ndarray, measured: np.ndarray | None, tolerance: float = DEFAULT_TOLERANCE) -> np.ndarray:
    """(H, W) bool: mesh pixels not occluded (measured depth in front by more than ``tolerance``, metres)."""
    mask = rendered > 0
    if measured is not None:
        occluded = (measured > 0) & (measured < rendered - tolerance)
        mask &= ~occluded
    return mask


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
    renderer = MeshRenderer(mesh, camera)
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
