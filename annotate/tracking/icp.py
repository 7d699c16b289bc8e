"""Point-to-plane ICP that reuses the target's search structure: Open3D's ``registration_icp``, step for step.

Open3D's ``registration_icp`` builds a KD-tree on the target at every call (twice per frame,
coarse and fine), and tracking registers many frames against the same model (tens of
registrations per model, each model several times larger than a frame: the tree builds take about
a third of the ICP time). This module runs the same loop with the model's search grid built once
(:meth:`ModelTarget.grid`: an exact k-nearest search, nearest_grid.py), and reproduces Open3D's
result bit for bit (Open3D 0.20, one thread):

- the transformed source cloud and the update (``compute_transformation``: the robust
  normal equations and their solve) are Open3D's own calls, on the same inputs;
- the correspondences are each point's nearest model point at a squared distance strictly
  below the squared cut, the squared distances summed as nanoflann sums them (x, y, z in
  order, no fused multiply-add), the error summed in source order as one-thread Open3D does;
- the accumulated transform ``update @ T`` sums its products in Eigen's order (k = 0..3);
- the convergence test, fitness and inlier RMSE are Registration.cpp's.

Only a tie, two model points at the same squared distance from a frame point to the last bit, can
resolve otherwise: nanoflann keeps the first it finds, the grid the lower index. Ties are rare but
real (of the order of one in a thousand registrations), and a run that meets one can then drift
to slightly different poses. tests/test_tracking_icp.py checks the equality against Open3D.

The per-point loops (the bookkeeping of :class:`NearestModelPoints`, the pairs) are compiled
(icp_kernels.py), with the same results to the last bit as the numpy code and scipy's KD-tree. The
compiled loops, with the fine stage taking over the coarse stage's points, take about half the time
of the numpy code, and the grid's searches instead of the KD-tree's take a fifth to a quarter off
that; cells of 3 voxels (``registration.GRID_CELL_VOXELS``) search faster than cells of 2 or 4.

The tracker's models also orient their normals (registration.py), and then, with
``RegistrationParams.facing`` (the default), a pair whose model normal faces away from the camera
is dropped and a stage ends once the pose stops moving: a departure from Open3D on purpose, which
Open3D's ``registration_icp`` cannot express. Targets without oriented normals run as above.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d

from . import icp_kernels
from .sampling import every_kth, every_kth_stride

if TYPE_CHECKING:  # registration imports this module
    from .registration import ModelTarget, RegistrationParams

#: Eigen's ``isIdentity()`` default precision for double (``dummy_precision``).
_EIGEN_PRECISION = 1e-12

#: The first search reaches this many cut distances: points off the model stay certified clear while ICP moves them.
REACH = 1.5

#: With the facing test, a stage also ends once an iteration moves the pose by less than these (m, rad):
#: tighter bounds let a stage run on, for a third more time per frame, through steps that no longer move the pose.
SETTLED_STEP_M = 1e-4
SETTLED_STEP_RAD = 3e-4

#: Model points kept per source point between searches (3, 6 or 8 are no faster with the grid).
CANDIDATES = 4


def is_identity(T: np.ndarray) -> bool:
    """Eigen's ``Matrix4d::isIdentity()``: Open3D skips transforming the source when this holds."""
    off = ~np.eye(4, dtype=bool)
    diagonal = np.diag(T)
    return bool(np.all(np.abs(T[off]) <= _EIGEN_PRECISION) and np.all(np.abs(diagonal - 1.0) <= np.minimum(np.abs(diagonal), 1.0) * _EIGEN_PRECISION))


def compose(update: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``update @ T`` (4x4) with each entry's four products summed in order k = 0..3, as Eigen does
    (numpy's matmul may sum in another order, and the last bit then differs)."""
    return ((update[:, 0:1] * T[0:1, :] + update[:, 1:2] * T[1:2, :]) + update[:, 2:3] * T[2:3, :]) + update[:, 3:4] * T[3:4, :]


#: Slack (m) on the certificates below: far above the rounding of distances under 1 m (~1e-16 m), far below model spacing.
_SLACK = 1e-9


class NearestModelPoints:
    """Each source point's nearest model point, kept up to date as the source moves between ICP iterations.

    A search for every point at every iteration is most of ICP's time, while ICP moves the
    points by a fraction of the model spacing per iteration. So each point keeps the ``CANDIDATES``
    model points found nearest to it by its last search (``len(target)`` where fewer were within
    ``reach``), the nearest of them (``best``), and two lower bounds (m): ``other``, on its distance
    to the other candidates, and ``clear``, on its distance to every non-candidate. A move by
    ``delta`` lowers both bounds by ``delta`` (triangle inequality). A point is settled, exactly,
    while ``best`` is nearer than both bounds, or while it and both bounds are beyond the cut (no
    model point within the cut). An unsettled point first checks all its candidates (renewing
    ``best`` and ``other``), and only a point still unsettled is searched again (the target's grid).
    """

    def __init__(self, target: "ModelTarget", query: np.ndarray, reach: float, known: "NearestModelPoints | None" = None, rows: np.ndarray | None = None) -> None:
        """The nearest model points of ``query`` (N, 3), searched within ``reach``; with ``known`` (a state of the
        points ``query[rows]`` on the same target, at any positions), those rows take over its candidates and bounds
        and only the others are searched (a fine stage after a coarse stage on every k-th of its points)."""
        self.target = target
        self.reach = float(reach)
        # the model's points with one far point appended, where a missing candidate points
        self._model = np.concatenate([target.points, np.full((1, 3), 1e6)])
        self.position = np.array(query, dtype=np.float64, order="C").reshape(-1, 3)
        n = len(self.position)
        self.candidates = np.empty((n, CANDIDATES), dtype=np.int64)
        self.clear = np.empty(n)
        self.best = np.empty(n, dtype=np.int64)
        self.other = np.empty(n)
        self._d2 = np.empty(n)
        todo = np.ones(n, dtype=bool)
        if known is not None:
            # the bounds hold for the known positions: the next move (advance) starts from those
            self.position[rows], self.candidates[rows], self.clear[rows] = known.position, known.candidates, known.clear
            self.best[rows], self.other[rows], self._d2[rows] = known.best, known.other, known._d2
            todo[rows] = False
        self._search(np.flatnonzero(todo))

    def _search(self, rows: np.ndarray) -> None:
        distance, index = self.target.grid().query(self.position[rows], CANDIDATES + 1, self.reach)
        icp_kernels.searched(rows, distance, index, len(self.target), self.reach, self.candidates, self.clear, self.position, self._model, self.best, self.other, self._d2)

    def within(self, query: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Move the points to ``query`` (N, 3); the rows whose nearest model point is at a squared distance
        strictly below ``distance``^2 (``distance`` <= ``reach``), their model indices and those squared distances."""
        d2 = self.move_to(query, distance)
        keep = np.flatnonzero(d2 < distance * distance)
        return keep, self.best[keep], d2[keep]

    def move_to(self, query: np.ndarray, distance: float) -> np.ndarray:
        """Move the points to ``query`` (N, 3): every point's squared distance (N,) to its nearest model point
        (``best``), exact where that lies within ``distance`` (<= ``reach``) of it. The array is the state's own."""
        stale = icp_kernels.advance(np.ascontiguousarray(query, dtype=np.float64), float(distance), _SLACK, self.position, self.clear, self.other,
                                    self.best, self.candidates, self._model, self._d2)
        if len(stale):
            self._search(stale)
        return self._d2


def correspondences(nearest: NearestModelPoints, query: np.ndarray, distance: float, camera: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Open3D's correspondence step (GetRegistrationResultAndCorrespondences) with the points moved to ``query`` (N, 3).

    With ``camera`` (the camera's centre in the object frame, m), pairs whose model normal faces away from it are dropped.

    Returns the (K, 2) int32 pairs (source index, model index) in source order, the fitness
    K / N and the inlier RMSE (m) of those pairs.
    """
    d2 = nearest.move_to(query, distance)
    # a frame sees only surfaces that face its camera: a model point whose (oriented) surface faces away from the
    # camera at this pose is the other side of a thin wall (a laptop's base seen from below, the model holding only
    # its top), no partner for the frame point beside it
    normals, offsets = nearest.target.facing_planes() if camera is not None else (_NO_NORMALS, _NO_OFFSETS)
    pairs, error2 = icp_kernels.pairs(d2, nearest.best, float(distance), camera is not None,
                                     np.zeros(3) if camera is None else np.asarray(camera, dtype=np.float64), normals, offsets)
    if len(pairs) == 0:
        return pairs, 0.0, 0.0
    return pairs, len(pairs) / len(query), float(np.sqrt(error2 / len(pairs)))


#: Stand-ins for a target's planes where no pair is tested for facing.
_NO_NORMALS, _NO_OFFSETS = np.zeros((1, 3)), np.zeros(1)


def icp_stage(
    source: o3d.geometry.PointCloud,
    target: "ModelTarget",
    distance: float,
    init: np.ndarray,
    estimation: o3d.pipelines.registration.TransformationEstimation,
    max_iteration: int,
    nearest: NearestModelPoints | None = None,
    relative_fitness: float = 1e-5,
    relative_rmse: float = 1e-5,
    facing: bool = False,
    carried: np.ndarray | None = None,
) -> tuple[np.ndarray, float, float, NearestModelPoints]:
    """One ``registration_icp`` call (Registration.cpp's RegistrationICP): transform, fitness, inlier RMSE (m),
    and the nearest-point state (pass it to the next stage on the same source and target; with ``carried``, the
    rows of ``source`` that ``nearest``'s points are, the other points' state is searched afresh). With ``facing``
    (the target's normals oriented), only model points whose surface faces the camera pair (:func:`correspondences`)."""
    T = np.array(init, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(source.points)  # Open3D copies the source; colours play no part here
    if not is_identity(T):
        pcd.transform(T)
    if nearest is None or carried is not None:
        nearest = NearestModelPoints(target, np.asarray(pcd.points), distance * REACH, nearest, carried)
    pairs, fitness, rmse = correspondences(nearest, np.asarray(pcd.points), distance, T[:3, 3] if facing else None)
    for _ in range(max_iteration):
        update = np.asarray(estimation.compute_transformation(pcd, target.cloud, o3d.utility.Vector2iVector(pairs)))
        T = compose(update, T)
        pcd.transform(update)
        previous = (fitness, rmse)
        pairs, fitness, rmse = correspondences(nearest, np.asarray(pcd.points), distance, T[:3, 3] if facing else None)
        if abs(previous[0] - fitness) < relative_fitness and abs(previous[1] - rmse) < relative_rmse:
            break
        if facing and np.abs(update[:3, 3]).max() < SETTLED_STEP_M and np.abs(update[:3, :3] - np.eye(3)).max() < SETTLED_STEP_RAD:
            # the facing test toggles pairs at grazing angles, so fitness and RMSE keep changing by a point or
            # two while the pose no longer moves
            break
    return T, fitness, rmse, nearest


def point_to_plane(source: o3d.geometry.PointCloud, target: "ModelTarget", init: np.ndarray, params: "RegistrationParams") -> tuple[np.ndarray, float, float]:
    """Coarse-to-fine point-to-plane ICP with a Tukey kernel: registration._icp_open3d's result, tree built once;
    with ``params.coarse_points``, the coarse stage on every k-th point (Open3D's ICP on those, then the fine stage's on all).

    The coarse stage runs most of the iterations (about 70 % on a laptop) on frames of up to 2,500 points (laptops
    ~2,100, bowls ~1,500, the others under 900). Every k-th point, up to ``coarse_points`` (1,500), brings the pose
    into the fine stage's reach as well as all of them do, and saves time on the large frames (a laptop's); fewer
    points (1,200) save little more and leave a bowl's rotations further off.
    """
    reg = o3d.pipelines.registration
    T, fitness, rmse, nearest, previous = np.asarray(init, dtype=np.float64), 0.0, 0.0, None, None
    # the coarse stage only brings the pose into the fine stage's reach: every k-th point does that (see above)
    coarse = thinned(source, params.coarse_points)
    for stage, distance in enumerate((params.max_distance, params.fine_distance)):
        estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=max(params.kernel, distance / 2)))
        points = coarse if stage == 0 else source
        carried = None
        if nearest is not None and nearest.reach < distance:
            nearest = None  # a wider stage than the last: search afresh
        elif nearest is not None and points is not previous:
            # the coarse stage's points are every k-th of these: their state carries over, a third of the searches
            carried = np.arange(0, len(points.points), every_kth_stride(len(points.points), params.coarse_points))
        T, fitness, rmse, nearest = icp_stage(points, target, distance, T, estimation, params.iterations, nearest, facing=params.facing and target.oriented,
                                              carried=carried)
        previous = points
    # column-major, as Open3D hands back its Eigen matrix: numpy's products on it then round as before
    return np.asfortranarray(T), fitness, rmse


def load_kernels() -> None:
    """Compile the compiled loops now, or load them from numba's cache (about 0.3 s), in this process: worker processes
    forked after this inherit them, where each would otherwise load them again at its first registration (tracking
    forks its workers anew for every map of frames)."""
    global _kernels_loaded
    if _kernels_loaded:
        return
    from .registration import ModelTarget, RegistrationParams

    # a small plate seen from above, registered from 1 mm off: every loop runs, with the argument types of real use
    grid = np.stack(np.meshgrid(np.arange(8), np.arange(8), [0.0]), axis=-1).reshape(-1, 3) * 0.003
    target = ModelTarget(grid, voxel_size=0.003, views=np.tile([0.0, 0.0, 1.0], (len(grid), 1)))
    init = np.eye(4)
    init[:3, 3] = [0.001, 0.0, 0.3]
    point_to_plane(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(grid + [0.0, 0.0, -0.3])), target, init, RegistrationParams())
    _kernels_loaded = True


_kernels_loaded = False


def thinned(source: o3d.geometry.PointCloud, count: int) -> o3d.geometry.PointCloud:
    """``source`` itself where it holds at most ``count`` points (0: no limit), otherwise a cloud of every k-th of its
    points (sampling.every_kth)."""
    points = np.asarray(source.points)
    kept = every_kth(points, count)
    return source if kept is points else o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept))
