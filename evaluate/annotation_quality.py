"""How close ground truth made by the toolkit (tracked poses, a reconstructed mesh) comes to a known truth.

The benchmark suite (``benchmarks/run_suite.py``) scores every sequence with these figures:

- poses: rotation error (symmetry-aware: for ``symmetry: y`` the angle between the y axes), box-centre
  error, the share of frames flagged for review, and frames off by more than 5 degrees (or 10 mm) that
  carry no flag;
- the reconstruction posed in every frame against the true mesh posed in it (the F-score at 5 mm in the
  true object frame, median over frames): pose and shape errors together, as a user of the export sees them;
- the reconstruction's shape alone (aligned to the true mesh by the mean of its frames' transforms, then
  ICP): F-score at 5 mm overall, and on the *observed* surface (what some frame measured: visible from its camera
  and within OBSERVED_TOLERANCE of a measured point of the object) recall over the true one and precision over the
  reconstruction's own (its labels, by the same definition: reconstruct.seen);
- the extents of its tight box against the true extents.

The true surface is the mesh's outer surface: a mesh built by joining parts (a camera's lens barrel set into its
body) holds faces inside the solid, which no camera can see; they are left out (:func:`exterior_samples`).

Frames: poses map object (ShapeNet axes, metres) to camera (OpenCV); meshes in the object frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from evaluate.metrics.pose_errors import rotation_error
from evaluate.metrics.sampling import ShapeIndex, sample_surface, sample_surface_faces
from evaluate.metrics.shape_metrics import fscore_from_hits

#: A true surface sample counts as observed in a frame when its camera sees it (the first hit of the ray to it, on a face
#: turned to the camera) and a measured object point lies within this distance (metres): depth noise, quantisation
#: and a pixel's footprint.
OBSERVED_TOLERANCE = 0.004
#: The F-score distance of the suite's shape and posed figures (metres).
FSCORE_THRESHOLD = 0.005
#: Directions (spread evenly over the sphere) tried for a ray from a true surface sample out of the object: enough
#: for the inner bottom of a mug (a cone of about 25 deg half-angle through its opening holds about 11 of them).
EXTERIOR_DIRECTIONS = 256


def surface_sample_count(area: float, threshold: float = FSCORE_THRESHOLD, minimum: int = 5000) -> int:
    """Points to sample on a surface of ``area`` m^2 so that they lie at most half the F-score threshold apart: two
    samplings of one surface agree only to about their spacing (a 3456 cm^2 laptop with 5000 points: F@5mm 0.83 against
    itself)."""
    return max(minimum, int(np.ceil(area / (threshold / 2) ** 2)))


def pose_scores(poses: dict[str, np.ndarray], flagged: dict[str, bool], truth_poses: dict[str, np.ndarray], symmetry: str) -> dict:
    """Figures of tracked ``poses`` against ``truth_poses`` over the frames both hold (degrees, millimetres, shares)."""
    ids = [f for f in truth_poses if f in poses]
    if not ids:
        raise ValueError("no frame has both a pose and a true pose")
    A = np.stack([truth_poses[f] for f in ids])
    B = np.stack([poses[f] for f in ids])
    degrees = rotation_error(A[:, :3, :3], B[:, :3, :3], symmetry)
    mm = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1) * 1000.0
    flags = np.array([bool(flagged.get(f, False)) for f in ids])
    return {
        "frames": len(ids),
        "rot_median_deg": float(np.median(degrees)),
        "rot_p90_deg": float(np.percentile(degrees, 90)),
        "centre_median_mm": float(np.median(mm)),
        "flagged_share": float(flags.mean()),
        "unflagged_over_5deg": int(np.sum((degrees > 5.0) & ~flags)),
        "unflagged_over_10mm": int(np.sum((mm > 10.0) & ~flags)),
    }


@dataclass
class TrueSurface:
    """The true surface's samples (object frame), indexed, and which of them some frame observed."""

    index: ShapeIndex
    observed: np.ndarray  # (N,) bool

    @property
    def observed_share(self) -> float:
        return float(self.observed.mean())


def _scene(mesh) -> "o3d.t.geometry.RaycastingScene":
    """Open3D's ray-casting scene of ``mesh``'s triangles."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return scene


def observed_samples(points: np.ndarray, mesh, frames) -> np.ndarray:
    """(N,) bool: which true surface ``points`` (object frame) some frame observed.

    ``frames`` yields (4x4 true pose, (M, 3) measured object points in the camera frame) per frame; the
    object's own mesh (object frame) decides what each camera sees, so a thin wall's far side does not count.
    """
    scene = _scene(mesh)
    observed = np.zeros(len(points), bool)
    for T, measured in frames:  # one ray cast and one tree per frame
        if len(measured) == 0:
            continue
        R, t = T[:3, :3], T[:3, 3]
        centre = -R.T @ t  # the camera in the object frame
        ray = points - centre
        length = np.linalg.norm(ray, axis=1)
        rays = np.concatenate([np.broadcast_to(centre, ray.shape), ray / length[:, None]], axis=1).astype(np.float32)
        answer = scene.cast_rays(o3d.core.Tensor(rays))
        # nothing of the object in front of the sample, which lies on a face turned to the camera (outward normals)
        visible = (answer["t_hit"].numpy() > length - 0.001) & (np.einsum("ij,ij->i", answer["primitive_normals"].numpy(), rays[:, 3:]) < 0)
        near = cKDTree((measured - t) @ R).query(points[visible], distance_upper_bound=OBSERVED_TOLERANCE)[0]
        observed[np.flatnonzero(visible)[np.isfinite(near)]] = True
    return observed


def revolution_fscore(mesh, threshold: float = FSCORE_THRESHOLD, turns: int = 6, samples: int = 20000, seed: int = 0) -> float:
    """How nearly ``mesh`` (object frame) is a solid of revolution about its y axis: the least F-score at ``threshold``
    between its surface samples and the same samples turned about y by each of ``turns`` angles evenly spread over
    (0, 180] deg. 1 for a cylinder; a square bowl 0.82, a flattened bottle 0.49."""
    points = sample_surface(mesh, samples, seed=seed)
    index = ShapeIndex(points)
    scores = []
    for angle in np.linspace(0.0, np.pi, turns + 1)[1:]:  # one F-score per turn
        c, s = np.cos(angle), np.sin(angle)
        turned = points @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]).T
        scores.append(index.fscore(turned, threshold).fscore)
    return float(min(scores))


def sphere_directions(count: int) -> np.ndarray:
    """``count`` unit vectors (count, 3) spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0**0.5) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def exterior_samples(points: np.ndarray, mesh, directions: int = EXTERIOR_DIRECTIONS, offset: float = 1e-4) -> np.ndarray:
    """(N,) bool: which ``points`` (N, 3) on ``mesh`` (object frame, m) lie on its outer surface: a ray from the point
    (started ``offset`` m along it) leaves the mesh without a hit in one of ``directions`` directions. A face inside
    the solid (where joined parts overlap) meets the enclosing walls in every direction."""
    scene = _scene(mesh)
    points = np.asarray(points, dtype=np.float64)
    outside = np.zeros(len(points), bool)
    for direction in sphere_directions(directions):  # one ray cast per direction, over the points not yet out
        todo = np.flatnonzero(~outside)
        if not len(todo):
            break
        rays = np.concatenate([points[todo] + offset * direction, np.broadcast_to(direction, (len(todo), 3))], axis=1)
        hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        outside[todo[~np.isfinite(hit)]] = True
    return outside


def true_surface(mesh, frames, threshold: float = FSCORE_THRESHOLD, seed: int = 0) -> TrueSurface:
    """Sample the true ``mesh`` (spacing at most half ``threshold``), keep its outer surface (:func:`exterior_samples`;
    a sample some frame observed is outer by definition), index it and mark what ``frames`` observed (see
    :func:`observed_samples`)."""
    points = sample_surface(mesh, surface_sample_count(float(mesh.area), threshold), seed=seed)
    observed = observed_samples(points, mesh, frames)
    keep = observed | exterior_samples(points, mesh)
    return TrueSurface(ShapeIndex(points[keep]), observed[keep])


def posed_fscore(mesh, poses: dict[str, np.ndarray], surface: TrueSurface, truth_poses: dict[str, np.ndarray],
                 threshold: float = FSCORE_THRESHOLD, seed: int = 0) -> float:
    """Median over frames of the F-score at ``threshold`` between the reconstruction posed by ``poses`` and the true
    mesh posed by ``truth_poses``: computed in the true object frame (the same distances as between the posed meshes),
    the reconstruction's samples mapped by T_true^-1 T_pose."""
    points = sample_surface(mesh, surface_sample_count(float(mesh.area), threshold), seed=seed)
    scores = []
    for frame_id, pose in poses.items():  # one transform and one F-score per frame
        if frame_id in truth_poses:
            to_true = np.linalg.inv(truth_poses[frame_id]) @ pose
            scores.append(surface.index.fscore(points @ to_true[:3, :3].T + to_true[:3, 3], threshold).fscore)
    return float(np.median(scores))


def mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """The rigid transform nearest the mean of ``transforms`` (4x4): rotations by their chordal mean (SVD of the sum),
    translations averaged."""
    stack = np.stack(transforms)
    U, _, Vt = np.linalg.svd(stack[:, :3, :3].sum(axis=0))
    out = np.eye(4)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[:3, 3] = stack[:, :3, 3].mean(axis=0)
    return out


def alignment(points: np.ndarray, start: np.ndarray, target: np.ndarray, reach: float = 0.01) -> np.ndarray:
    """The 4x4 transform that takes ``points`` onto ``target``: ``start``, then point-to-point ICP (Open3D) with
    correspondences within ``reach`` metres (what remains of the poses' common error, removed)."""
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points @ start[:3, :3].T + start[:3, 3]))
    goal = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    result = o3d.pipelines.registration.registration_icp(source, goal, reach, np.eye(4),
                                                         o3d.pipelines.registration.TransformationEstimationPointToPoint(),
                                                         o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30))
    return result.transformation @ start


def aligned_points(points: np.ndarray, start: np.ndarray, target: np.ndarray, reach: float = 0.01) -> np.ndarray:
    """``points`` moved by :func:`alignment` onto ``target``: the reconstruction's shape compared without what remains
    of its poses' common error."""
    T = alignment(points, start, target, reach)
    return points @ T[:3, :3].T + T[:3, 3]


#: The box faces in the order of reconstruct.seen.BOX_FACES (object frame, ShapeNet axes).
FACE_NAMES = ("-y (bottom)", "+y (top)", "-x", "+x", "-z", "+z")


def shape_scores(mesh, poses: dict[str, np.ndarray], surface: TrueSurface, truth_poses: dict[str, np.ndarray],
                 threshold: float = FSCORE_THRESHOLD, seed: int = 0, observed_faces: np.ndarray | None = None) -> dict:
    """The reconstruction's shape against the true surface, aligned (:func:`mean_transform` of its frames' T_true^-1
    T_pose, then :func:`aligned_points`): F-score, precision and recall at ``threshold``, overall and on the observed
    surface; and per box face (:data:`FACE_NAMES`) how far the aligned reconstruction's extreme lies outside the
    truth's (mm; negative: inside).

    On the observed surface: recall over the observed true samples, precision over the reconstruction's own observed
    part, ``observed_faces`` ((F,) bool per face of ``mesh``: the part the reconstruction says some frame measured, by
    the definition of the truth's, reconstruct.seen), both after an alignment fitted on those two parts alone (what
    was guessed where no frame looked must not move what was seen). A guess beside the seen part (a hull bulging
    where no frame looked) is then no precision error of the seen part: it is judged by the shape F-score, the
    extents and the observed share reported. Without ``observed_faces``, the reconstruction's samples whose nearest
    true sample is an observed one stand for its observed part."""
    start = mean_transform([np.linalg.inv(truth_poses[f]) @ T for f, T in poses.items() if f in truth_poses])
    points, faces = sample_surface_faces(mesh, surface_sample_count(float(mesh.area), threshold), seed=seed)
    aligned = aligned_points(points, start, surface.index.points)
    true_hit, hit = surface.index.hits(aligned, threshold)
    overall = fscore_from_hits(true_hit, hit)
    observed = None
    claimed = None if observed_faces is None else np.asarray(observed_faces, dtype=bool)[faces]
    on_observed = surface.observed[surface.index.tree.query(aligned)[1]] if claimed is None else claimed
    if surface.observed.any() and on_observed.any():
        T = alignment(points[on_observed], start, surface.index.points[surface.observed])
        moved = points @ T[:3, :3].T + T[:3, 3]
        true_hit, hit = surface.index.hits(moved, threshold)
        on_observed = surface.observed[surface.index.tree.query(moved)[1]] if claimed is None else claimed
        observed = fscore_from_hits(true_hit[surface.observed], hit[on_observed]) if on_observed.any() else None
    low, high = aligned.min(axis=0) - surface.index.points.min(axis=0), aligned.max(axis=0) - surface.index.points.max(axis=0)
    faces = {name: float(value * 1000) for name, value in zip(FACE_NAMES, (-low[1], high[1], -low[0], high[0], -low[2], high[2]))}
    return {
        "face_errors_mm": faces,
        "shape_f5": overall.fscore,
        "shape_precision5": overall.precision,
        "shape_recall5": overall.recall,
        "observed_f5": None if observed is None else observed.fscore,
        "observed_precision5": None if observed is None else observed.precision,
        "observed_recall5": None if observed is None else observed.recall,
    }


def extents_error_mm(extents: np.ndarray, truth_extents: np.ndarray) -> list[float]:
    """The reconstruction's box sides minus the true ones, along object x, y, z (millimetres)."""
    return [float(x) for x in (np.asarray(extents, float) - np.asarray(truth_extents, float)) * 1000.0]
