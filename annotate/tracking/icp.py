"""Point-to-plane ICP that reuses the target's KD-tree: Open3D's ``registration_icp``, step for step.

Open3D's ``registration_icp`` builds a KD-tree on the target at every call (twice per frame,
coarse and fine), and tracking registers many frames against the same model (measured: v5
laptop seed 0, 722 registrations against 51 models, 17,000 model points against 2,100 frame
points; the tree builds were a third of the ICP time). This module runs the same loop with
the model's KD-tree built once (:meth:`ModelTarget.tree`, scipy), and reproduces Open3D's
result bit for bit (Open3D 0.20, one thread):

- the transformed source cloud and the update (``compute_transformation``: the robust
  normal equations and their solve) are Open3D's own calls, on the same inputs;
- the correspondences are each point's nearest model point at a squared distance strictly
  below the squared cut, the squared distances summed as nanoflann sums them (x, y, z in
  order, no fused multiply-add), the error summed in source order as one-thread Open3D does;
- the accumulated transform ``update @ T`` sums its products in Eigen's order (k = 0..3);
- the convergence test, fitness and inlier RMSE are Registration.cpp's.

Only a tie between two model points at the same distance to a frame point could resolve
otherwise (nanoflann keeps the first one found); model points are voxel centroids, so ties
do not occur in practice. tests/test_tracking_icp.py checks the equality against Open3D.

The tracker's models also orient their normals (registration.py), and then, with
``RegistrationParams.facing`` (the default), a pair whose model normal faces away from the camera
is dropped and a stage ends once the pose stops moving: a departure from Open3D on purpose, which
Open3D's ``registration_icp`` cannot express. Targets without oriented normals run as above.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d

from .sampling import every_kth

if TYPE_CHECKING:  # registration imports this module
    from .registration import ModelTarget, RegistrationParams

#: Eigen's ``isIdentity()`` default precision for double (``dummy_precision``).
_EIGEN_PRECISION = 1e-12

#: The first search reaches this many cut distances: points off the model stay certified clear while ICP moves them.
REACH = 1.5

#: With the facing test, a stage also ends once an iteration moves the pose by less than these (m, rad):
#: measured on a v5 laptop (seed 3), 1e-5 / 1e-4 left 185 ms per frame, these 138 (without the test 117).
SETTLED_STEP_M = 1e-4
SETTLED_STEP_RAD = 3e-4

#: Model points kept per source point between KD-tree searches.
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

    A KD-tree query for every point at every iteration is most of ICP's time, while ICP moves the
    points by a fraction of the model spacing per iteration. So each point keeps the ``CANDIDATES``
    model points found nearest to it by its last search (``len(target)`` where fewer were within
    ``reach``), the nearest of them (``best``), and two lower bounds (m): ``other``, on its distance
    to the other candidates, and ``clear``, on its distance to every non-candidate. A move by
    ``delta`` lowers both bounds by ``delta`` (triangle inequality). A point is settled, exactly,
    while ``best`` is nearer than both bounds, or while it and both bounds are beyond the cut (no
    model point within the cut). An unsettled point first checks all its candidates (renewing
    ``best`` and ``other``), and only a point still unsettled goes back to the tree.
    """

    def __init__(self, target: "ModelTarget", query: np.ndarray, reach: float) -> None:
        self.target = target
        self.reach = float(reach)
        # model coordinates one axis per array (gathers and arithmetic on (K, N) blocks run ~3x faster than on
        # (N, K, 3)), with one far point appended, where a missing candidate points
        self._model = [np.append(target.points[:, k], 1e6) for k in range(3)]
        self.position = _columns(query)
        n = len(query)
        self.candidates = np.empty((CANDIDATES, n), dtype=np.int64)
        self.clear = np.empty(n)
        self.best = np.empty(n, dtype=np.int64)
        self.other = np.empty(n)
        self._search(np.arange(n))

    def _search(self, rows: np.ndarray) -> None:
        query = np.stack([c[rows] for c in self.position], axis=1)
        distance, index = self.target.tree().query(query, k=CANDIDATES + 1, distance_upper_bound=self.reach)
        self.candidates[:, rows] = index[:, :CANDIDATES].T
        # the next neighbour bounds every non-candidate; with none within reach, reach does
        self.clear[rows] = np.where(index[:, CANDIDATES] < len(self.target), distance[:, CANDIDATES], self.reach)
        self._rank(rows)

    def _squared(self, rows: np.ndarray | slice, index: np.ndarray) -> np.ndarray:
        """Squared distances between the points ``rows`` and model points ``index`` (..., len(rows)), as nanoflann
        sums them: x, y, z in order, no fused multiply-add."""
        dx, dy, dz = (p[rows] - m[index] for p, m in zip(self.position, self._model))
        return (dx * dx + dy * dy) + dz * dz

    def _rank(self, rows: np.ndarray) -> np.ndarray:
        """Renew ``best`` and ``other`` of ``rows`` from all their candidates; the squared distance to ``best``."""
        candidates = self.candidates[:, rows]
        d2 = self._squared(rows, candidates)
        pick = np.arange(len(rows))
        first = np.argmin(d2, axis=0)
        nearest = d2[first, pick]
        self.best[rows] = candidates[first, pick]
        d2[first, pick] = np.inf
        self.other[rows] = np.sqrt(d2.min(axis=0))
        return nearest

    def within(self, query: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Move the points to ``query`` (N, 3); the rows whose nearest model point is at a squared distance
        strictly below ``distance``^2 (``distance`` <= ``reach``), their model indices and those squared distances."""
        step = query - np.stack(self.position, axis=1)
        moved = np.sqrt(np.einsum("ij,ij->i", step, step)) + _SLACK
        self.clear -= moved
        self.other -= moved
        self.position = _columns(query)
        d2 = self._squared(slice(None), self.best)
        stale = np.flatnonzero(~_settled(d2, np.minimum(self.other, self.clear), distance))
        if len(stale):
            d2[stale] = self._rank(stale)
            still = stale[~_settled(d2[stale], self.clear[stale], distance)]
            if len(still):
                self._search(still)
                d2[still] = self._squared(still, self.best[still])
        keep = np.flatnonzero(d2 < distance * distance)
        return keep, self.best[keep], d2[keep]


def _columns(points: np.ndarray) -> list[np.ndarray]:
    """The x, y and z columns of ``points`` (N, 3) as three contiguous arrays."""
    points = np.asarray(points, dtype=np.float64)
    return [np.ascontiguousarray(points[:, k]) for k in range(3)]


def _settled(d2: np.ndarray, bound: np.ndarray, distance: float) -> np.ndarray:
    """Whether a point's kept nearest point (squared distance ``d2``) decides its correspondence, every other
    model point lying at least ``bound`` away: it is nearer than all of them, or it and they are beyond the cut."""
    bound = bound - _SLACK
    return (np.sqrt(d2) < bound) | ((d2 >= distance * distance) & (bound >= distance))


def correspondences(nearest: NearestModelPoints, query: np.ndarray, distance: float, camera: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Open3D's correspondence step (GetRegistrationResultAndCorrespondences) with the points moved to ``query`` (N, 3).

    With ``camera`` (the camera's centre in the object frame, m), pairs whose model normal faces away from it are dropped.

    Returns the (K, 2) int32 pairs (source index, model index) in source order, the fitness
    K / N and the inlier RMSE (m) of those pairs.
    """
    rows, index, d2 = nearest.within(query, distance)
    if camera is not None and len(rows):
        # a frame sees only surfaces that face its camera: a model point whose (oriented) surface faces away
        # from the camera at this pose is the other side of a thin wall (a laptop's base seen from below,
        # the model holding only its top), no partner for the frame point beside it
        facing = nearest.target.facing(camera, index)
        rows, index, d2 = rows[facing], index[facing], d2[facing]
    if len(rows) == 0:
        return np.zeros((0, 2), dtype=np.int32), 0.0, 0.0
    pairs = np.empty((len(rows), 2), dtype=np.int32)
    pairs[:, 0] = rows
    pairs[:, 1] = index
    error2 = float(np.add.accumulate(d2)[-1])  # sequential, in source order (not numpy's pairwise sum)
    return pairs, len(rows) / len(query), float(np.sqrt(error2 / len(rows)))


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
) -> tuple[np.ndarray, float, float, NearestModelPoints]:
    """One ``registration_icp`` call (Registration.cpp's RegistrationICP): transform, fitness, inlier RMSE (m),
    and the nearest-point state (pass it to the next stage on the same source and target). With ``facing``
    (the target's normals oriented), only model points whose surface faces the camera pair (:func:`correspondences`)."""
    T = np.array(init, dtype=np.float64)
    pcd = o3d.geometry.PointCloud(source.points)  # Open3D copies the source; colours play no part here
    if not is_identity(T):
        pcd.transform(T)
    if nearest is None:
        nearest = NearestModelPoints(target, np.asarray(pcd.points), distance * REACH)
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

    The coarse stage runs 70 % of the iterations (a v5 laptop: 9.7 per registration against 3.8 in the fine stage)
    on frames of up to 2,500 points (laptops ~2,100, bowls ~1,500, the others under 900). Measured with at most
    1,500 points in it (bench_tracking --reconstruct, v5 seeds 0-3, 4 manual frames off by up to 3 deg / 5 mm / 8 %):
    sums over the 24 sequences of rotation median 12.47 -> 12.40 deg, p90 27.84 -> 26.09, centre 35.53 -> 35.00 mm,
    no goal check failing either way (posed-mesh F@5mm 0.92-1.00); cans and cameras within 0.02; laptops 144/221/204/
    168 -> 165/176/175/144 ms per frame in one session (the flagged frames, whose rechecks cost registrations, move
    both ways: seed 0 0 -> 22). With 3 manual frames (bowls and mugs, where that setting fails checks) 3 -> 3 checks
    failing, bowl seed 1's p90 3.55 -> 2.67 deg, mug seed 2's 2.16 -> 1.34. At most 1,200 points: laptops a further
    6 ms faster, but bowl seed 1's p90 1.18 -> 2.52 deg.
    """
    reg = o3d.pipelines.registration
    T, fitness, rmse, nearest, previous = np.asarray(init, dtype=np.float64), 0.0, 0.0, None, None
    # the coarse stage only brings the pose into the fine stage's reach: every k-th point does that (measured above)
    coarse = thinned(source, params.coarse_points)
    for stage, distance in enumerate((params.max_distance, params.fine_distance)):
        estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=max(params.kernel, distance / 2)))
        points = coarse if stage == 0 else source
        if nearest is not None and (nearest.reach < distance or points is not previous):
            nearest = None  # a wider stage than the last, or other points: search afresh
        T, fitness, rmse, nearest = icp_stage(points, target, distance, T, estimation, params.iterations, nearest, facing=params.facing and target.oriented)
        previous = points
    # column-major, as Open3D hands back its Eigen matrix: numpy's products on it then round as before
    return np.asfortranarray(T), fitness, rmse


def thinned(source: o3d.geometry.PointCloud, count: int) -> o3d.geometry.PointCloud:
    """``source`` itself where it holds at most ``count`` points (0: no limit), otherwise a cloud of every k-th of its
    points (sampling.every_kth)."""
    points = np.asarray(source.points)
    kept = every_kth(points, count)
    return source if kept is points else o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept))
