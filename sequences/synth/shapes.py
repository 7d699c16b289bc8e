"""Procedural object meshes per category, and loading a given mesh file, in the ShapeNet object frame.

Object frame: ShapeNet axes (y up; bottles, bowls and cans symmetric about y; a mug's handle along
-z, as in REDWOOD75 and NOCS after cpas_toolbox's remapping), metres, centred on its axis-aligned box. Sizes are drawn per seed within realistic ranges:
mug 8-12 cm tall, bowl 12-18 cm wide, bottle 20-30 cm tall, can about 6.6-7.6 x 10-13 cm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from ..errors import InputError
from .options import MESH_AXES, PROCEDURAL_CATEGORIES
from .primitives import revolve, tube

#: Accepted object sizes for a given mesh (largest box side, metres): the scene is built for hand-held objects.
MESH_SIZE_RANGE = (0.02, 0.6)


def centred(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh translated so its axis-aligned box is centred on the origin."""
    mesh = mesh.copy()
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def _mesh(parts: list[tuple[np.ndarray, np.ndarray]]) -> trimesh.Trimesh:
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    return centred(trimesh.Trimesh(vertices, faces, process=False))


def _bottle(rng: np.random.Generator) -> trimesh.Trimesh:
    height = rng.uniform(0.20, 0.30)
    radius = rng.uniform(0.030, 0.045)
    neck = rng.uniform(0.011, 0.017)
    shoulder = rng.uniform(0.55, 0.68) * height
    neck_start = shoulder + rng.uniform(0.08, 0.14) * height
    s = np.linspace(0.0, 1.0, 12)
    shoulder_curve = np.stack([neck + (radius - neck) * np.cos(s * np.pi / 2) ** 1.5, shoulder + (neck_start - shoulder) * s], -1)
    profile = np.concatenate([
        [[0.0, 0.0], [radius - 0.004, 0.0], [radius, 0.005]],
        [[radius, shoulder * 0.5], [radius * rng.uniform(0.93, 1.0), shoulder * 0.75]],
        shoulder_curve,
        [[neck, height - 0.018], [neck + 0.002, height - 0.016], [neck + 0.002, height - 0.003], [neck + 0.001, height], [0.0, height]],
    ])
    return _mesh([revolve(profile, 48)])


def _can(rng: np.random.Generator) -> trimesh.Trimesh:
    height = rng.uniform(0.10, 0.13)
    radius = rng.uniform(0.033, 0.038)
    profile = [[0.0, 0.004], [radius - 0.006, 0.0], [radius - 0.002, 0.0], [radius, 0.006], [radius, height - 0.009],
               [radius - 0.004, height - 0.002], [radius - 0.003, height], [radius - 0.005, height], [radius - 0.006, height - 0.003],
               [0.0, height - 0.003]]
    return _mesh([revolve(np.array(profile), 48)])


def _bowl(rng: np.random.Generator) -> trimesh.Trimesh:
    rim = rng.uniform(0.06, 0.09)
    height = rng.uniform(0.45, 0.65) * rim
    foot = rng.uniform(0.35, 0.5) * rim
    wall = rng.uniform(0.004, 0.007)
    s = np.linspace(0.0, 1.0, 14)
    outer = np.stack([foot + (rim - foot) * np.sin(s * np.pi / 2) ** 0.8, 0.006 + (height - 0.006) * s], -1)
    inner = np.stack([(foot - wall) + (rim - wall - foot + wall) * np.sin(s * np.pi / 2) ** 0.8, wall + 0.006 + (height - wall - 0.006) * s], -1)[::-1]
    profile = np.concatenate([[[0.0, 0.0], [foot, 0.0]], outer, [[rim - wall / 2, height + 0.001]], inner, [[0.0, wall + 0.006]]])
    return _mesh([revolve(profile, 64)])


def _mug(rng: np.random.Generator) -> trimesh.Trimesh:
    height = rng.uniform(0.08, 0.12)
    radius = rng.uniform(0.036, 0.048)
    wall = rng.uniform(0.003, 0.006)
    taper = rng.uniform(0.9, 1.0)  # bottom radius / top radius
    profile = np.array([[0.0, 0.0], [radius * taper - 0.003, 0.0], [radius * taper, 0.003], [radius, height],
                        [radius - wall, height], [radius * taper - wall, wall + 0.004], [0.0, wall + 0.004]])
    body = revolve(profile, 64)
    # handle: a C-shaped tube in the y-z plane on the -z side (the real REDWOOD75/NOCS mugs'
    # handles lie along -z in ShapeNet axes), its ends buried in the wall
    reach = rng.uniform(0.022, 0.035)
    half = rng.uniform(0.28, 0.36) * height
    thickness = rng.uniform(0.005, 0.008)
    a = np.linspace(-np.pi / 2, np.pi / 2, 20)
    wall_z = radius * (0.5 * (1 + taper)) - wall / 2
    path = np.stack([np.zeros_like(a), height * 0.5 - half * np.sin(a), -(wall_z + reach * np.cos(a) ** 0.8)], -1)
    handle = tube(path, thickness, 12)
    return _mesh([body, handle])


def _box(size: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=size)
    return np.asarray(box.vertices) + centre, np.asarray(box.faces)


def _camera(rng: np.random.Generator) -> trimesh.Trimesh:
    body = np.array([rng.uniform(0.10, 0.14), rng.uniform(0.065, 0.09), rng.uniform(0.035, 0.05)])
    lens_r = rng.uniform(0.022, 0.032)
    lens_len = rng.uniform(0.02, 0.05)
    a = np.linspace(0, 1, 2)
    lens = tube(np.stack([np.zeros(2), np.zeros(2), body[2] / 2 - 0.002 + a * lens_len], -1), lens_r, 24)
    grip = _box(np.array([0.025, body[1] * 0.95, body[2] * 0.5]), np.array([body[0] / 2 - 0.014, 0.0, body[2] * 0.5]))
    return _mesh([_box(body, np.zeros(3)), lens, grip])


def _laptop(rng: np.random.Generator) -> trimesh.Trimesh:
    width, depth, thick = rng.uniform(0.28, 0.36), rng.uniform(0.19, 0.25), rng.uniform(0.012, 0.02)
    opening = np.deg2rad(rng.uniform(95, 120))
    base = _box(np.array([width, thick, depth]), np.array([0.0, thick / 2, 0.0]))
    screen_v, screen_f = _box(np.array([width, depth, thick * 0.5]), np.array([0.0, depth / 2, 0.0]))
    # hinge along x at the back edge of the base (-z), screen tilted back by the opening angle
    tilt = opening - np.pi / 2
    c, s = np.cos(tilt), np.sin(tilt)
    R = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    screen_v = screen_v @ R.T + np.array([0.0, thick, -depth / 2])
    return _mesh([base, (screen_v, screen_f)])


_BUILDERS = {"bottle": _bottle, "bowl": _bowl, "mug": _mug, "can": _can, "camera": _camera, "laptop": _laptop}


def procedural_mesh(category: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A procedural object of ``category`` (one of :data:`PROCEDURAL_CATEGORIES`), shape drawn from ``rng``."""
    if category not in PROCEDURAL_CATEGORIES:
        raise ValueError(f"no procedural shape for {category!r}; one of {', '.join(PROCEDURAL_CATEGORIES)}")
    return _BUILDERS[category](rng)


def load_mesh(path: str | Path, axes: str = "shapenet") -> trimesh.Trimesh:
    """Read any mesh file trimesh can load; convert REDWOOD75 raw axes to ShapeNet's; centre on its box.

    Raises InputError for an unreadable file, a file without triangles, or an implausible size.
    """
    from evaluate.geometry import raw_to_shapenet_points

    path = Path(path)
    if axes not in MESH_AXES:
        raise InputError(path, f"mesh axes {axes!r} are not one of {', '.join(MESH_AXES)}")
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for corrupt files
        raise InputError(path, f"unreadable mesh ({error.__class__.__name__}: {' '.join(str(error).split())[:120]})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "mesh file holds no triangles")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "mesh has NaN or infinite vertex coordinates")
    if axes == "redwood75":
        vertices = raw_to_shapenet_points(vertices)
    mesh = centred(trimesh.Trimesh(vertices, np.asarray(mesh.faces), process=False))
    size = float(mesh.extents.max())
    if not (MESH_SIZE_RANGE[0] <= size <= MESH_SIZE_RANGE[1]):
        raise InputError(path, f"mesh is {size:.3g} m across; expected a hand-held object of {MESH_SIZE_RANGE[0]}-{MESH_SIZE_RANGE[1]} m (units must be metres)")
    return mesh
