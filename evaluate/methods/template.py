"""``template``: fit a per-category template shape to the observed points, over all of SO(3), with scale.

Pipeline (camera frame: OpenCV, metres; the template in its object frame: ShapeNet axes,
box-centred, metres):

1. Observed points: the masked depth pixels without depth outliers (``box.masked_points``),
   subsampled deterministically (a fixed-seed choice) for speed.
2. Hypotheses: a deterministic, near-uniform set of rotations covering ALL of SO(3) (a
   super-Fibonacci spiral, Alexa 2022), not only upright ones. For categories symmetric about y the
   rotation about y does not matter, so the hypotheses are the directions of the object's y axis (a
   Fibonacci sphere) instead.
3. Per hypothesis, without any search over translation or scale: the template samples this view
   sees (tabulated once per template for 160 viewing directions by ray casting: facing the camera
   and not self-occluded), weighted by projected area as pixels sample a surface, stand in for the
   observation; their centroid is put on the observed centroid and their spread (RMS radius)
   matched to the observed spread, which gives translation and scale.
4. Score per hypothesis (all hypotheses at once, vectorised), lower is better: the mean truncated
   distance from the observed points to the template surface, read from a precomputed distance
   field, where a point whose nearest template sample this view cannot see (facing away or
   self-occluded, from a visibility table ray-cast once per template) counts as far; plus, for the
   template samples this view sees, projected into the image: 1 outside the (3-pixel dilated) mask,
   else the truncated disagreement with the observed depth.
5. The best few distinct hypotheses (``refine``, at least ``separation`` degrees apart) are
   refined. Asymmetric categories first turn each about the template's body axis (object y) all
   the way round in 10 degree steps, keeping the best: the handle alone fixes that turn and ICP
   barely moves it. Then a local grid of rotations around each (+-30 degrees, 10 degree steps), a
   brief similarity ICP (nearest template samples that this view sees, trimmed, Umeyama with scale
   per iteration), a re-score with exact KD-tree distances; the best ``finish`` get a finer grid
   (+-6 degrees, 3 degree steps) and a full ICP, and the best of those wins.
6. A can hardly shows its top from its bottom, so its y is turned towards the camera's up
   (the upright prior), which costs nothing in fit.

The ICP also fits the template's proportions (one factor for y, one for x and z, within
``stretch``): a category's members differ in height against width (a shallow or a deep bowl).
The prediction: the pose of the template's box centre, extents = template extents x per-axis scale,
and the template mesh so scaled, in the object frame, as the reconstruction.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from evaluate.geometry import matrix_to_quat
from sequences.annotation import SYMMETRIC_CATEGORIES  # their templates are rotationally symmetric about object y
from sequences.camera import Camera
from sequences.names import safe_name

from .base import Method, Prediction
from .box import check_inputs, masked_points
from .templates import TEMPLATE_CATEGORIES, builtin_template

#: Categories whose shape hardly tells top from bottom (a can): y is turned to the camera's up.
UP_DOWN_AMBIGUOUS = ("can",)
#: Fraction of the distance cap below which a depth disagreement is free (noise, binned visibility).
DEPTH_TOLERANCE = 0.3
#: Local rotation grids around candidates: (half width, step) in degrees, coarse (every candidate) then fine.
LOCAL_SEARCH = ((30.0, 10.0), (6.0, 3.0))


# --------------------------------------------------------------------------------------- rotations


def super_fibonacci_rotations(n: int) -> np.ndarray:
    """(n, 3, 3) rotations spread near-uniformly over SO(3) (super-Fibonacci spiral; deterministic)."""
    phi = np.sqrt(2.0)
    psi = 1.533751168755204288118041
    s = np.arange(n) + 0.5
    r = np.sqrt(s / n)
    big_r = np.sqrt(1.0 - s / n)
    alpha = 2.0 * np.pi * s / phi
    beta = 2.0 * np.pi * s / psi
    quaternions = np.stack([r * np.sin(alpha), r * np.cos(alpha), big_r * np.sin(beta), big_r * np.cos(beta)], axis=1)
    return Rotation.from_quat(quaternions).as_matrix()


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread near-uniformly over the sphere (deterministic)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    theta = np.pi * (1.0 + np.sqrt(5.0)) * i
    rho = np.sqrt(1.0 - z**2)
    return np.stack([rho * np.cos(theta), rho * np.sin(theta), z], axis=1)


def rotations_taking_y_to(directions: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations whose second column (object y in the camera) is each unit direction (n, 3)."""
    y = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    helper = np.where(np.abs(y[:, [0]]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]))
    z = np.cross(helper, y)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=2)


# --------------------------------------------------------------------------------------- templates


def sample_surface(mesh: trimesh.Trimesh, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted seeded surface samples (count, 3) and their face normals (count, 3) of a mesh."""
    rng = np.random.default_rng(seed)
    triangles = np.asarray(mesh.triangles)
    areas = np.asarray(mesh.area_faces)
    face = rng.choice(len(areas), size=count, p=areas / areas.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = triangles[face, 0], triangles[face, 1], triangles[face, 2]
    points = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    return points, np.asarray(mesh.face_normals)[face]


@dataclass
class FittedTemplate:
    """A template prepared for fitting (object frame, m).

    Surface samples with normals; a distance field (distance from each voxel centre to the nearest
    sample, and that sample's index); and a visibility table: for a set of viewing directions
    (rays travelling along ``view_directions``, orthographic), which samples the camera sees
    (facing it and not occluded by the template itself, found by ray casting once here).
    """

    mesh: trimesh.Trimesh
    extents: np.ndarray  # (3,) full box side lengths
    points: np.ndarray  # (M, 3) surface samples
    normals: np.ndarray  # (M, 3) outward unit normals
    coarse: np.ndarray  # indices of a sparse subset of ``points`` for hypothesis scoring
    field_origin: np.ndarray  # (3,) centre of voxel (0, 0, 0)
    voxel: float  # voxel side
    distance: np.ndarray  # (X, Y, Z) distance from voxel centres to the nearest sample, m
    nearest: np.ndarray  # (X, Y, Z) index into ``points`` of that nearest sample
    view_directions: np.ndarray  # (V, 3) unit viewing directions (camera to object), object frame
    visible: np.ndarray  # (V, M) bool: sample seen from each viewing direction
    view_centroid: np.ndarray  # (V, 3) centroid of what each view sees, weighted by projected area
    view_rms: np.ndarray  # (V,) RMS distance of what each view sees from that centroid
    tree: cKDTree  # over ``points``: exact nearest samples where the distance field is too coarse

    @property
    def body_axis_point(self) -> np.ndarray:
        """A point (3,) on the body's axis along y: the samples' median x and z (an appendage barely moves it)."""
        x, z = np.median(self.points[:, 0]), np.median(self.points[:, 2])
        return np.array([x, 0.0, z])

    @classmethod
    def from_mesh(
        cls, mesh: trimesh.Trimesh, samples: int = 8000, coarse: int = 300, resolution: int = 80, views: int = 160
    ) -> "FittedTemplate":
        mesh = mesh.copy()
        mesh.apply_translation(-mesh.bounds.mean(axis=0))  # box-centred, whatever the input
        points, normals = sample_surface(mesh, samples)
        extents = np.asarray(mesh.extents, dtype=np.float64)
        margin = 0.25 * extents.max()
        low = mesh.bounds[0] - margin
        voxel = float((extents.max() + 2 * margin) / resolution)
        shape = np.ceil((extents + 2 * margin) / voxel).astype(int) + 1
        cells = np.clip(np.round((points - low) / voxel).astype(int), 0, shape - 1)
        occupied = np.ones(shape, dtype=bool)
        occupied[tuple(cells.T)] = False
        owner = np.full(shape, -1, dtype=np.int64)
        owner[tuple(cells.T)] = np.arange(len(points))
        _, indices = ndimage.distance_transform_edt(occupied, return_indices=True)
        nearest = owner[tuple(indices)]
        grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1) * voxel + low
        distance = np.linalg.norm(grid - points[nearest], axis=-1)
        directions = fibonacci_sphere(views)
        visible = visibility_table(mesh, points, normals, directions, offset=1e-3 * extents.max())
        # Per-pixel observations sample a surface by projected area: weight samples by |cos| to the view.
        weights = visible * np.maximum(-(directions @ normals.T), 0.0)
        total = weights.sum(axis=1) + 1e-12
        view_centroid = weights @ points / total[:, None]
        second_moment = weights @ (points**2).sum(axis=1) / total
        view_rms = np.sqrt(np.maximum(second_moment - (view_centroid**2).sum(axis=1), 1e-12))
        step = max(1, samples // coarse)
        return cls(
            mesh, extents, points, normals, np.arange(0, samples, step), low, voxel, distance, nearest, directions, visible,
            view_centroid, view_rms, cKDTree(points),
        )

    #: The arrays that make a template (the KD-tree is rebuilt from ``points``, the mesh from its two arrays).
    ARRAYS = ("extents", "points", "normals", "coarse", "field_origin", "distance", "nearest", "view_directions", "visible",
              "view_centroid", "view_rms")

    def to_npz(self) -> bytes:
        """The template as npz bytes (no pickles): what :meth:`from_npz` reads back to the same arrays, bit for bit."""
        buffer = io.BytesIO()
        np.savez(buffer, vertices=np.asarray(self.mesh.vertices), faces=np.asarray(self.mesh.faces), voxel=np.float64(self.voxel),
                 **{name: getattr(self, name) for name in self.ARRAYS})
        return buffer.getvalue()

    @classmethod
    def from_npz(cls, path: str | Path) -> "FittedTemplate":
        """A template written by :meth:`to_npz`; ValueError (or OSError) when the file is not one."""
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in ("vertices", "faces", "voxel", *cls.ARRAYS) if k not in data.files]
            if missing:
                raise ValueError(f"{path}: not a prepared template (no {missing[0]})")
            arrays = {name: data[name] for name in cls.ARRAYS}
            mesh = trimesh.Trimesh(data["vertices"], data["faces"], process=False)
            voxel = float(data["voxel"])
        fields = dict(arrays, mesh=mesh, voxel=voxel, tree=cKDTree(arrays["points"]))
        return cls(**fields)

    def view_bin(self, directions: np.ndarray) -> np.ndarray:
        """Index (...) of the tabulated viewing direction closest to each object-frame direction (..., 3)."""
        return np.argmax(directions @ self.view_directions.T, axis=-1)

    def lookup(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (...) to the template surface and the index of the nearest sample, for object-frame points (..., 3).

        Points outside the field read its border and add their distance to it.
        """
        shape = np.array(self.distance.shape)
        cell = (points - self.field_origin) / self.voxel
        clipped = np.clip(np.round(cell), 0, shape - 1).astype(np.intp)
        outside = np.linalg.norm(cell - np.clip(cell, 0, shape - 1), axis=-1) * self.voxel
        index = (clipped[..., 0] * shape[1] + clipped[..., 1]) * shape[2] + clipped[..., 2]
        return self.distance.reshape(-1)[index] + outside, self.nearest.reshape(-1)[index]


def visibility_table(mesh: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray, directions: np.ndarray, offset: float) -> np.ndarray:
    """(V, M) bool: sample i is seen along viewing direction v (facing it, and its ray to the camera unoccluded)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32))
    )
    facing = directions @ normals.T < 0.0
    view_index, sample_index = np.nonzero(facing)
    origins = points[sample_index] + offset * normals[sample_index]
    rays = np.concatenate([origins, -directions[view_index]], axis=1).astype(np.float32)
    occluded = scene.test_occlusions(o3d.core.Tensor(rays)).numpy().astype(bool)
    visible = np.zeros(facing.shape, dtype=bool)
    visible[view_index[~occluded], sample_index[~occluded]] = True
    return visible


def load_template(source) -> trimesh.Trimesh:
    """A template mesh from a trimesh.Trimesh or a mesh file path."""
    if isinstance(source, trimesh.Trimesh):
        return source
    path = Path(source)
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as error:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: cannot read template mesh ({error.__class__.__name__}: {error})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: template mesh has no triangles")
    return mesh


# --------------------------------------------------------------------------------------- fitting


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |s R source + t - target|^2 over (N, 3) pairs (Umeyama 1991)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd(b.T @ a / len(source))
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2] = -1.0
    rotation = u @ np.diag(d) @ vt
    variance = (a**2).sum() / len(source)
    scale = float((sigma * d).sum() / variance)
    return scale, rotation, mu_t - scale * rotation @ mu_s


def _dilated(mask: np.ndarray, pixels: int) -> np.ndarray:
    return ndimage.binary_dilation(mask, iterations=pixels) if pixels > 0 else mask


class TemplateMethod(Method):
    """Template fitting with a multi-hypothesis rotation search over all of SO(3) and similarity ICP.

    ``templates``: {category: trimesh.Trimesh or mesh path} (object frame ShapeNet axes, metres);
    categories not given use the built-in procedural templates (``evaluate.methods.templates``).
    ``config`` keys (all optional): ``templates`` (the same mapping, or a folder of
    ``<category>.obj|ply|stl`` files), ``hypotheses`` (SO(3) rotations, 3000),
    ``symmetric_hypotheses`` (y directions for symmetric categories, 400), ``points`` (observed points
    used for scoring, 300), ``icp_points`` (800), ``refine`` (distinct hypotheses refined briefly, 10), ``separation`` (degrees between them, 15), ``finish`` (of those, refined fully, 3),
    ``icp_iterations`` (25), ``truncation`` (distance cap relative to the template size, 0.1),
    ``scale_range`` ([0.5, 2.0], allowed scale relative to the template), ``seed`` (0), ``stretch`` (largest change of the template's proportions, y against x and z,
    1.3; 1 keeps them).
    """

    name = "template"

    def __init__(self, config: dict | None = None, templates: dict | str | Path | None = None) -> None:
        config = dict(config or {})
        sources = templates if templates is not None else config.pop("templates", None)
        config.pop("templates", None)
        self.hypotheses = int(config.pop("hypotheses", 3000))
        self.symmetric_hypotheses = int(config.pop("symmetric_hypotheses", 400))
        self.score_points = int(config.pop("points", 300))
        self.icp_points = int(config.pop("icp_points", 800))
        self.refine = int(config.pop("refine", 10))
        self.icp_iterations = int(config.pop("icp_iterations", 25))
        self.finish = int(config.pop("finish", 3))
        self.separation = float(config.pop("separation", 15.0))
        self.truncation = float(config.pop("truncation", 0.1))
        self.scale_range = tuple(float(v) for v in config.pop("scale_range", (0.5, 2.0)))
        self.seed = int(config.pop("seed", 0))
        self.stretch = float(config.pop("stretch", 1.3))
        if config:
            raise ValueError(f"unknown template method options {sorted(config)}")
        self._sources = self._resolve_sources(sources)
        self._prepared: dict[str, FittedTemplate] = {}
        self._trees: dict[int, dict] = {}
        self._rotations = super_fibonacci_rotations(self.hypotheses)
        self._symmetric_rotations = rotations_taking_y_to(fibonacci_sphere(self.symmetric_hypotheses))

    @staticmethod
    def _resolve_sources(sources) -> dict:
        if sources is None:
            return {}
        if isinstance(sources, (str, Path)):
            folder = Path(sources)
            if not folder.is_dir():
                raise ValueError(f"{folder}: template folder does not exist")
            found = {}
            for path in sorted(folder.iterdir()):
                if path.suffix.lower() in (".obj", ".ply", ".stl", ".off", ".glb"):
                    found.setdefault(path.stem, path)
            return found
        return dict(sources)

    def _mesh(self, category: str) -> trimesh.Trimesh:
        if category in self._sources:
            return load_template(self._sources[category])
        if category in TEMPLATE_CATEGORIES:
            return builtin_template(category)
        raise ValueError(f"no template for category {category!r}; give one with templates={{{category!r}: mesh}}")

    def template(self, category: str) -> FittedTemplate:
        """The prepared template of ``category`` (built once, then cached)."""
        if category not in self._prepared:
            self._prepared[category] = FittedTemplate.from_mesh(self._mesh(category))
        return self._prepared[category]

    def prepare_shared(self, categories: list[str], folder: Path) -> None:
        """The templates of ``categories`` (those it has), each prepared once for a batch: read from ``folder``
        where another unit left it, else built and written there atomically. The file's name holds a fingerprint
        of the mesh and of this module's code, so a template is never read for another."""
        from sequences.atomic import write_bytes_atomic

        code = Path(__file__).read_bytes()
        for category in categories:
            if category in self._prepared:
                continue
            try:
                mesh = self._mesh(category)
            except ValueError:  # no template: its samples fail with the reason, one by one
                continue
            digest = hashlib.sha256(code)
            for array in (np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)):
                digest.update(repr(array.shape).encode() + array.tobytes())
            key = digest.hexdigest()[:16]
            path = Path(folder) / f"{safe_name(category)}-{key}.npz"
            try:
                self._prepared[category] = FittedTemplate.from_npz(path)
                continue
            except (OSError, ValueError):  # not there yet, or unreadable: build it
                pass
            self._prepared[category] = FittedTemplate.from_mesh(mesh)
            try:
                write_bytes_atomic(path, self._prepared[category].to_npz())
            except OSError:  # a folder that cannot be written costs time, not results
                pass

    # ------------------------------------------------------------------ inference

    def inference(self, color: np.ndarray, depth: np.ndarray, mask: np.ndarray, category: str, camera: Camera) -> Prediction:
        depth, mask = check_inputs(depth, mask, camera)
        template = self.template(category)
        observed = masked_points(depth, mask, camera)
        rng = np.random.default_rng(self.seed)
        fit_points = observed[rng.choice(len(observed), min(self.icp_points, len(observed)), replace=False)]
        score_points = fit_points[: self.score_points]
        silhouette = _dilated(mask, 3)
        object_depth = np.where(mask & np.isfinite(depth), depth, 0.0)
        rotations = self._symmetric_rotations if category in SYMMETRIC_CATEGORIES else self._rotations

        scales, translations, scores = self._score_hypotheses(template, observed, score_points, rotations, silhouette, object_depth, camera)
        order = np.argsort(scores)
        chosen: list[int] = []
        apart = 1.0 + 2.0 * np.cos(np.radians(self.separation))  # trace of a relative rotation by that angle
        for k in order:  # the best few hypotheses whose rotations differ by more than ``separation``
            if all(np.trace(rotations[k].T @ rotations[j]) < apart for j in chosen):
                chosen.append(int(k))
            if len(chosen) == self.refine:
                break
        # Each candidate: a nearby rotation grid, brief ICP, re-score; the best few: a finer grid, full ICP.
        (coarse_width, coarse_step), (fine_width, fine_step) = LOCAL_SEARCH
        refined = []
        for k in chosen:
            pose = (scales[k], rotations[k], translations[k])
            if category not in SYMMETRIC_CATEGORIES:
                pose = self._swing_search(template, observed, score_points, pose, silhouette, object_depth, camera)
            pose = self._local_search(template, observed, score_points, pose, silhouette, object_depth, camera, coarse_width, coarse_step)
            refined.append(self._icp(template, fit_points, *pose, self.icp_iterations // 3))
        rescored = np.array([self._pose_score(template, observed, fit_points, pose, silhouette, object_depth, camera) for pose in refined])
        finished = []
        for k in np.argsort(rescored)[: self.finish]:
            pose = self._local_search(template, observed, score_points, refined[k], silhouette, object_depth, camera, fine_width, fine_step)
            finished.append(self._icp(template, fit_points, *pose, self.icp_iterations))
        final = [self._pose_score(template, observed, fit_points, pose, silhouette, object_depth, camera) for pose in finished]
        scale, rotation, translation = finished[int(np.argmin(final))]
        if category in UP_DOWN_AMBIGUOUS and rotation[:, 1] @ np.array([0.0, -1.0, 0.0]) < 0.0:
            rotation = rotation @ np.diag([1.0, -1.0, -1.0])  # turn 180 deg about object x: same box, y up
        reconstruction = template.mesh.copy()
        reconstruction.apply_transform(np.diag([*scale, 1.0]))
        return Prediction(translation, matrix_to_quat(rotation), template.extents * scale, reconstruction)

    def _score_hypotheses(
        self, template, observed, points, rotations, silhouette, depth, camera, fixed=None, samples=None, exact=False
    ):
        """Per hypothesis: per-axis scale (H, 3), translation (H, 3) and score (H,) (lower is better).

        Scale and translation come from matching the visible template to the observed points,
        unless ``fixed`` = (scales (H, 3), translations (H, 3)) gives them. ``samples`` indexes the
        template samples checked against the image (default: the sparse scoring subset). ``exact``
        takes distances from the KD-tree rather than the distance field (slower, no voxel rounding).
        """
        samples = template.coarse if samples is None else samples
        centroid = observed.mean(axis=0)
        view = centroid / np.linalg.norm(centroid)
        observed_rms = np.sqrt(((observed - centroid) ** 2).sum(axis=1).mean())
        sample_points = template.points[samples]
        views_object = view @ rotations  # (H, 3) = R^T view
        bins = template.view_bin(views_object)
        visible = template.visible[bins][:, samples]  # (H, M)
        if fixed is None:
            scales = np.repeat(np.clip(observed_rms / template.view_rms[bins], *self.scale_range)[:, None], 3, axis=1)
            translations = centroid - np.einsum("hij,hj->hi", rotations, scales * template.view_centroid[bins])
        else:
            scales, translations = fixed
        # Observed points into each hypothesis' object frame: q = R^T (p - t) / s (row form: (p - t) R).
        local = np.matmul(points[None, :, :] - translations[:, None, :], rotations) / scales[:, None, :]
        distance, nearest = template.tree.query(local) if exact else template.lookup(local)
        # Visibility: an observed point must lie on template surface that this view can see.
        unseen = ~template.visible[bins[:, None], nearest]
        cap = self.truncation * float(template.extents.max())
        distance = np.where(unseen, cap, np.minimum(distance, cap))
        fit = distance.mean(axis=1) / cap
        disagreement = self._projection_term(sample_points, visible, scales, rotations, translations, silhouette, depth, cap, camera)
        return scales, translations, fit + disagreement

    def _swing_search(self, template, observed, points, pose, silhouette, depth, camera, step: float = 10.0):
        """Best turn of a pose about the template's body axis (object y through the samples' median x, z), all the way round.

        In the ShapeNet frame y is the up axis, about which these categories are nearly symmetric
        (a mug without its handle), so the turn about y is what the points constrain least: it is
        searched in full, in ``step`` degree steps.
        """
        scale, rotation, translation = pose
        angles = np.radians(np.arange(0.0, 360.0, step))
        c, s = np.cos(angles), np.sin(angles)
        turns = np.zeros((len(angles), 3, 3))
        turns[:, 0, 0], turns[:, 0, 2], turns[:, 1, 1], turns[:, 2, 0], turns[:, 2, 2] = c, s, 1.0, -s, c
        rotations = rotation[None] @ turns
        pivot = template.body_axis_point
        translations = translation + rotation @ (scale * pivot) - rotations @ (scale * pivot)
        fixed = (np.broadcast_to(scale, (len(angles), 3)), translations)
        _, _, scores = self._score_hypotheses(template, observed, points, rotations, silhouette, depth, camera, fixed=fixed)
        best = int(np.argmin(scores))
        return scale, rotations[best], translations[best]

    def _local_search(self, template, observed, points, pose, silhouette, depth, camera, half_width: float, step: float):
        """Best of a grid of rotation perturbations (rotation vectors within +-``half_width`` degrees, object frame)
        around a pose, each turned about the centroid of what the camera sees, scale kept.

        ICP alone barely turns a mug about its body axis (only the few handle points pull), so a
        nearby grid is searched outright.
        """
        scale, rotation, translation = pose
        ticks = np.radians(np.arange(-half_width, half_width + 1e-9, step))
        grid = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), axis=-1).reshape(-1, 3)
        rotations = rotation[None] @ Rotation.from_rotvec(grid).as_matrix()
        view = observed.mean(axis=0)
        view = view / np.linalg.norm(view)
        pivot = template.view_centroid[template.view_bin(rotation.T @ view)]  # object frame
        translations = translation + rotation @ (scale * pivot) - rotations @ (scale * pivot)
        fixed = (np.broadcast_to(scale, (len(grid), 3)), translations)
        _, _, scores = self._score_hypotheses(template, observed, points, rotations, silhouette, depth, camera, fixed=fixed)
        best = int(np.argmin(scores))
        return scale, rotations[best], translations[best]

    def _pose_score(self, template, observed, points, pose, silhouette, depth, camera) -> float:
        """The hypothesis score of one pose (scale (3,), rotation (3, 3), translation (3,)), on 4x denser template samples."""
        scale, rotation, translation = pose
        fixed = (np.asarray(scale)[None], translation[None])
        dense = np.arange(0, len(template.points), max(1, (template.coarse[1] - template.coarse[0]) // 4))
        scores = self._score_hypotheses(template, observed, points, rotation[None], silhouette, depth, camera, fixed=fixed, samples=dense, exact=True)
        return float(scores[2][0])

    @staticmethod
    def _projection_term(points, visible, scales, rotations, translations, silhouette, depth, cap, camera) -> np.ndarray:
        """(H,) how badly each hypothesis' visible template samples (M, 3) disagree with the image, in [0, 1].

        A visible sample projecting outside the (dilated) mask costs 1; one on the mask costs its depth
        disagreement with the observed depth, truncated at ``cap`` m and divided by it (a sample in
        front of or behind the observed surface is where the object is not).
        """
        cam = np.matmul(scales[:, None, :] * points[None, :, :], np.transpose(rotations, (0, 2, 1))) + translations[:, None, :]
        pixels, z = camera.project(cam)
        u = np.round(pixels[..., 0]).astype(np.intp)
        v = np.round(pixels[..., 1]).astype(np.intp)
        inside_image = (u >= 0) & (u < silhouette.shape[1]) & (v >= 0) & (v < silhouette.shape[0]) & (z > 0)
        u, v = np.where(inside_image, u, 0), np.where(inside_image, v, 0)
        on_silhouette = inside_image & silhouette[v, u]
        observed = depth[v, u]
        measured = on_silhouette & (observed > 0)
        # Depth noise and the tabulated (orthographic, binned) visibility make small disagreements
        # everywhere; only what exceeds DEPTH_TOLERANCE of the cap counts.
        excess = np.maximum(np.abs(z - observed) - DEPTH_TOLERANCE * cap, 0.0)
        cost = np.where(measured, np.minimum(excess, cap) / cap, np.where(on_silhouette, 0.0, 1.0))
        counted = visible.sum(axis=1)
        return (np.where(visible, cost, 0.0).sum(axis=1) / np.maximum(counted, 1)).astype(np.float64)

    def _visible_tree(self, template: FittedTemplate, view_bin: int) -> tuple[np.ndarray, cKDTree]:
        """Indices of the samples seen from a tabulated view and a KD-tree over them (cached per template)."""
        cache = self._trees.setdefault(id(template), {})
        if view_bin not in cache:
            index = np.flatnonzero(template.visible[view_bin])
            cache[view_bin] = (index, cKDTree(template.points[index]))
        return cache[view_bin]

    def _icp(self, template: FittedTemplate, points: np.ndarray, scale: np.ndarray, rotation: np.ndarray, translation: np.ndarray, iterations: int):
        """Similarity ICP from a start pose: observed points (N, 3) to the nearest template samples the view can see.

        ``scale`` (3,) is per object axis: each iteration fits a similarity (Umeyama) to the template
        stretched by the current proportions, then, with the pose fixed, the proportions themselves by
        least squares: one factor for y and one shared by x and z (these categories have round
        bodies), each within 1 / ``stretch`` .. ``stretch`` of the template's.
        """
        view = points.mean(axis=0)
        view = view / np.linalg.norm(view)
        low, high = self.scale_range
        scale = np.asarray(scale, dtype=np.float64)
        for _ in range(iterations):
            index, tree = self._visible_tree(template, int(template.view_bin(rotation.T @ view)))
            local = (points - translation) @ rotation / scale
            distance, nearest = tree.query(local)
            keep = distance <= max(3.0 * np.median(distance), 1e-4)
            size = float(np.prod(scale) ** (1.0 / 3.0))
            proportions = scale / size
            model = template.points[index[nearest[keep]]]
            new_size, new_rotation, new_translation = umeyama(model * proportions, points[keep])
            new_size = float(np.clip(new_size, low, high))
            if self.stretch > 1.0:
                q = (points[keep] - new_translation) @ new_rotation / new_size  # object frame, template units
                horizontal = (q[:, [0, 2]] * model[:, [0, 2]]).sum() / max((model[:, [0, 2]] ** 2).sum(), 1e-12)
                vertical = (q[:, 1] * model[:, 1]).sum() / max((model[:, 1] ** 2).sum(), 1e-12)
                proportions = np.array([horizontal, vertical, horizontal])
                proportions = proportions / np.prod(proportions) ** (1.0 / 3.0)
                proportions = np.clip(proportions, 1.0 / self.stretch, self.stretch)
            new_scale = new_size * proportions
            step = np.linalg.norm(new_translation - translation) + np.abs(new_scale - scale).max() * template.extents.max()
            scale, rotation, translation = new_scale, new_rotation, new_translation
            if step < 5e-5:  # 0.05 mm: converged
                break
        return scale, rotation, translation
