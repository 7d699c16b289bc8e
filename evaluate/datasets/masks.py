"""Instance masks from a posed mesh: ray-cast depth (CPU, no OpenGL) and cpas_toolbox's occlusion rule."""

from __future__ import annotations

import numpy as np
import trimesh

from evaluate.rendering import MeshRenderer, visible_mask
from sequences.camera import Camera

__all__ = ["OCCLUSION_MARGIN", "box_mesh", "render_depth", "visible_mask"]

#: Observed depth this much (m) in front of the rendered surface marks the pixel as occluded,
#: as in cpas_toolbox's AnnotatedRedwoodDataset._compute_mask.
OCCLUSION_MARGIN = 0.01


def render_depth(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) z-depth (m) of a triangle mesh given in camera coordinates; 0 where no surface is hit."""
    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces), process=False)
    return MeshRenderer(mesh, camera).depth(np.eye(4))


def box_mesh(extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and triangles (12, 3) of a box centred on the origin with full side lengths ``extents``."""
    from evaluate.geometry import box_corners

    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x = -e/2, x = +e/2
         [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y = -e/2, y = +e/2
         [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # z = -e/2, z = +e/2
    )
    return box_corners(extents), faces
