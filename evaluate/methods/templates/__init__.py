"""Built-in procedural category templates: one typical real-size mesh per category.

Object frame: ShapeNet axes (y up; bottle, bowl and can rotationally symmetric about y; a mug's
handle along -z, as the real REDWOOD75 and NOCS mugs in ShapeNet axes), metres, box-centred (the axis-aligned bounding box is centred on the origin).
Sizes are typical household objects (a 0.5 l bottle, a 330 ml can, a cereal bowl, a coffee mug),
so a template is also a size prior. The shapes are made here from revolved profiles rather than
shipped as files, so they are small, exact and reproducible.
"""

from __future__ import annotations

import numpy as np
import trimesh

#: Categories with a built-in template.
TEMPLATE_CATEGORIES = ("bottle", "bowl", "can", "mug")

# trimesh.creation.revolve turns a (radius, height) profile about the 3D z axis; this maps z to y
# (x, y, z) -> (x, z, -y), a proper rotation, so the revolved axis becomes the object's y axis.
_Z_TO_Y = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def _revolved(profile: np.ndarray, sections: int = 48) -> trimesh.Trimesh:
    """Closed surface of revolution about object y from a (radius, height) profile that starts and ends on the axis."""
    mesh = trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)
    mesh.apply_transform(_Z_TO_Y)
    return mesh


def _box_centred(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def bottle_template() -> trimesh.Trimesh:
    """A 0.5 l plastic bottle: body radius 3.3 cm, shoulder, neck radius 1.3 cm, 21 cm tall."""
    shoulder = np.linspace(0.0, np.pi / 2, 8)
    r_body, r_neck, h_body, h_shoulder = 0.033, 0.013, 0.13, 0.045
    shoulder_profile = np.stack(
        [r_neck + (r_body - r_neck) * np.cos(shoulder), h_body + h_shoulder * np.sin(shoulder)], axis=1
    )
    profile = np.vstack([[[0.0, 0.0], [r_body, 0.0]], shoulder_profile, [[r_neck, 0.21], [0.0, 0.21]]])
    return _box_centred(_revolved(profile))


def can_template() -> trimesh.Trimesh:
    """A 330 ml drink can: radius 3.3 cm, 12.2 cm tall, with tapered rims."""
    profile = np.array([[0.0, 0.004], [0.026, 0.0], [0.033, 0.008], [0.033, 0.112], [0.027, 0.122], [0.0, 0.12]])
    return _box_centred(_revolved(profile))


def bowl_template() -> trimesh.Trimesh:
    """A cereal bowl: rim radius 8 cm, foot radius 4 cm, 6.5 cm tall, 5 mm wall (an open shell)."""
    t = np.linspace(0.0, 1.0, 10)
    outer = np.stack([0.04 + 0.04 * np.sin(t * np.pi / 2), 0.065 * t**1.3], axis=1)
    inner = np.stack([outer[::-1, 0] - 0.005, np.maximum(outer[::-1, 1], 0.006)], axis=1)
    profile = np.vstack([[[0.0, 0.0]], outer, inner, [[0.0, 0.006]]])
    return _box_centred(_revolved(profile))


def _handle_tube(
    y_half: float, reach: float, z_base: float, tube_radius: float, arc_sections: int = 24, ring_sections: int = 12
) -> trimesh.Trimesh:
    """A tube along a half-ellipse in the y-z plane from (0, -y_half, z_base) out to z_base + reach and back."""
    theta = np.linspace(-np.pi / 2, np.pi / 2, arc_sections)
    centre = np.stack([np.zeros_like(theta), y_half * np.sin(theta), z_base + reach * np.cos(theta)], axis=1)
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    side = np.array([1.0, 0.0, 0.0])  # the arc lies in the y-z plane, so x is normal to it everywhere
    binormal = np.cross(tangent, side)
    phi = np.linspace(0.0, 2 * np.pi, ring_sections, endpoint=False)
    ring = np.cos(phi)[None, :, None] * side[None, None, :] + np.sin(phi)[None, :, None] * binormal[:, None, :]
    vertices = (centre[:, None, :] + tube_radius * ring).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(arc_sections - 1), np.arange(ring_sections), indexing="ij")
    a = i * ring_sections + j
    b = i * ring_sections + (j + 1) % ring_sections
    c, d = a + ring_sections, b + ring_sections
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    # Cap both ends with a fan so the tube is closed.
    start = np.arange(ring_sections)
    end = (arc_sections - 1) * ring_sections + np.arange(ring_sections)
    cap_start = len(vertices)
    vertices = np.vstack([vertices, centre[0], centre[-1]])
    caps = np.concatenate(
        [
            np.stack([np.full(ring_sections, cap_start), np.roll(start, -1), start], -1),
            np.stack([np.full(ring_sections, cap_start + 1), end, np.roll(end, -1)], -1),
        ]
    )
    mesh = trimesh.Trimesh(vertices, np.concatenate([faces, caps]), process=True)
    mesh.fix_normals()
    return mesh


def mug_template() -> trimesh.Trimesh:
    """A coffee mug: body radius 4.1 cm, 9.6 cm tall, 4 mm wall, a handle reaching 3.1 cm out along -z."""
    r, h, wall = 0.041, 0.096, 0.004
    body = _revolved(np.array([[0.0, 0.0], [r, 0.0], [r, h], [r - wall, h], [r - wall, 0.008], [0.0, 0.008]]))
    handle = _handle_tube(y_half=0.032, reach=0.025, z_base=r - 0.002, tube_radius=0.006)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [0.0, 1.0, 0.0]))  # out along -z
    handle.apply_translation([0.0, h / 2, 0.0])
    return _box_centred(trimesh.util.concatenate([body, handle]))


_BUILDERS = {"bottle": bottle_template, "bowl": bowl_template, "can": can_template, "mug": mug_template}


def builtin_template(category: str) -> trimesh.Trimesh:
    """The built-in template mesh of ``category`` (ShapeNet axes, metres, box-centred)."""
    try:
        return _BUILDERS[category]()
    except KeyError:
        raise ValueError(f"no built-in template for category {category!r}; known: {', '.join(TEMPLATE_CATEGORIES)}") from None
