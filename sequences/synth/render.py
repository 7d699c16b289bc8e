"""Rendering a frame's geometry with Open3D's RaycastingScene (CPU, headless): one ray per pixel centre.

All parts are merged into one triangle mesh with a label per triangle, so a single ``cast_rays``
call over all pixels tells, per pixel, the depth, what was hit (object, hand, person, wall,
table), the face normal (for grazing-angle dropout) and the interpolated vertex normal (for
shading). Camera frame: OpenCV (x right, y down, z forward), metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import open3d as o3d

from ..camera import Camera
from .primitives import Part, concatenate


@dataclass
class Render:
    """Per-pixel render results, (H, W[, 3]) arrays; ``label`` 0 and ``depth`` 0 where no surface was hit."""

    depth: np.ndarray  # z of the hit point, metres (float64)
    label: np.ndarray  # uint8 scene label of the hit triangle (see scene.py)
    points: np.ndarray  # hit points, camera frame
    normals: np.ndarray  # interpolated unit vertex normals, turned to face the camera
    cos_incidence: np.ndarray  # |cos| of the angle between the ray and the face normal (1 = head on)


@lru_cache(maxsize=4)
def _rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Rays (H*W, 6) float32 from the origin through pixel centres (direction z = 1), and unit directions (H*W, 3)."""
    directions = camera.pixel_rays().reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(directions), directions], axis=1).astype(np.float32)
    return rays, directions / np.linalg.norm(directions, axis=1, keepdims=True)


def render(parts: list[Part], camera: Camera) -> Render:
    """Cast one ray per pixel against all parts; ray directions have z = 1 so the hit distance is the depth z."""
    vertices, faces, normals, labels = concatenate(parts)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    rays, unit = _rays(camera)
    answer = scene.cast_rays(o3d.core.Tensor(rays))
    t = answer["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t)
    prim = np.where(hit, answer["primitive_ids"].numpy(), 0).astype(np.int64)
    uv = answer["primitive_uvs"].numpy().astype(np.float64)
    face_n = answer["primitive_normals"].numpy().astype(np.float64)
    corners = faces[prim]  # (N, 3) vertex indices of the hit triangles
    w = np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])  # Embree barycentrics
    n = np.einsum("nk,nkj->nj", w, normals[corners])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    # look at the side facing the camera (the inside of a mug, the back of a quad)
    n *= -np.sign(np.einsum("ij,ij->i", n, unit) + 1e-12)[:, None]
    cos = np.abs(np.einsum("ij,ij->i", face_n, unit))
    depth = np.where(hit, t, 0.0)
    shape = camera.shape
    return Render(
        depth=depth.reshape(shape),
        label=np.where(hit, labels[prim], 0).astype(np.uint8).reshape(shape),
        points=(rays[:, 3:] * depth[:, None]).reshape(*shape, 3),
        normals=np.where(hit[:, None], n, 0.0).reshape(*shape, 3),
        cos_incidence=np.where(hit, cos, 0.0).reshape(shape),
    )
