"""Procedural object meshes, and loading a given mesh (or point) file, in the ShapeNet object frame.

Object frame: ShapeNet axes (y up; a mug's handle along -z, as in REDWOOD75 and NOCS after
cpas_toolbox's remapping), metres, centred on its axis-aligned box. Sizes are drawn per seed within
realistic ranges: mug 8-12 cm tall, bowl 12-18 cm wide, bottle 20-30 cm tall, can about 6.6-7.6 x 10-13 cm.

Each category has its plain shape (a solid of revolution for bottles, bowls and cans) and variants
(:data:`PROCEDURAL_SHAPES`): bottles, bowls and cans carry the label ``symmetry: y`` in the document,
but a square or oval bowl and a flattened or fluted bottle are no solids of revolution, and mugs come
with C, D and ring handles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from ..axes import MESH_AXES, to_shapenet_points
from ..errors import InputError
from .options import PROCEDURAL_SHAPES
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


def superellipse(phi: np.ndarray, half_z: float, half_x: float, power: float) -> np.ndarray:
    """Radius (per unit) of the superellipse |z / half_z|^p + |x / half_x|^p = 1 at angles ``phi`` (from +z toward +x):
    power 2 an ellipse, larger powers a rounded rectangle."""
    c, s = np.abs(np.cos(phi)) / half_z, np.abs(np.sin(phi)) / half_x
    return (c**power + s**power) ** (-1.0 / power)


def _angles(sections: int) -> np.ndarray:
    return np.linspace(0.0, 2 * np.pi, sections, endpoint=False)


def _bottle(rng: np.random.Generator, variant: str = "round") -> trimesh.Trimesh:
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
    if variant == "round":
        return _mesh([revolve(profile, 48)])
    sections = 96
    phi = _angles(sections)
    # the body takes the cross-section; it blends into the round neck through the shoulder
    body = np.clip((neck_start - profile[:, 1]) / (neck_start - shoulder), 0.0, 1.0)[:, None]
    if variant == "flat":  # a flask: an oval body, a third to a half narrower across x
        section = superellipse(phi, 1.0, rng.uniform(0.5, 0.68), rng.uniform(2.0, 3.0))
    else:  # fluted: vertical grooves around the body
        section = 1.0 + rng.uniform(0.05, 0.08) * np.cos(rng.integers(8, 13) * phi)
    return _mesh([revolve(profile, sections, 1.0 + body * (section[None] - 1.0))])


def _can(rng: np.random.Generator) -> trimesh.Trimesh:
    height = rng.uniform(0.10, 0.13)
    radius = rng.uniform(0.033, 0.038)
    profile = [[0.0, 0.004], [radius - 0.006, 0.0], [radius - 0.002, 0.0], [radius, 0.006], [radius, height - 0.009],
               [radius - 0.004, height - 0.002], [radius - 0.003, height], [radius - 0.005, height], [radius - 0.006, height - 0.003],
               [0.0, height - 0.003]]
    return _mesh([revolve(np.array(profile), 48)])


def _bowl(rng: np.random.Generator, variant: str = "round") -> trimesh.Trimesh:
    rim = rng.uniform(0.06, 0.09)
    height = rng.uniform(0.45, 0.65) * rim
    foot = rng.uniform(0.35, 0.5) * rim
    wall = rng.uniform(0.004, 0.007)
    s = np.linspace(0.0, 1.0, 14)
    outer = np.stack([foot + (rim - foot) * np.sin(s * np.pi / 2) ** 0.8, 0.006 + (height - 0.006) * s], -1)
    inner = np.stack([(foot - wall) + (rim - wall - foot + wall) * np.sin(s * np.pi / 2) ** 0.8, wall + 0.006 + (height - wall - 0.006) * s], -1)[::-1]
    profile = np.concatenate([[[0.0, 0.0], [foot, 0.0]], outer, [[rim - wall / 2, height + 0.001]], inner, [[0.0, wall + 0.006]]])
    if variant == "round":
        return _mesh([revolve(profile, 64)])
    phi = _angles(128)
    if variant == "square":  # a rounded square seen from above, its sides as wide as the round bowl's rim
        section = superellipse(phi, 1.0, 1.0, rng.uniform(4.0, 8.0))
    else:  # oval: a fifth to a third narrower across x
        section = superellipse(phi, 1.0, rng.uniform(0.68, 0.8), 2.0)
    return _mesh([revolve(profile, 128, section)])


def _mug(rng: np.random.Generator, handle: str = "c") -> trimesh.Trimesh:
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
    if handle == "c":
        path = np.stack([np.zeros_like(a), height * 0.5 - half * np.sin(a), -(wall_z + reach * np.cos(a) ** 0.8)], -1)
    elif handle == "d":  # squared off: out, down, back in, with rounded corners
        a = np.linspace(-np.pi / 2, np.pi / 2, 40)
        power = rng.uniform(8.0, 12.0)
        along = np.sign(np.sin(a)) * np.abs(np.sin(a)) ** (2 / power)
        path = np.stack([np.zeros_like(a), height * 0.5 - half * along, -(wall_z + reach * np.abs(np.cos(a)) ** (2 / power))], -1)
    else:  # ring: a small closed loop on the upper wall, as on a teacup
        loop = rng.uniform(0.010, 0.014)
        thickness *= 0.75
        b = np.linspace(0.0, 2 * np.pi, 33)
        centre_y = height * rng.uniform(0.6, 0.72)
        # the loop's near side is buried in the wall (the mug tapers: the wall is nearer the axis below the rim)
        path = np.stack([np.zeros_like(b), centre_y + loop * np.sin(b), -(wall_z - 0.5 * thickness + loop * (1.0 - np.cos(b)))], -1)
    return _mesh([body, tube(path, thickness, 12)])


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


_BUILDERS = {
    "bottle": _bottle, "flat_bottle": lambda rng: _bottle(rng, "flat"), "fluted_bottle": lambda rng: _bottle(rng, "fluted"),
    "bowl": _bowl, "square_bowl": lambda rng: _bowl(rng, "square"), "oval_bowl": lambda rng: _bowl(rng, "oval"),
    "can": _can, "mug": _mug, "mug_d_handle": lambda rng: _mug(rng, "d"), "mug_ring_handle": lambda rng: _mug(rng, "ring"),
    "camera": _camera, "laptop": _laptop,
}


def procedural_mesh(shape: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A procedural object (a category's name, or a variant of :data:`PROCEDURAL_SHAPES`), its sizes drawn from ``rng``."""
    if shape not in PROCEDURAL_SHAPES:
        raise ValueError(f"no procedural shape {shape!r}; one of {', '.join(PROCEDURAL_SHAPES)}")
    return _BUILDERS[shape](rng)


#: Point files (x y z per line, metres) are meshed; the YCB models of YCB-Video come as such.
POINT_SUFFIXES = (".xyz", ".pts")


#: Alpha radii (metres) tried in turn when meshing a point file: the smallest that closes the surface wins.
ALPHAS = (0.015, 0.02, 0.03, 0.04, 0.06, 0.08, 0.12)


def mesh_from_points(points: np.ndarray) -> trimesh.Trimesh:
    """A closed surface through an object's surface points (N, 3): the alpha shape (Open3D) of the smallest radius of
    :data:`ALPHAS` whose largest part is watertight, else the convex hull.

    Sparse, uneven samples (YCB-Video's 2621 points per model, gaps of a centimetre on flat faces) defeat
    normal-based methods: screened Poisson grew sheets inside a box where the tangent planes flipped at its
    edges. An alpha shape needs no normals and follows concavities wider than its radius (a banana's curve).
    """
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    for alpha in ALPHAS:  # a few tries, each a tetrahedralisation of the points
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            shape = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(cloud, alpha)
        mesh = trimesh.Trimesh(np.asarray(shape.vertices), np.asarray(shape.triangles), process=True)
        parts = mesh.split(only_watertight=False)
        if len(parts):
            mesh = max(parts, key=lambda part: part.area)
            if mesh.is_watertight and abs(mesh.volume) > 0:
                if mesh.volume < 0:
                    mesh.invert()
                return mesh
    return trimesh.convex.convex_hull(points)


#: Voxel (metres) and ray directions of :func:`closed_mesh`.
CLOSING_VOXEL = 0.0015
CLOSING_DIRECTIONS = 48


def _sphere_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


def closed_mesh(mesh: trimesh.Trimesh, voxel: float = CLOSING_VOXEL, directions: int = CLOSING_DIRECTIONS) -> trimesh.Trimesh:
    """A closed solid's surface for a scan that is not watertight (NOCS's scans are open where they stood on the table).

    Each point of a grid votes over ``directions`` rays: inside where the first face a ray meets faces away from
    it (the ray leaves the object). The share of such rays approximates the generalised winding number: about 1
    inside, 0 outside, and a smooth fall to 0.5 across a hole, so the 0.5 level (marching cubes) caps holes and
    seals cracks. Needs faces wound outward, as scans are.
    """
    import open3d as o3d
    from scipy import ndimage
    from skimage import measure

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    low = mesh.bounds[0] - 3 * voxel
    shape = np.ceil((mesh.bounds[1] + 3 * voxel - low) / voxel).astype(int) + 1
    points = np.stack(np.meshgrid(*[low[a] + voxel * np.arange(shape[a]) for a in range(3)], indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    leaving = np.zeros(len(points), np.float32)
    for direction in _sphere_directions(directions).astype(np.float32):  # one cast of every grid point per direction
        answer = scene.cast_rays(o3d.core.Tensor(np.concatenate([points, np.broadcast_to(direction, points.shape)], axis=1)))
        leaving += np.isfinite(answer["t_hit"].numpy()) & (answer["primitive_normals"].numpy() @ direction > 0)
    share = ndimage.gaussian_filter((leaving / directions).reshape(shape), 0.5)
    vertices, faces, _, _ = measure.marching_cubes(share, 0.5)
    solid = trimesh.Trimesh(vertices * voxel + low, faces)
    solid = max(solid.split(only_watertight=False), key=lambda part: part.area)
    if solid.volume < 0:
        solid.invert()
    return solid


def _read_points(path: Path) -> np.ndarray:
    try:
        points = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as error:
        raise InputError(path, f"unreadable point file ({error.__class__.__name__}: {' '.join(str(error).split())[:120]})") from error
    if points.ndim != 2 or points.shape[1] < 3 or len(points) < 100:
        raise InputError(path, f"point file must hold at least 100 rows of x y z, got shape {points.shape}")
    return points[:, :3]


def load_mesh(path: str | Path, axes: str = "shapenet") -> trimesh.Trimesh:
    """Read any mesh file trimesh can load (or a point file, meshed: :func:`mesh_from_points`); convert its axes
    (:data:`sequences.axes.MESH_AXES`) to ShapeNet's; close it if it is open (:func:`closed_mesh`); centre on its box.

    Raises InputError for an unreadable file, a file without triangles, or an implausible size.
    """
    path = Path(path)
    if axes not in MESH_AXES:
        raise InputError(path, f"mesh axes {axes!r} are not one of {', '.join(MESH_AXES)}")
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    if path.suffix.lower() in POINT_SUFFIXES:
        points = _read_points(path)
        if not np.all(np.isfinite(points)):
            raise InputError(path, "point file has NaN or infinite coordinates")
        mesh = mesh_from_points(points)
    else:
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as error:  # trimesh raises many types for corrupt files
            raise InputError(path, f"unreadable mesh ({error.__class__.__name__}: {' '.join(str(error).split())[:120]})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "mesh file holds no triangles")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "mesh has NaN or infinite vertex coordinates")
    mesh = trimesh.Trimesh(to_shapenet_points(vertices, axes), np.asarray(mesh.faces), process=False)
    merged = mesh.copy()
    merged.merge_vertices()
    if not merged.is_watertight:  # a camera would see into it through its holes: no physical object
        mesh = closed_mesh(merged)
    mesh = centred(mesh)
    size = float(mesh.extents.max())
    if not (MESH_SIZE_RANGE[0] <= size <= MESH_SIZE_RANGE[1]):
        raise InputError(path, f"mesh is {size:.3g} m across; expected a hand-held object of {MESH_SIZE_RANGE[0]}-{MESH_SIZE_RANGE[1]} m (units must be metres)")
    return mesh
