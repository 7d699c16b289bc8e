"""Triangle-mesh building blocks for the synthetic scene: capsules, ellipsoids, quads, tubes, revolved profiles.

Every builder is vectorised over its primitives and returns a :class:`Part` (vertices, faces and
unit vertex normals in one frame, metres). Capsules and ellipsoids share one latitude-longitude
sphere template, so a hand of 20 capsules is one numpy expression, not 20 mesh constructions.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass
class Part:
    """A triangle mesh with vertex normals and a scene label (see :mod:`sequences.synth.render`)."""

    vertices: np.ndarray  # (V, 3) float64, metres
    faces: np.ndarray  # (F, 3) int64
    normals: np.ndarray  # (V, 3) unit vertex normals
    label: int = 0

    def transformed(self, T: np.ndarray) -> "Part":
        """The part moved by a rigid 4x4 transform."""
        R, t = T[:3, :3], T[:3, 3]
        return Part(self.vertices @ R.T + t, self.faces, self.normals @ R.T, self.label)


def concatenate(parts: list[Part]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Merge parts into one mesh: vertices (V, 3), faces (F, 3), vertex normals (V, 3), per-face labels (F,)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
    normals = np.concatenate([p.normals for p in parts])
    labels = np.concatenate([np.full(len(p.faces), p.label, dtype=np.uint8) for p in parts])
    return vertices, faces, normals, labels


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of a triangle mesh (outward for counter-clockwise faces)."""
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):  # three corners, not a loop over data
        np.add.at(normals, faces[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


@lru_cache(maxsize=8)
def _sphere_template(n_lat: int = 8, n_lon: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit sphere with a doubled equator ring: unit vertices (V, 3), faces (F, 3), upper-half flag (V,).

    Rings run from the +y pole to the -y pole; the equator appears twice (once in each half) so a
    capsule is the template with its upper half shifted along +y by the capsule's length.
    """
    half = n_lat // 2
    theta_top = np.linspace(0.0, np.pi / 2, half + 1)
    theta = np.concatenate([theta_top, np.pi - theta_top[::-1]])  # equator twice
    phi = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.sin(phi), np.broadcast_to(ct, (len(theta), n_lon)), st * np.cos(phi)], axis=-1)
    vertices = ring.reshape(-1, 3)
    upper = np.repeat(np.arange(len(theta)) <= half, n_lon)
    rows = len(theta)
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(n_lon), indexing="ij")
    a = i * n_lon + j
    b = i * n_lon + (j + 1) % n_lon
    c = (i + 1) * n_lon + j
    d = (i + 1) * n_lon + (j + 1) % n_lon
    # counter-clockwise seen from outside (normals outward)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    # drop the degenerate triangles at the poles (measured on a stretched capsule: the equator band is not degenerate)
    stretched = vertices + upper[:, None] * np.array([0.0, 1.0, 0.0])
    tri = stretched[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return vertices, faces[area > 1e-12], upper


def _frames_along(axes: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations whose second column (local +y) is each unit axis (N, 3)."""
    helper = np.where(np.abs(axes[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]))
    x = np.cross(axes, helper)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    z = np.cross(x, axes)
    return np.stack([x, axes, z], axis=-1)


def capsules(starts: np.ndarray, ends: np.ndarray, radii: np.ndarray, label: int = 0, n_lat: int = 8, n_lon: int = 12) -> Part:
    """Capsules (cylinders with hemispherical caps) from ``starts`` (N, 3) to ``ends`` (N, 3) with ``radii`` (N,)."""
    unit, faces_t, upper = _sphere_template(n_lat, n_lon)
    starts, ends = np.asarray(starts, float), np.asarray(ends, float)
    radii = np.broadcast_to(np.asarray(radii, float), (len(starts),))
    axis = ends - starts
    length = np.linalg.norm(axis, axis=1)
    # a zero-length capsule (two finger joints wrapped onto the same surface point) is a sphere: any axis will do
    axis = np.where(length[:, None] > 1e-9, axis / np.maximum(length, 1e-9)[:, None], np.array([0.0, 1.0, 0.0]))
    R = _frames_along(axis)  # (N, 3, 3)
    local = unit[None] * radii[:, None, None]
    local[:, :, 1] += upper[None] * length[:, None]
    vertices = np.einsum("nij,nvj->nvi", R, local) + starts[:, None]
    normals = np.einsum("nij,vj->nvi", R, unit)
    faces = (faces_t[None] + (np.arange(len(starts)) * len(unit))[:, None, None]).reshape(-1, 3)
    return Part(vertices.reshape(-1, 3), faces, normals.reshape(-1, 3), label)


def ellipsoids(centres: np.ndarray, axes: np.ndarray, label: int = 0, n_lat: int = 10, n_lon: int = 16) -> Part:
    """Ellipsoids: ``centres`` (N, 3), ``axes`` (N, 3, 3) whose columns are the semi-axis vectors."""
    unit, faces_t, _ = _sphere_template(n_lat, n_lon)
    centres, axes = np.asarray(centres, float), np.asarray(axes, float)
    vertices = np.einsum("nij,vj->nvi", axes, unit) + centres[:, None]
    normals = np.einsum("nij,vj->nvi", np.linalg.inv(axes).transpose(0, 2, 1), unit)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    faces = (faces_t[None] + (np.arange(len(centres)) * len(unit))[:, None, None]).reshape(-1, 3)
    return Part(vertices.reshape(-1, 3), faces, normals.reshape(-1, 3), label)


def quad(centre: np.ndarray, half_u: np.ndarray, half_v: np.ndarray, label: int = 0) -> Part:
    """A rectangle spanned by half-edge vectors ``half_u`` and ``half_v``; its normal is u x v."""
    c, u, v = (np.asarray(x, float) for x in (centre, half_u, half_v))
    vertices = np.stack([c - u - v, c + u - v, c + u + v, c - u + v])
    normal = np.cross(u, v)
    normal /= np.linalg.norm(normal)
    return Part(vertices, np.array([[0, 1, 2], [0, 2, 3]]), np.tile(normal, (4, 1)), label)


def tube(path: np.ndarray, radius: float, sections: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube of ``radius`` swept along a polyline ``path`` (N, 3), capped at both ends: (vertices, faces)."""
    path = np.asarray(path, float)
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    R = _frames_along(tangent)
    phi = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    circle = np.stack([np.cos(phi), np.zeros_like(phi), np.sin(phi)], -1) * radius
    rings = np.einsum("nij,kj->nki", R, circle) + path[:, None]
    n = len(path)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(sections), indexing="ij")
    a, b = i * sections + j, i * sections + (j + 1) % sections
    c, d = a + sections, b + sections
    side = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    vertices = np.concatenate([rings.reshape(-1, 3), path[[0, -1]]])
    first, last = len(vertices) - 2, len(vertices) - 1
    k = np.arange(sections)
    cap0 = np.stack([np.full(sections, first), (k + 1) % sections, k], -1)
    cap1 = np.stack([np.full(sections, last), (n - 1) * sections + k, (n - 1) * sections + (k + 1) % sections], -1)
    faces = np.concatenate([side, cap0, cap1])
    return vertices, _outward(vertices, faces)


def revolve(profile: np.ndarray, sections: int = 64, section_scale: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Surface about +y of a closed-at-the-axis profile (N, 2) of (radius, height): (vertices, faces).

    The profile must start and end on the axis (radius 0) so the surface is closed. ``section_scale``
    ((sections,) or (N, sections), positive) multiplies each ring's radius per angle phi (measured from +z
    toward +x, ``phi = 2 pi j / sections``): ones give a solid of revolution, a superellipse a square or
    oval cross-section.
    """
    profile = np.asarray(profile, float)
    phi = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    r, h = profile[:, :1], profile[:, 1:]
    if section_scale is not None:
        r = r * np.broadcast_to(np.asarray(section_scale, float), (len(profile), sections))
    rings = np.stack([r * np.sin(phi), np.broadcast_to(h, (len(profile), sections)), r * np.cos(phi)], -1)
    n = len(profile)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(sections), indexing="ij")
    a, b = i * sections + j, i * sections + (j + 1) % sections
    c, d = a + sections, b + sections
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    vertices = rings.reshape(-1, 3)
    tri = vertices[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    faces = faces[area > 1e-14]  # rings on the axis collapse to a point
    # merge the collapsed axis rings so the mesh is watertight
    key = np.round(vertices / 1e-9).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    remap = np.empty(len(order), dtype=np.int64)
    remap[order] = np.arange(len(order))
    vertices = vertices[np.sort(first)]
    faces = remap[inverse.reshape(-1)][faces]
    return vertices, _outward(vertices, faces)


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip the winding of a closed mesh whose signed volume is negative (normals pointing in)."""
    tri = vertices[faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    return faces[:, ::-1].copy() if volume < 0 else faces
