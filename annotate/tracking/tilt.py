"""An object's tilt, frame by frame, from its own faces: a shallow bowl's across its axis, a laptop's whole rotation.

A shallow bowl is close to a sphere: a frame's points pin its tilt (the direction of its axis) only through the
few flat faces across the axis, its foot and its inner bottom, which point-to-plane registration weighs no more
than the curved wall. The axis fit to the model is refused for such a shape (engine._usable_axis), so every frame
keeps the tilt the chains and the smoothing gave it, off by 2-4 deg over whole stretches (v5 bowl seed 1, 3 manual
frames). A frame that sees a flat face measures its tilt directly: the normals of its own points within
``cone_deg`` of the object's y are turned onto y (faces.tilt_onto_axis, about x and z only; the spin is free).
One frame's normals are noisy (a few hundred, estimated from 1-2 mm depth noise), so each frame takes the median
of the tilts measured within ``half_window`` frames of it, where there are at least ``min_count`` of them (a guard
against one frame's noise; on the v5 bowls it moved no median by more than 0.04 deg): a hand-held bowl's tilt
error changes slowly.

Measured on the v5 bowls (bench_tracking, rotation median / p90, deg), against the model-based snap alone
(faces.tilt_onto_axis on the model), with 5 deg cones, 20 normals at least, +-6 frames and 3 measured in them:
- 4 manual frames off by up to 3 deg / 5 mm / 8 %, seeds 0-3: 0.77/1.49, 1.10/1.92, 0.64/1.32, 0.94/1.76 ->
  0.26/0.63, 0.49/1.41, 0.35/0.69, 0.51/1.08; unseen seeds 4-7: 0.92/1.53, 0.52/0.71, 0.52/1.05, 1.62/5.21 ->
  0.26/0.64, 0.27/0.49, 0.41/0.87, 0.46/2.55;
- 3 manual frames off by up to 3 deg: 0.68/1.60, 2.19/3.71, 0.50/1.07, 0.75/3.00 -> 0.50/1.56, 0.94/3.28,
  0.32/0.86, 0.67/2.11; off by up to 5 deg: 0.90/2.36, 2.70/4.57, 0.49/0.99, 1.62/3.75 -> 0.44/4.37, 1.57/3.69,
  0.37/1.12, 1.07/4.21 (seed 0's frames 89-96 were the chains' sheared poses, propagate.predict, fixed since:
  0.40/0.98 with both).
Sums over the 16 runs: medians 16.9 -> 8.9 deg, p90s 36.0 -> 29.6 deg; failing bowl checks 10 -> 7. Post hoc on the
same poses (medians / p90s summed, deg): 32 neighbours per normal 8.6 / 25.6, 16 9.9 / 26.1, 64 9.2 / 27.1; with
16, cones of 4 and 7 deg 11.0 / 27.4 and 9.4 / 26.0, 40 normals 10.2 / 28.4, windows of +-4 and +-8 frames 9.9 /
26.6 and 10.2 / 26.7.
A mug (not symmetric, its body nearly round), after the body's axis snap or where that is refused (all v5 mugs with
3 manual frames): its foot and inner bottom measure the tilt the same way. v5 mugs, rotation medians / p90s (deg):
- 4 manual frames, seeds 0-3: 1.35/2.26, 1.36/2.86, 0.69/2.67, 0.74/2.12 -> 0.93/2.18, 1.12/2.85, 0.75/2.60,
  0.96/2.04; 3 manual frames off by 3 deg: 0.74/1.60, 1.19/2.99, 0.70/2.16, 2.29/3.10 -> 0.85/1.35, 1.08/2.85,
  0.72/2.16, 2.12/3.11; off by 5 deg: 0.86/2.24, 1.08/2.71, 0.63/1.20, 1.86/3.17 -> 0.81/2.37, 0.90/1.84, 0.62/1.18,
  1.70/3.16; unseen seeds 4-7: 1.70/48.8, 0.78/1.89, 1.32/2.45, 1.23/2.77 -> 1.41/48.8, 0.82/2.78, 1.33/2.38,
  1.01/2.80.
The 16 medians summed 18.5 -> 17.1 deg, failing mug checks 8 -> 7 (seed 4's median now passes); what is left is
the spin about the axis (mug seed 3 with 3 manual frames: -1.56 deg on average where the handle is hidden).
Measured and not kept: the axis from the side's normals per frame instead (the plane their directions span):
medians with 3 manual frames 0.74, 1.19, 0.70, 2.29 -> 1.54, 3.61, 1.40, 2.68 deg (the handle and the hand).

Not for cans and bottles, whose side pins the tilt in every frame and whose axis fit the engine accepts: there it
made the p90s worse in 31 of 32 runs (can seed 1: 0.50 -> 3.99 deg).

A laptop (``hinged``): the hinge snap turns all frames alike onto the model's faces, but the frames that see the base
from above and those that see it from below share no face, and each group keeps the rotation its manual frames
gave it. v5 laptop seed 1 (4 manual frames, one of them above): spins about y of +1.0 deg above and -1.25 deg below
(medians), and the reconstructed lid two-faced by 2 deg. Each frame's base (normals onto +-y) and lid (normals
into the y-z plane, which fixes the spin) measure all three angles (faces.hinge_rotation on the frame's own
normals), and each frame takes the median over the same window. Measured (bench_tracking, v5 laptops, rotation
medians and box-centre medians; the turn is about the box centre, so the centres stay):
- 4 manual frames off by up to 3 deg / 5 mm / 8 %, seeds 0-3: 0.62, 1.20, 0.52, 0.29 -> 0.10, 0.17, 0.14, 0.11 deg;
  p90s 0.69, 1.59, 0.91, 0.57 -> 0.39, 1.35, 0.84, 0.40 deg; F@5 mm after reconstruct-sequence 0.998, 0.832,
  0.992, 0.989 -> 1.000, 0.865, 0.989, 0.990 (seed 1 now passing);
- 3 manual frames off by up to 3 deg: 0.16, 1.20, 0.42, 0.59 -> 0.08, 0.13, 0.13, 0.12 deg; off by up to 5 deg:
  0.21, 1.76, 0.53, 1.18 -> 0.08, 0.13, 0.12, 0.12 deg (seed 1 now passing); unseen seeds 4-7: 0.36, 0.47, 0.86,
  0.60 -> 0.25, 0.12, 0.13, 0.15 deg.
Measured on every second frame only (``TrackingConfig.hinge_tilt_every``): a laptop frame's crop and normals cost
~30 ms of CPU (laptop seed 1: 3.09 -> 1.66 s of CPU in all), and over the four settings the same checks fail, the
medians within 0.02 deg, seed 2's p90 0.84 -> 1.05 deg, F@5 mm within 0.002.
Laptop checks failing over the four settings: 8 -> 6 (the centres left: seed 1's group seen from above sits 3.5 mm
off along y, which no face ties). Turned about each frame's points' centroid instead of the box centre: centres
summed over three settings 35.5 -> 35.6 mm, the same checks failing. For cameras (faces.face_rotation per frame, two
faces at least) it was worse: medians 0.76, 0.85, 0.64, 1.35 -> 0.80, 0.90, 0.99, 0.66 deg, p90s up to 2.67 deg.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from evaluate.geometry import untransform

from .faces import hinge_rotation, tilt_onto_axis
from .tracker import Tracker
from annotate.workers import ordered_map


def frame_tilt(points_obj: np.ndarray, normal_radius: float, cone_deg: float, min_normals: int, max_deg: float, max_nn: int = 32,
               plane_deg: float | None = None) -> np.ndarray | None:
    """The rotation vector (3,; rad, object frame, about x and z) that turns the normals of a frame's points
    ``points_obj`` (N, 3; object frame, m) lying within ``cone_deg`` of +-y onto y, or None where fewer than
    ``min_normals`` lie there or the turn exceeds ``max_deg`` (a hand's palm, or a curved patch seen from one side
    whose normals pull the cone's mean towards its edge: not a face of the object).

    With ``plane_deg`` (a hinged body, a laptop), the whole rotation of faces.hinge_rotation instead: the base's
    normals onto +-y and those within ``plane_deg`` of the y-z plane (the lid's, the base's front and back edges')
    into it, which also fixes the spin about y; None where fewer than ``min_normals`` lie in the cone or the plane.

    The frame's pose is corrected by :func:`untilted` (``pose @ R(w)^T``): its object frame turns by the inverse.
    """
    points_obj = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3)
    if len(points_obj) < min_normals:
        return None
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_obj))
    # normals from up to ``max_nn`` points within a few voxels: one frame's depth noise (1-2 mm on 4 mm voxels)
    # spreads 16-point normals by several degrees, and the cone then keeps a lopsided share of them
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius, max_nn=max_nn))
    normals = np.asarray(cloud.normals)
    if plane_deg is None:
        rotation, _ = tilt_onto_axis(normals, cone_deg, min_points=min_normals)
    else:
        rotation, _ = hinge_rotation(normals, cone_deg, plane_deg, min_points=min_normals)
    if rotation is None:
        return None
    turn = Rotation.from_matrix(rotation).as_rotvec()
    return turn if np.degrees(np.linalg.norm(turn)) <= max_deg else None


def frame_tilts(tracker: Tracker, poses: dict[str, np.ndarray], hinged: bool = False, every: int = 1, skip: frozenset = frozenset()) -> dict[str, np.ndarray]:
    """Per frame whose points measure it (:func:`frame_tilt`, with the tracker's configuration): its tilt (3,);
    ``hinged``: a laptop's whole rotation (the hinge's cone and plane). One crop and normal estimate per frame, on
    the tracker's workers; with ``every`` k > 1, only every k-th frame of ``poses`` (in its order) is measured, and
    never the frames in ``skip`` (suspect ones: a frame far off its object measures a tilt that is not the object's)."""
    config = tracker.config
    plane = config.hinge_plane_deg if hinged else None
    cone = config.hinge_cone_deg if hinged else config.flat_cone_deg

    def measure(frame_id: str) -> np.ndarray | None:
        pose = poses[frame_id]
        points, _ = tracker.crop(frame_id, pose, margin=0.0)
        return frame_tilt(untransform(pose, points), 4 * config.voxel_size, cone, config.min_tilt_normals, config.max_frame_tilt_deg, plane_deg=plane)

    ids = [f for f in list(poses)[:: max(int(every), 1)] if f not in tracker.store.errors and f not in skip]
    return {f: tilt for f, tilt in zip(ids, ordered_map(measure, ids, config.worker_count())) if tilt is not None}


def windowed_medians(ids: list[str], measured: dict[str, np.ndarray], half_window: int, min_count: int = 1) -> dict[str, np.ndarray]:
    """Per frame of ``ids`` (in order) with at least ``min_count`` measurements (``measured``: frame id -> (3,), a
    tilt in rad or an offset in m) within ``half_window`` frames: the median (per component) of those. Other frames
    are absent from the result (they keep their pose)."""
    values = np.full((len(ids), 3), np.nan)
    for i, frame_id in enumerate(ids):
        if frame_id in measured:
            values[i] = measured[frame_id]
    out = {}
    for i, frame_id in enumerate(ids):
        window = values[max(0, i - half_window) : i + half_window + 1]
        window = window[np.isfinite(window[:, 0])]
        if len(window) >= max(min_count, 1):
            out[frame_id] = np.median(window, axis=0)
    return out


def each_frame_untilted(tracker: Tracker, ids: list[str], poses: dict[str, np.ndarray], hinged: bool = False, every: int = 1,
                        skip: frozenset = frozenset()) -> dict[str, np.ndarray]:
    """``poses`` (frame id -> 4x4, frames ``ids`` in order) each turned by the median of the tilts measured within
    ``tilt_window`` frames of it (:func:`frame_tilts`, :func:`windowed_medians`, :func:`untilted`); a frame with fewer
    than ``min_tilt_frames`` measured near it keeps its pose; the frames in ``skip`` are turned but measure nothing."""
    config = tracker.config
    tilts = windowed_medians(ids, frame_tilts(tracker, poses, hinged=hinged, every=every, skip=skip), config.tilt_window, config.min_tilt_frames)
    return {f: untilted(p, tilts[f]) if f in tilts else p for f, p in poses.items()}


def untilted(pose: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """``pose`` (4x4) with its object frame turned by the inverse of ``tilt`` (3,; rad) about the box centre."""
    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, :3] = out[:3, :3] @ Rotation.from_rotvec(tilt).as_matrix().T
    return out
