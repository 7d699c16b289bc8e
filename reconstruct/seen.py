"""What was seen: every part of the reconstructed surface labelled observed, inferred or unseen, and the tight box's
faces that a measurement bounds.

- observed: some frame measured that surface: its camera sees the point (the first hit of the ray to it, on
  the reconstruction at that frame's pose, on a face turned to the camera) and a measured depth point lies
  within OBSERVED_TOLERANCE of it
  (the benchmark's definition of the true surface's observed part, applied to the reconstruction);
- inferred: no frame measured it, but the solid of revolution placed it (the fill carved the space beside it,
  within LABEL_REACH voxels: :mod:`reconstruct.revolution`);
- unseen: neither: the hull's face toward space that no frame saw free (a bowl's underside never shown becomes
  a solid skirt down to where the carving's grid ends).

The labels go with the export (a coloured PLY beside the report, their shares in it); a box face is bounded by
a measurement when at least half the surface within LABEL_REACH voxels of it is observed ("measured"), or when it
faces the plane the object stands on (:mod:`reconstruct.support`) and at least half that surface lies on it
("support": the table measured beside it bounds it, though no frame saw the face itself). Faces of the box that
rest on surface no frame measured are named, with the turn that would show them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from evaluate.geometry import box_corners

from .carving import VoxelGrid
from .support import SupportPlane

OBSERVED, INFERRED, UNSEEN = 0, 1, 2
LABEL_NAMES = ("observed", "inferred", "unseen")
#: Colours (RGB) of the labels in the PLY and the browser's preview: grey, blue, orange-red.
LABEL_COLOURS = np.array([[200, 200, 200], [80, 140, 230], [235, 90, 40]], dtype=np.uint8)
#: How far (voxels) the fill's evidence reaches a surface point, and how near a box face the surface that bounds it
#: lies: marching cubes puts the surface between voxel centres, and smoothing moves it by about a voxel more.
LABEL_REACH = 2
#: A surface point is observed in a frame that sees it when a measured point lies this near (metres): depth noise,
#: quantisation and a pixel's footprint (as the benchmark's observed true surface).
OBSERVED_TOLERANCE = 0.004
#: Every this many pixels of a frame's depth are measured points for the test (a pixel is ~1.3 mm at 0.7 m).
PIXEL_STRIDE = 2
#: Face states whose extent a measurement bounds: the face's own surface, or the plane the object stands on.
BOUNDED = ("measured", "support")
#: A box face faces the support when its outward normal is within acos(this) of the plane's inward one, reversed.
SUPPORT_FACING_COS = 0.95
#: The box's faces, as (axis, sign, name, the turn that shows them) in the object frame (ShapeNet axes, y up).
BOX_FACES = (
    (1, -1, "-y (bottom)", "turn the object over to show its underside"),
    (1, 1, "+y (top)", "show the object from above"),
    (0, -1, "-x", "turn the object about its vertical axis to show its -x side"),
    (0, 1, "+x", "turn the object about its vertical axis to show its +x side"),
    (2, -1, "-z", "turn the object about its vertical axis to show its -z side (a mug's handle side)"),
    (2, 1, "+z", "turn the object about its vertical axis to show its +z side"),
)


@dataclass
class SurfaceLabels:
    """Per-vertex labels of a mesh (OBSERVED, INFERRED, UNSEEN) and what they say about its tight box."""

    labels: np.ndarray  # (V,) uint8
    shares: dict[str, float]  # area share of each label
    faces: dict[str, str]  # box face -> "measured" | "support" | "inferred" | "unseen"

    def observed_faces(self, faces: np.ndarray) -> np.ndarray:
        """(F,) bool: the mesh's ``faces`` (F, 3 vertex indices) labelled observed (:func:`face_labels`)."""
        return face_labels(self.labels, faces) == OBSERVED

    def unmeasured_faces(self) -> list[tuple[str, str]]:
        """(face, the turn that would show it) for every box face no measurement bounds."""
        return [(name, advice) for _, _, name, advice in BOX_FACES if self.faces.get(name) not in BOUNDED]

    def report(self) -> dict:
        return {"surface_shares": {k: round(v, 4) for k, v in self.shares.items()}, "box_faces": dict(self.faces),
                "to_show": [f"{face}: {advice}" for face, advice in self.unmeasured_faces()]}


def face_labels(labels: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) label per face of ``faces`` (F, 3 vertex indices) from the vertices' ``labels`` (V,): a face takes its
    vertices' most trusted label, observed over inferred over unseen (the shares and the benchmark count faces so)."""
    return np.asarray(labels)[np.asarray(faces)].min(axis=1)


def _lookup(zone: np.ndarray, grid: VoxelGrid, points: np.ndarray) -> np.ndarray:
    index = np.rint((points - np.asarray(grid.origin)) / grid.voxel_size).astype(np.int64)
    inside = np.all((index >= 0) & (index < np.array(grid.shape)), axis=1)
    out = np.zeros(len(points), bool)
    out[inside] = zone[tuple(index[inside].T)]
    return out


#: The side (metres) of the cells that pre-select the points near a measured one: a hair over the tolerance, so that
#: a pair within it, rounded per axis, never lies two cells apart.
NEAR_CELL = OBSERVED_TOLERANCE * (1 + 1e-6)


def _cell_index(points: np.ndarray, low: np.ndarray, cells: tuple[int, int, int]) -> np.ndarray:
    """(N, 3) index, padded by one, of the cell (side NEAR_CELL from ``low``) holding each of ``points`` (at or above ``low``)."""
    return np.minimum(((points - low) / NEAR_CELL).astype(np.int64), np.array(cells) - 1) + 1


def _near_cells(measured: np.ndarray, low: np.ndarray, cells: tuple[int, int, int]) -> np.ndarray:
    """(cells + 2) bool, padded by one cell on every side: the cells (:func:`_cell_index`) holding a ``measured``
    point or next to one."""
    padded = np.array(cells) + 2
    index = _cell_index(measured, low, cells)
    occupied = np.unique(np.ravel_multi_index(index.T, padded))
    steps = np.ravel_multi_index(np.indices((3, 3, 3)).reshape(3, -1), padded) - np.ravel_multi_index((1, 1, 1), padded)
    near = np.zeros(int(np.prod(padded)), bool)
    near[(occupied[:, None] + steps[None]).ravel()] = True  # the 3x3x3 neighbourhood of each cell (never wraps: padded)
    return near.reshape(padded)


def observed_points(points: np.ndarray, faces: np.ndarray, frames, camera) -> np.ndarray:
    """(V,) bool: which surface ``points`` (V, 3, object frame; a mesh's vertices with its ``faces``) some frame observed.

    ``frames`` yields (4x4 pose object to camera, depth (H, W) metres, 0 = none). A point once observed is not
    tested again, so the frames after the first few test few points.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(points.astype(np.float32)), o3d.core.Tensor(np.asarray(faces, np.uint32)))
    observed = np.zeros(len(points), bool)
    low, high = points.min(axis=0) - 0.01, points.max(axis=0) + 0.01
    corners = box_corners(high - low) + (high + low) / 2
    cells = tuple(int(n) for n in np.floor((high - low) / NEAR_CELL) + 1)
    cell_of = _cell_index(points, low, cells)
    for pose, depth in frames:  # one ray cast and one tree per frame, over the points not yet observed
        todo = np.flatnonzero(~observed)
        if not len(todo):
            break
        R, t = pose[:3, :3], pose[:3, 3]
        # only the pixels where the box about the points projects can hold a measured point near one
        measured, _ = camera.backproject(depth, stride=PIXEL_STRIDE, window=camera.window(corners @ R.T + t))
        measured = (measured - t) @ R
        measured = measured[np.all((measured >= low) & (measured <= high), axis=1)]
        if not len(measured):
            continue
        # near a measured point first, and only those points need the ray cast: a point within the tolerance of one
        # lies in its cell of side NEAR_CELL or a neighbouring one (a cheap superset), then the tree's test
        todo = todo[_near_cells(measured, low, cells)[tuple(cell_of[todo].T)]]
        tree = cKDTree(measured, balanced_tree=False, compact_nodes=False)
        todo = todo[np.isfinite(tree.query(points[todo], distance_upper_bound=OBSERVED_TOLERANCE)[0])]
        if not len(todo):
            continue
        centre = -R.T @ t
        ray = points[todo] - centre
        length = np.linalg.norm(ray, axis=1)
        rays = np.concatenate([np.broadcast_to(centre, ray.shape), ray / length[:, None]], axis=1).astype(np.float32)
        answer = scene.cast_rays(o3d.core.Tensor(rays))
        # the ray's first hit is the point, on a face turned to the camera (a grazing ray slips past an edge)
        visible = (answer["t_hit"].numpy() > length - 0.001) & (np.einsum("ij,ij->i", answer["primitive_normals"].numpy(), rays[:, 3:]) < 0)
        observed[todo[visible]] = True
    return observed


def label_surface(mesh: trimesh.Trimesh, grid: VoxelGrid, frames, camera, filled: np.ndarray | None, centre: np.ndarray,
                  support: SupportPlane | None = None) -> SurfaceLabels:
    """Label ``mesh`` (object frame, re-centred by the tight box's ``centre``: its points lie at p + centre in the frame
    the ``frames``' poses and the ``grid`` use). ``frames`` yields (pose, depth) as for :func:`observed_points`;
    ``filled``: voxels the revolved fill carved (None without symmetry); ``support``: the plane the object stands on
    (that frame), or None."""
    points = np.asarray(mesh.vertices) + np.asarray(centre)
    labels = np.full(len(points), UNSEEN, dtype=np.uint8)
    if filled is not None and filled.any():
        zone = ndimage.binary_dilation(filled, ndimage.generate_binary_structure(3, 1), iterations=LABEL_REACH)
        labels[_lookup(zone, grid, points)] = INFERRED
    labels[observed_points(points, np.asarray(mesh.faces), frames, camera)] = OBSERVED
    per_face = face_labels(labels, mesh.faces)
    area = np.asarray(mesh.area_faces)
    total = max(float(area.sum()), 1e-12)
    shares = {name: float(area[per_face == k].sum() / total) for k, name in enumerate(LABEL_NAMES)}
    vertices = np.asarray(mesh.vertices)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    reach = LABEL_REACH * grid.voxel_size
    faces = {}
    for axis, sign, name, _ in BOX_FACES:  # six faces
        near = vertices[:, axis] <= low[axis] + reach if sign < 0 else vertices[:, axis] >= high[axis] - reach
        if not near.any():
            faces[name] = "unseen"
            continue
        share = np.bincount(labels[near], minlength=3) / near.sum()
        faces[name] = "measured" if share[OBSERVED] >= 0.5 else "inferred" if share[INFERRED] >= share[UNSEEN] else "unseen"
        if faces[name] != "measured" and support is not None and -sign * support.normal[axis] >= SUPPORT_FACING_COS:
            on_plane = support.height(points[near]) <= support.band + reach
            if on_plane.mean() >= 0.5:
                faces[name] = "support"
    return SurfaceLabels(labels, shares, faces)


def coloured_ply(mesh: trimesh.Trimesh, labels: SurfaceLabels) -> bytes:
    """The mesh as a binary PLY with its vertices coloured by label (:data:`LABEL_COLOURS`)."""
    coloured = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=LABEL_COLOURS[labels.labels], process=False)
    return trimesh.exchange.ply.export_ply(coloured, encoding="binary")
