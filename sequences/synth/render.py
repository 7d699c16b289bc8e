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

    depth: np.ndarray  # z of the hit point, metres (float32)
    label: np.ndarray  # uint8 scene label of the hit triangle (see scene.py)
    points: np.ndarray  # hit points, camera frame (float32)
    normals: np.ndarray  # interpolated unit vertex normals, turned to face the camera (float32)
    cos_incidence: np.ndarray  # |cos| of the angle between the ray and the face normal (1 = head on; float32)
    shadow: np.ndarray  # bool: the projector's pattern cannot reach the point (another surface is in the way)


def crop(render: Render, window: tuple[int, int, int, int]) -> Render:
    """The part of a render inside rows v0:v1 and columns u0:u1 (views, not copies)."""
    v0, v1, u0, u1 = window
    return Render(*(getattr(render, name)[v0:v1, u0:u1] for name in ("depth", "label", "points", "normals", "cos_incidence", "shadow")))


@lru_cache(maxsize=4)
def _rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Rays (H*W, 6) float32 from the origin through pixel centres (direction z = 1), and unit directions (H*W, 3) float32."""
    directions = camera.pixel_rays().reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(directions), directions], axis=1).astype(np.float32)
    return rays, (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(np.float32)


def projected_window(parts: list[Part], camera: Camera, margin: int = 2, projector: np.ndarray | None = None) -> tuple[int, int, int, int] | None:
    """Pixel rows v0:v1 and columns u0:u1 covering the projection of the parts (None if one is at or behind the camera).

    With a ``projector`` (camera-frame position, on the x axis) the window also covers the shadows
    the parts cast on what lies behind them: up to baseline x fx / (nearest depth) pixels away
    from the projector's side.
    """
    vertices = np.concatenate([p.vertices for p in parts])
    if vertices[:, 2].min() <= 1e-3:
        return None
    uv, _ = camera.project(vertices)
    u0, v0 = np.floor(uv.min(axis=0)).astype(int) - margin
    u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + margin + 1
    if projector is not None:
        reach = int(np.ceil(abs(projector[0]) * camera.fx / vertices[:, 2].min()))
        u0, u1 = (u0 - reach, u1) if projector[0] > 0 else (u0, u1 + reach)
    v0, u0 = max(v0, 0), max(u0, 0)
    v1, u1 = min(v1, camera.height), min(u1, camera.width)
    return (v0, max(v1, v0), u0, max(u1, u0))


def render(parts: list[Part], camera: Camera, base: Render | None = None, window: tuple[int, int, int, int] | None = None,
           projector: np.ndarray | None = None) -> Render:
    """Cast one ray per pixel against all parts; ray directions have z = 1 so the hit distance is the depth z.

    With a ``projector`` position (camera frame, metres), a second cast tests, per hit point,
    whether the way to the projector is blocked (a structured-light sensor measures nothing there).

    With ``base`` (a render of the still parts of the scene) and ``window`` (rows v0:v1, columns
    u0:u1 that hold every moving part, see :func:`projected_window`), only the window's rays are
    cast and the rest is copied from ``base``: outside the window nothing differs.
    """
    height, width = camera.shape
    if base is None or window is None:
        window = (0, height, 0, width)
    v0, v1, u0, u1 = window
    if base is not None and (v1 <= v0 or u1 <= u0):  # the moving parts are out of view
        return Render(*(np.array(getattr(base, name)) for name in ("depth", "label", "points", "normals", "cos_incidence", "shadow")))
    rays, unit = _rays(camera)
    rays = np.ascontiguousarray(rays.reshape(height, width, 6)[v0:v1, u0:u1].reshape(-1, 6))
    unit = unit.reshape(height, width, 3)[v0:v1, u0:u1].reshape(-1, 3)
    vertices, faces, normals, labels = concatenate(parts)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    answer = scene.cast_rays(o3d.core.Tensor(rays))
    t = answer["t_hit"].numpy()
    hit = np.isfinite(t)
    depth = np.where(hit, t, np.float32(0.0))
    prim = np.where(hit, answer["primitive_ids"].numpy(), 0)
    uv = answer["primitive_uvs"].numpy()
    # smooth normal: the hit triangle's vertex normals weighted by Embree's barycentrics (1 - u - v, u, v)
    corner_normals = normals.astype(np.float32)[faces[prim]]  # (N, 3, 3)
    n = corner_normals[:, 0] + uv[:, :1] * (corner_normals[:, 1] - corner_normals[:, 0]) + uv[:, 1:] * (corner_normals[:, 2] - corner_normals[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.float32(1e-12))
    # look at the side facing the camera (the inside of a mug, the back of a quad)
    n *= np.where(np.einsum("ij,ij->i", n, unit) > 0, np.float32(-1.0), np.float32(1.0))[:, None]
    n[~hit] = 0.0
    cos = np.abs(np.einsum("ij,ij->i", answer["primitive_normals"].numpy(), unit))
    cos[~hit] = 0.0
    points = rays[:, 3:] * depth[:, None]
    shadow = np.zeros(len(depth), dtype=bool)
    if projector is not None and hit.any():
        # from just off the surface toward the projector; t in (0, 1) covers exactly the way there
        origins = points[hit] + n[hit] * np.float32(5e-4)
        towards = np.asarray(projector, np.float32) - origins
        shadow[hit] = scene.test_occlusions(o3d.core.Tensor(np.concatenate([origins, towards], 1)), tnear=1e-4, tfar=1.0).numpy()
    shape = (v1 - v0, u1 - u0)
    local = Render(
        depth=depth.reshape(shape),
        label=np.where(hit, labels[prim], 0).astype(np.uint8).reshape(shape),
        points=points.reshape(*shape, 3),
        normals=n.reshape(*shape, 3),
        cos_incidence=cos.reshape(shape),
        shadow=shadow.reshape(shape),
    )
    if shape == (height, width):
        return local
    out = Render(*(np.array(getattr(base, name)) for name in ("depth", "label", "points", "normals", "cos_incidence", "shadow")))
    for name in ("depth", "label", "points", "normals", "cos_incidence", "shadow"):
        getattr(out, name)[v0:v1, u0:u1] = getattr(local, name)
    return out
