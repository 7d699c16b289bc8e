"""Registration backends: a frame's points (camera frame) against the object model (object frame).

Every backend answers the same question: the 4x4 transform ``T_obj_cam`` (camera to object
coordinates, metres) that best aligns the frame's points onto the model, starting from an
initial guess. Backends are selected by name (:data:`BACKENDS`):

- ``point_to_plane``: Open3D point-to-plane ICP with a Tukey robust kernel (the hand and
  background points inside the box are outliers to it), coarse-to-fine.
- ``colored``: Open3D coloured ICP (Park et al.), geometry plus photometric term.
- ``generalized``: Open3D generalized ICP (plane-to-plane).
- ``kiss``: kiss-icp's building blocks (VoxelHashMap + Registration, point-to-point with a
  Geman-McClure kernel) at object scale.

No backend may take the process down: inputs are validated (finite, enough points, a
finite initial guess, positive kernel widths, which kiss-icp's Sophus code asserts on),
outputs are checked for finiteness, and a failure comes back as ``ok=False`` with a reason.

Facing pairs (``RegistrationParams.facing``, on by default; ``annotate --track --no-facing`` turns it
off): a frame sees only surfaces that face its camera, so a point-to-plane pair whose model normal faces
away from the camera at the current pose is dropped (icp.correspondences). The model's normals are
turned towards the cameras that saw each voxel (model.ObjectModel keeps their mean direction), so no
frame normals are estimated (PCA frame normals cost 2.5 s per laptop sequence). This tells the two
sides of a thin wall apart: without it a laptop's chains slid along its up axis by the base's thickness
(the keyboard face paired with the model's underside, at a high fitness), and with the test they do not
(tests: a 6 mm slab seen from below slides 6 mm without it, under 0.1 mm with it).
A stage then also ends once an iteration moves the pose by less than 0.1 mm and 0.017 deg (pairs at
grazing angles toggle, and fitness never settles). With the test fewer goal checks fail and the centres
lie closer, most of all on laptops; a few more frames can come out far off where they are taken from the
one chain that lost the object (a weakness of the seam, not of the pairs). The test is not applied in the
chains of an object without symmetry whose placed frames' model is nearly round (engine: a mug, its chains
then lost the spin where the handle was hidden; a camera, nearly round by that test too, failed more goal
checks with it); its joint refinement applies it (engine.py: a mug's inner bottom paired with the outer one).

Not used: ``colored`` as the default (no more accurate, a mug's run lost the object, and a laptop several
times slower), nor an earlier form of the facing test (frame normals estimated, an opposite-facing nearest
point replaced by the nearest facing candidate), which lost a laptop and was slower. ``colored`` on the
laptops, through the whole pipeline, left the centres further off and took two to three times as long; as a
last step for a stretch a few mm off, each frame registered with colour to the model of the other frames, it
made the frames jump to the next of the label's stripes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
import open3d as o3d

from annotate.workers import open3d_threads  # noqa: F401  (re-exported: the engine and tests import it from here)

from . import icp

#: The side of the ICP's search grid's cells, in model voxels (the fastest: icp.py's module doc).
GRID_CELL_VOXELS = 3.0

#: Below this many points on either side a registration is not attempted (too few to fix 6 DoF robustly).
MIN_POINTS = 30


@dataclass
class RegistrationResult:
    """``transform``: 4x4 T_obj_cam; ``fitness``: share of source points within ``max_distance`` of the model;
    ``inlier_rmse``: RMS distance of those (m); ``ok``: False when the registration could not run or diverged."""

    transform: np.ndarray
    fitness: float
    inlier_rmse: float
    ok: bool = True
    reason: str = ""


class ModelTarget:
    """The registration target: model points (M, 3) in the object frame with normals and colours, built once.

    Holds the Open3D cloud and, lazily, a search grid of the points (nearest_grid.CellGrid: the point-to-plane ICP,
    :mod:`.icp`, and the fitness and information measures query it; built once per target, where Open3D's ICP built a
    KD-tree per call) and kiss-icp's voxel map.
    """

    def __init__(self, points: np.ndarray, colors: np.ndarray | None = None, voxel_size: float = 0.003, views: np.ndarray | None = None) -> None:
        """``views`` (M, 3): per point, a direction towards the cameras that saw it (object frame; any length, 0:
        unknown): the normals are turned to face it, so that a surface's two sides are told apart."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        finite = np.all(np.isfinite(points), axis=1)
        self.points = points[finite]
        self.colors = None if colors is None else np.asarray(colors, dtype=np.float64).reshape(-1, 3)[finite]
        self.voxel_size = float(voxel_size)
        self.cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        if self.colors is not None:
            self.cloud.colors = o3d.utility.Vector3dVector(self.colors)
        self.oriented = False  # whether the normals face the cameras that saw their points
        if len(self.points) >= 3:
            # normals from ~4 voxels around each point: object-scale surface patches
            self.cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * self.voxel_size, max_nn=16))
            if views is not None:
                normals = np.asarray(self.cloud.normals)
                views = np.asarray(views, dtype=np.float64).reshape(-1, 3)[finite]
                away = np.einsum("ij,ij->i", normals, views) < 0
                normals[away] *= -1.0
                self.cloud.normals = o3d.utility.Vector3dVector(normals)
                self.oriented = True
                # a camera at c faces the surface at point q when n . c > n . q
                self._normals, self._offsets = normals, np.einsum("ij,ij->i", normals, self.points)
        self._kiss_map = None
        self._grid = None

    def facing_planes(self) -> tuple[np.ndarray, np.ndarray]:
        """The oriented normals (M, 3) and the offsets (M,) n . q of the model points' planes: a camera at c (object
        frame) faces the surface at point q when n . c > n . q (targets built with ``views`` only: :attr:`oriented`)."""
        if not self.oriented:
            raise ValueError("the model's normals are not oriented: build the target with views")
        return self._normals, self._offsets

    def nearest(self, points: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
        """Per point (N, 3), object frame: the distance (N,) m to its nearest model point and that point's index (N,),
        where one lies strictly within ``distance``; inf and ``len(self)`` where none does (scipy's KD-tree's answer)."""
        found, index = self.grid().query(points, 1, distance)
        return found[:, 0], index[:, 0]

    def grid(self):
        """The model points sorted into cells of ``GRID_CELL_VOXELS`` voxels (nearest_grid.CellGrid), built once: the
        ICP's nearest-point searches."""
        if self._grid is None:
            from .nearest_grid import CellGrid

            self._grid = CellGrid(self.points, GRID_CELL_VOXELS * self.voxel_size)
        return self._grid

    def __len__(self) -> int:
        return len(self.points)

    def kiss_map(self):
        if self._kiss_map is None:
            from kiss_icp.mapping import VoxelHashMap

            # one kiss voxel per model voxel, a few points each; max_distance is a range cut around the origin (object frame)
            self._kiss_map = VoxelHashMap(voxel_size=self.voxel_size, max_distance=100.0, max_points_per_voxel=4)
            self._kiss_map.add_points(self.points)
        return self._kiss_map




@dataclass
class RegistrationParams:
    """Object-scale ICP parameters (metres)."""

    max_distance: float = 0.01  #: correspondence cut of the coarse stage
    fine_distance: float = 0.004  #: correspondence cut of the fine stage
    kernel: float = 0.003  #: robust kernel width (Tukey k, kiss-icp's sigma)
    iterations: int = 30  #: per stage
    coarse_points: int = 1500  #: point_to_plane: the coarse stage registers at most this many of the points (every k-th; 0: all), the fine stage all of them (icp.point_to_plane)
    quality_distance: float = 0.004  #: inlier distance for fitness / RMSE
    facing: bool = True  #: point_to_plane: pair a frame point only with a model point whose surface faces the frame's camera (thin slabs; see the module doc)
    facing_figures: bool = True  #: ... and measure fitness and RMSE on those pairs too (False: on all pairs within quality_distance, as Open3D does)


def _evaluate(source: o3d.geometry.PointCloud, target: ModelTarget, transform: np.ndarray, distance: float) -> tuple[float, float]:
    ev = o3d.pipelines.registration.evaluate_registration(source, target.cloud, distance, transform)
    return float(ev.fitness), float(ev.inlier_rmse)


def _source_cloud(points: np.ndarray, colors: np.ndarray | None) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if colors is not None:
        cloud.colors = o3d.utility.Vector3dVector(colors)
    return cloud


def _icp_open3d(backend: str, source, target: ModelTarget, init: np.ndarray, params: RegistrationParams) -> tuple[np.ndarray, float, float]:
    """The transform, and the fitness and inlier RMSE at it within ``params.fine_distance`` (Open3D's
    result of the last stage: the same figures as evaluate_registration at that distance)."""
    reg = o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-5, relative_rmse=1e-5, max_iteration=params.iterations)
    T = init
    for distance in (params.max_distance, params.fine_distance):
        if backend == "point_to_plane":
            estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=max(params.kernel, distance / 2)))
            result = reg.registration_icp(source, target.cloud, distance, T, estimation, criteria)
        elif backend == "colored":
            estimation = reg.TransformationEstimationForColoredICP(lambda_geometric=0.968, kernel=reg.TukeyLoss(k=max(params.kernel, distance / 2)))
            result = reg.registration_colored_icp(source, target.cloud, distance, T, estimation, criteria)
        elif backend == "generalized":
            estimation = reg.TransformationEstimationForGeneralizedICP(epsilon=1e-3, kernel=reg.TukeyLoss(k=max(params.kernel, distance / 2)))
            result = reg.registration_generalized_icp(source, target.cloud, distance, T, estimation, criteria)
        else:
            raise ValueError(backend)
        T = result.transformation
    return np.asarray(T), float(result.fitness), float(result.inlier_rmse)


def _icp_kiss(points: np.ndarray, target: ModelTarget, init: np.ndarray, params: RegistrationParams) -> np.ndarray:
    from kiss_icp.registration import Registration

    registration = Registration(max_num_iterations=params.iterations * 2, convergence_criterion=1e-6, max_num_threads=1)
    T = np.asarray(init, dtype=np.float64)
    for distance, kernel in ((params.max_distance, max(params.kernel, params.max_distance / 3)), (params.fine_distance, params.kernel)):
        # kiss-icp asserts (aborts the process) when the kernel is 0 or inputs are NaN: both are excluded by the caller
        T = np.asarray(registration.align_points_to_map(points, target.kiss_map(), T, float(distance), float(kernel)))
    return T


def _normals_needed(backend: str) -> bool:
    return backend in ("point_to_plane", "colored")


def register(
    points: np.ndarray,
    target: ModelTarget,
    init: np.ndarray,
    backend: str = "point_to_plane",
    params: RegistrationParams | None = None,
    colors: np.ndarray | None = None,
) -> RegistrationResult:
    """Align camera-frame ``points`` (N, 3) m (optional ``colors`` (N, 3) in 0..1) to the model.

    ``init`` is the initial T_obj_cam. Never raises on bad geometry: returns ``ok=False`` and the
    initial transform with a reason (too few points, NaN, diverged).
    """
    params = params or RegistrationParams()
    if backend not in BACKENDS:
        raise ValueError(f"unknown registration backend {backend!r}; one of {', '.join(BACKENDS)}")
    init = np.asarray(init, dtype=np.float64)
    fail = lambda reason: RegistrationResult(init.copy(), 0.0, float("inf"), False, reason)  # noqa: E731
    if init.shape != (4, 4) or not np.all(np.isfinite(init)):
        return fail("initial pose is not a finite 4x4 transform")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1)
    if colors is not None:
        colors = np.asarray(colors, dtype=np.float64).reshape(-1, 3)
        finite &= np.all(np.isfinite(colors), axis=1)
        colors = colors[finite]
    points = points[finite]
    if len(points) < MIN_POINTS:
        return fail(f"only {len(points)} points in the box")
    if len(target) < MIN_POINTS:
        return fail(f"only {len(target)} points in the model")
    if not (params.kernel > 0 and params.max_distance > 0 and params.fine_distance > 0):
        return fail("registration distances must be positive")
    if backend == "colored" and (colors is None or target.colors is None):
        backend = "point_to_plane"  # no colour on one side: the geometric term alone
    if _normals_needed(backend) and not target.cloud.has_normals():
        return fail("model has no normals")
    source = _source_cloud(points, colors)
    figures = None
    try:
        if backend == "kiss":
            T = _icp_kiss(points, target, init, params)
        else:
            icp_run = icp.point_to_plane if backend == "point_to_plane" else partial(_icp_open3d, backend)
            T, fitness, rmse = icp_run(source, target, init, params)
            if params.quality_distance == params.fine_distance and (params.facing_figures or not params.facing):
                figures = (fitness, rmse)  # the ICP measured them at the final transform: no second search
    except RuntimeError as error:  # Open3D raises on degenerate systems (e.g. colored ICP without enough texture)
        return fail(f"registration failed: {' '.join(str(error).split())}")
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return fail("registration diverged (non-finite transform)")
    fitness, rmse = figures if figures is not None else _evaluate(source, target, T, params.quality_distance)
    return RegistrationResult(T, fitness, rmse, True, "")


BACKENDS = ("point_to_plane", "colored", "generalized", "kiss")
