"""Instance masks from a posed mesh: ray-cast depth (CPU, no OpenGL) and cpas_toolbox's occlusion rule."""

from __future__ import annotations

import numpy as np

from sequences.camera import Camera

#: Observed depth this much (m) in front of the rendered surface marks the pixel as occluded,
#: as in cpas_toolbox's AnnotatedRedwoodDataset._compute_mask.
OCCLUSION_MARGIN = 0.01


def render_depth(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) z-depth (m) of a triangle mesh given in camera coordinates; 0 where no surface is hit.

    Rays go through pixel centres (integer coordinates); the hit distance along a ray with
    z-component 1 is the z-depth, the same quantity a depth camera measures.
    """
    import open3d as o3d  # slow import: only when a mask is needed

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
    )
    rays = np.zeros((camera.height, camera.width, 6), dtype=np.float32)
    rays[..., 3:] = camera.pixel_rays()
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(hit), hit, 0.0).astype(np.float32)


def visible_mask(rendered: np.ndarray, observed: np.ndarray | None, margin: float = OCCLUSION_MARGIN) -> np.ndarray:
    """(H, W) bool: pixels covered by the rendered object and not occluded in the observed depth (m)."""
    mask = rendered > 0
    if observed is not None:
        occluded = (observed > 0) & (observed < rendered - margin)
        mask &= ~occluded
    return mask


def box_mesh(extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and triangles (12, 3) of a box centred on the origin with full side lengths ``extents``."""
    from evaluate.geometry import box_corners

    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x = -e/2, x = +e/2
         [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y = -e/2, y = +e/2
         [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # z = -e/2, z = +e/2
    )
    return box_corners(extents), faces
