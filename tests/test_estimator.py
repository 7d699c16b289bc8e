"""The graph estimator (annotate.estimator): its pose graph against known poses, its ICP against a known motion,
the information it reports, which boxes are anchors, and a rendered sequence tracked end to end."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_tracking_render import render_sequence

from annotate.engines import engine_name, tracking_engine
from annotate.estimator import EstimatorConfig, anchor_frames, refine_frame, track_sequence
import gtsam

from annotate.estimator.graph import Factor, _steady, sigmas, solve, without_spin
from annotate.estimator.model import fuse, is_revolution, revolution_axis, revolved
from annotate.estimator.observations import Crop, FrameCrops
from annotate.estimator.scene import PLANE_DISTANCE
from annotate.estimator.pipeline import CLOSURE_SIGMAS, _chain_model, _closure, _object_part, _Setup, chain_trust, initial_poses
from annotate.estimator.registration import Model, offset, register, retract
from annotate.estimator.review import MAX_WEAK_TURN, flag_weak_runs
from sequences.annotation import Annotation, FramePose, load_annotation, save_annotation
from sequences.reader import open_sequence
from sequences.sensor_noise import depth_sigma


def _walk(n: int, seed: int = 0) -> np.ndarray:
    """n smooth poses (n, 4, 4) of an object 0.6 m in front of the camera."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.normal(0, 0.004, (n, 3)), axis=0) + [0, 0, 0.6]
    return T


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.linalg.norm(Rotation.from_matrix(np.transpose(a[:, :3, :3], (0, 2, 1)) @ b[:, :3, :3]).as_rotvec(), axis=1))


def test_graph_recovers_poses_from_exact_steps_and_one_anchor():
    truth = _walk(40)
    info = np.diag([1e5] * 3 + [1e8] * 3)
    steps = [Factor(i, i + 1, np.linalg.inv(truth[i]) @ truth[i + 1], info) for i in range(39)]
    # the start a chain gives: the steps composed, here from a first pose 10 deg and 2 cm off the anchor
    start = truth.copy()
    start[0] = retract(truth[0], np.array([0.17, 0, 0, 0.02, 0, 0]))
    for i in range(39):
        start[i + 1] = start[i] @ steps[i].measured
    solution = solve(start, [], steps, {0: truth[0]}, sigmas(3, 0.005), sigmas(1.5, 0.003), False, 2.0)
    assert _angles(solution.poses, truth).max() < 0.05
    assert np.abs(solution.poses[:, :3, 3] - truth[:, :3, 3]).max() < 1e-4
    # the marginals grow with the distance from the anchor (a chain of relative measurements)
    sd = np.sqrt(solution.covariances[:, 3, 3])
    assert sd[39] > sd[1]


def test_the_constant_velocity_factor_has_the_jacobians_of_finite_differences():
    poses = [gtsam.Pose3(T) for T in _walk(3, seed=4)]
    values = gtsam.Values()
    for k, pose in enumerate(poses):
        values.insert(k, pose)
    factor = gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(6), [0, 1, 2], _steady)
    jacobians = [None, None, None]
    error = _steady(factor, values, jacobians)
    step = 1e-6
    for k in range(3):
        numeric = np.zeros((6, 6))
        for axis in range(6):
            moved = gtsam.Values()
            for m, pose in enumerate(poses):
                delta = np.zeros(6)
                if m == k:
                    delta[axis] = step
                moved.insert(m, pose.retract(delta))
            numeric[:, axis] = (_steady(factor, moved, None) - error) / step
        assert np.abs(jacobians[k] - numeric).max() < 1e-4
    # a steady motion costs nothing
    steady = [gtsam.Pose3(np.linalg.matrix_power(_walk(2, seed=5)[1], n)) for n in range(3)]
    for k, pose in enumerate(steady):
        values.update(k, pose)
    assert np.abs(_steady(factor, values, None)).max() < 1e-9


def test_the_graph_carries_a_steady_turn_on_past_the_last_data_and_the_walk_alone_would_not():
    # 9 deg a frame about x; the steps end at frame 14 (the object then unseen), where a chain carries its last
    # velocity on: the start there is that turn, a few degrees off
    truth = np.stack([np.eye(4)] * 20)
    truth[:, :3, :3] = Rotation.from_rotvec(np.radians(9.0) * np.arange(20)[:, None] * [1, 0, 0]).as_matrix()
    truth[:, :3, 3] = [0, 0, 0.6]
    info = np.diag([1e5] * 3 + [1e8] * 3)
    steps = [Factor(i, i + 1, np.linalg.inv(truth[i]) @ truth[i + 1], info) for i in range(14)]
    rng = np.random.default_rng(3)
    start = truth.copy()
    for k in range(15, 20):
        start[k] = retract(truth[k], np.concatenate([rng.normal(0, np.radians(2), 3), rng.normal(0, 0.002, 3)]))
    solution = solve(start, [], steps, {0: truth[0]}, sigmas(3, 0.005), sigmas(1.5, 0.003), False, 2.0)
    # the zero-velocity walk alone would stop the turn: frame 19 up to 45 deg behind
    assert _angles(solution.poses, truth).max() < 0.5


def test_each_frame_starts_from_the_chain_that_closes_better_else_the_nearer_anchor():
    def marked(value: float) -> np.ndarray:
        pose = np.eye(4)
        pose[0, 3] = value
        return pose

    anchors = {0: marked(0.0), 10: marked(0.0)}
    forward = {k: marked(1.0) for k in range(1, 10)}  # frames 1-9 from the anchor at 0 ...
    backward = {k: marked(2.0) for k in range(1, 10)}  # ... and from the anchor at 10
    tail = {k: marked(3.0) for k in range(11, 14)}  # past the last anchor: one chain only
    alike = initial_poses(14, anchors, [(0, forward, 1.0), (10, backward, 1.0), (10, tail, 0.0)])[:, 0, 3]
    assert list(alike) == [0, 1, 1, 1, 1, 1, 2, 2, 2, 2, 0, 3, 3, 3]  # frame 5 is as near to both: the first run
    astray = initial_poses(14, anchors, [(0, forward, 1.0), (10, backward, 30.0), (10, tail, 0.0)])[:, 0, 3]
    # the chain from 10 ended 30 sigmas off: it starts none of them, not even frame 9 (30 x 1/10 > 1 x 9/10)
    assert list(astray) == [0, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 3, 3, 3]


def test_a_chains_closure_carries_its_last_velocity_one_frame_on_and_counts_in_anchor_sigmas():
    from types import SimpleNamespace

    config = EstimatorConfig()  # anchor sigmas 3 deg and 5 mm
    setup = SimpleNamespace(config=config, symmetric=False)
    turn = lambda deg, x=0.0: retract(np.eye(4), np.array([0, np.radians(deg), 0, x, 0, 0]))
    start = np.eye(4)
    # a chain turning 2 deg a frame about y over frames 1-3 predicts 8 deg at frame 4, where the anchor says 8: closes
    poses = {"1": turn(2), "2": turn(4), "3": turn(6)}
    assert _closure(setup, start, poses, ["1", "2", "3"], turn(8)) < 1e-6
    # the anchor says 2 deg and 5 mm more: 2/3 + 1 sigmas
    assert abs(_closure(setup, start, poses, ["1", "2", "3"], turn(10, 0.005)) - (2 / 3 + 1)) < 1e-6
    # a one-frame chain takes its velocity from its own anchor's pose
    assert _closure(setup, start, {"1": turn(2)}, ["1"], turn(4)) < 1e-6
    # for symmetry y a spin about y is no closure error
    assert _closure(SimpleNamespace(config=config, symmetric=True), start, poses, ["1", "2", "3"], turn(40)) < 1e-6


def test_a_chain_that_does_not_close_is_outweighed_by_the_one_that_does():
    truth = _walk(21, seed=3)
    info = np.diag([1e4] * 3 + [1e7] * 3)  # a step's sigma: 0.57 deg and 0.3 mm
    exact = [Factor(i, i + 1, np.linalg.inv(truth[i]) @ truth[i + 1], info) for i in range(20)]
    # the chain from the anchor at 20 back to 0 drifts 1 deg and 1 mm a step, each step within 2 sigmas of its own
    drift = retract(np.eye(4), np.array([np.radians(1.0), 0, 0, 0.001, 0, 0]))
    astray = [Factor(i, i + 1, np.linalg.inv(truth[i]) @ truth[i + 1] @ drift, info) for i in range(20)]
    back = truth.copy()
    for i in range(19, -1, -1):
        back[i] = back[i + 1] @ np.linalg.inv(astray[i].measured)
    closure = _angles(back[:1], truth[:1])[0] / 3 + 1000 * np.linalg.norm(back[0, :3, 3] - truth[0, :3, 3]) / 5  # anchor sigmas
    assert closure > 2 * CLOSURE_SIGMAS and chain_trust(closure) < 0.25
    assert chain_trust(CLOSURE_SIGMAS) == 1.0 and chain_trust(0.0) == 1.0 and chain_trust(2 * CLOSURE_SIGMAS) == 0.25

    def worst(weight: float) -> float:
        steps = exact + [replace(f, weight=weight) for f in astray]
        solution = solve(truth, [], steps, {0: truth[0], 20: truth[20]}, sigmas(3, 0.005), sigmas(1.5, 0.003), False, 2.0)
        return _angles(solution.poses, truth).max()

    assert worst(1.0) > 2.0  # trusted alike, the drift spreads over the run and moves the anchors 3 deg
    assert worst(chain_trust(closure)) < 0.4 * worst(1.0)


def test_graph_registrations_fix_poses_and_an_outlier_is_held_by_the_robust_kernel():
    truth = _walk(30, seed=1)
    info = np.diag([1e4] * 3 + [1e7] * 3)
    measured = truth.copy()
    measured[12] = retract(truth[12], np.array([0.3, 0, 0, 0.05, 0, 0]))  # a registration 17 deg and 5 cm off
    regs = [Factor(i, None, measured[i], info) for i in range(30)]
    steps = [Factor(i, i + 1, np.linalg.inv(truth[i]) @ truth[i + 1], info) for i in range(29)]
    solution = solve(truth.copy(), regs, steps, {}, sigmas(3, 0.005), sigmas(1.5, 0.003), False, 2.0)
    assert _angles(solution.poses, truth)[12] < 0.5
    assert np.linalg.norm(solution.poses[12, :3, 3] - truth[12, :3, 3]) < 0.002


def test_symmetry_removes_the_spin_from_the_factors():
    truth = _walk(20, seed=2)
    info = np.diag([1e5] * 3 + [1e8] * 3)
    spun = truth.copy()
    for k in range(20):  # registrations that spun the object about its y by up to 40 deg: a symmetric one fits as well
        spun[k] = retract(truth[k], np.array([0, np.radians(2 * k), 0, 0, 0, 0]))
    regs = [Factor(k, None, spun[k], info) for k in range(20)]
    solution = solve(truth.copy(), regs, [], {0: truth[0]}, sigmas(3, 0.005), sigmas(1.5, 0.003), True, 2.0)
    y_true, y_solved = truth[:, :3, 1], solution.poses[:, :3, 1]
    # within a third of the registrations' own 0.18 deg (the motion prior meets the walk's changes of velocity)
    assert np.degrees(np.arccos(np.clip(np.sum(y_true * y_solved, axis=1), -1, 1))).max() < 0.06
    removed = without_spin(info)
    assert removed[1, 1] < 1e-8 * np.trace(info) and removed[0, 0] == info[0, 0]


def _box_model(half=(0.05, 0.03, 0.04), spacing=0.003) -> Model:
    """Points and outward normals on the faces of a box (object frame)."""
    points, normals = [], []
    half = np.asarray(half)
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        u = np.arange(-half[others[0]], half[others[0]] + 1e-9, spacing)
        v = np.arange(-half[others[1]], half[others[1]] + 1e-9, spacing)
        U, V = np.meshgrid(u, v, indexing="ij")
        for sign in (-1, 1):
            p = np.zeros((U.size, 3))
            p[:, others[0]], p[:, others[1]], p[:, axis] = U.ravel(), V.ravel(), sign * half[axis]
            n = np.zeros_like(p)
            n[:, axis] = sign
            points.append(p)
            normals.append(n)
    return Model(np.concatenate(points), np.concatenate(normals))


def _seen(model: Model, pose: np.ndarray, noise: float, rng) -> Crop:
    """The model's points that face the camera at ``pose``, in the camera frame, with depth noise."""
    points = model.points @ pose[:3, :3].T + pose[:3, 3]
    normals = model.normals @ pose[:3, :3].T
    facing = np.einsum("ij,ij->i", normals, -points) > 0
    return Crop(points[facing] + rng.normal(0, noise, (facing.sum(), 3)), normals[facing])


def test_registration_recovers_a_known_pose_and_reports_its_information():
    rng = np.random.default_rng(0)
    model = _box_model()
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("xyz", [30, 40, 10], degrees=True).as_matrix()
    truth[:3, 3] = [0.02, -0.01, 0.6]
    crop = _seen(model, truth, 0.0005, rng)
    start = retract(truth, np.array([np.radians(3), -np.radians(2), 0.0, 0.004, -0.003, 0.002]))
    result = register(crop, model, start, EstimatorConfig())
    error = offset(truth, result.pose)
    assert np.degrees(np.linalg.norm(error[:3])) < 0.1
    assert np.linalg.norm(error[3:]) < 0.0003
    assert result.fitness > 0.95 and result.rmse < 0.001
    assert np.all(np.linalg.eigvalsh(result.information) > 0)


def test_a_cylinder_leaves_its_spin_without_information():
    angles = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    heights = np.linspace(-0.04, 0.04, 25)
    A, H = np.meshgrid(angles, heights)
    points = np.stack([0.04 * np.cos(A.ravel()), H.ravel(), 0.04 * np.sin(A.ravel())], axis=1)
    normals = np.stack([np.cos(A.ravel()), np.zeros(A.size), np.sin(A.ravel())], axis=1)
    model = Model(points, normals)
    pose = np.eye(4)
    pose[:3, 3] = [0, 0, 0.6]
    result = register(_seen(model, pose, 0.0, np.random.default_rng(1)), model, pose, EstimatorConfig())
    info = result.information
    assert info[1, 1] < 1e-6 * info[0, 0]  # the spin about y: no information
    assert info[4, 4] < 1e-6 * info[3, 3]  # and the slide along y neither


def test_a_run_of_weak_turns_is_flagged_whole_and_a_box_ends_it():
    # turns:       a run 1..5 with one frame over the limit, a lone 2.1 at 7 (no frame over: kept), a run 9..12 cut by the box at 11
    turns = [1.2, 2.1, 2.05, 2.6, 2.0, 2.15, 1.1, 2.1, 1.0, 2.1, 2.3, 2.4, 2.1, None]
    figures = [{} if t is None else {"weak_turn": t} for t in turns]
    for f in figures:
        if f.get("weak_turn", 0) > MAX_WEAK_TURN:
            f.update(flagged=True, flag_reason="own reason")
    anchored = np.zeros(len(turns), dtype=bool)
    anchored[11] = True
    flag_weak_runs(figures, anchored)
    flagged = [k for k, f in enumerate(figures) if f.get("flagged")]
    assert flagged == [1, 2, 3, 4, 5, 9, 10, 11]  # 11 is the box (its own figures flagged it; the pipeline keeps boxes unflagged)
    assert "5 frames in a row" in figures[2]["flag_reason"] and "2.6x" in figures[2]["flag_reason"]
    assert figures[3]["flag_reason"] == "own reason"  # a frame over the limit keeps its own reason alone
    assert "2 frames in a row" in figures[9]["flag_reason"]  # 9..10: the box at 11 ends the run; 12 stays unflagged
    assert not figures[12].get("flagged")


def test_fuse_keeps_the_two_sides_of_a_thin_wall_apart():
    x = np.linspace(0, 0.05, 20)
    outer = np.stack([x, np.zeros_like(x), np.full_like(x, 0.001)], axis=1)
    inner = np.stack([x, np.zeros_like(x), np.full_like(x, -0.001)], axis=1)
    up, down = np.tile([0, 0, 1.0], (20, 1)), np.tile([0, 0, -1.0], (20, 1))
    model = fuse([(outer, up), (inner, down)], 0.004)
    assert np.any(model.normals[:, 2] > 0.99) and np.any(model.normals[:, 2] < -0.99)


def _bowl_profile(step: float = 0.0005) -> tuple[np.ndarray, np.ndarray]:
    """A bowl's profile, (K, 2) points (r, y) and their normals (K, 2), axis frame (m): a cone wall 3 mm thick
    flaring from r 5 cm at its foot (y -3 cm) to 8 cm at its rim (y +3 cm), a flat bottom inside and out, a flat rim."""
    y = np.arange(-0.03, 0.03, step)
    outer = np.stack([0.05 + 0.5 * (y + 0.03), y], axis=1)
    y_in = y[y > -0.027]
    inner = np.stack([0.047 + 0.5 * (y_in + 0.03), y_in], axis=1)
    slant = np.array([1.0, -0.5]) / np.hypot(1.0, 0.5)
    r_out, r_in = np.arange(0, 0.05, step), np.arange(0, 0.0485, step)
    rim = np.arange(0.077, 0.08, step)
    points = np.concatenate([outer, inner, np.stack([r_out, np.full_like(r_out, -0.03)], 1),
                             np.stack([r_in, np.full_like(r_in, -0.027)], 1), np.stack([rim, np.full_like(rim, 0.03)], 1)])
    normals = np.concatenate([np.tile(slant, (len(outer), 1)), np.tile(-slant, (len(inner), 1)), np.tile([0, -1.0], (len(r_out), 1)),
                              np.tile([0, 1.0], (len(r_in), 1)), np.tile([0, 1.0], (len(rim), 1))])
    return points, normals


def _bowl_model(tilt_deg: tuple[float, float], centre_mm: tuple[float, float], rng, hand: bool = False, oval: float = 1.0) -> tuple[Model, np.ndarray, np.ndarray]:
    """The bowl spun about an axis tilted (about x, z) and moved (x, z) in the object frame, 2 mm apart, 0.5 mm noise;
    with ``hand``, a 2 cm patch of points 1 cm outside its wall on one side; ``oval`` stretches it along x. Also the
    axis (R, c)."""
    profile, normals = _bowl_profile(0.002)
    spins = 160
    angle = np.repeat(np.linspace(0, 2 * np.pi, spins, endpoint=False)[None], len(profile), 0).ravel()
    r, y = np.repeat(profile, spins, 0).T
    nr, ny = np.repeat(normals, spins, 0).T
    points = np.stack([r * np.cos(angle), y, r * np.sin(angle)], 1)
    normal = np.stack([nr * np.cos(angle), ny, nr * np.sin(angle)], 1)
    if hand:
        a, h = np.meshgrid(np.linspace(-0.15, 0.15, 12), np.linspace(-0.01, 0.01, 12))
        radius = 0.05 + 0.5 * (h.ravel() + 0.03) + 0.01
        points = np.concatenate([points, np.stack([radius * np.cos(a.ravel()), h.ravel(), radius * np.sin(a.ravel())], 1)])
        normal = np.concatenate([normal, np.stack([np.cos(a.ravel()), np.zeros(a.size), np.sin(a.ravel())], 1)])
    if oval != 1.0:
        points[:, 0] *= oval
        normal[:, 0] /= oval
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    R = Rotation.from_euler("xz", tilt_deg, degrees=True).as_matrix()
    c = np.array([centre_mm[0], 0.0, centre_mm[1]]) / 1000
    return Model(points @ R.T + c + rng.normal(0, 0.0005, points.shape), normal @ R.T), R, c


def _profile_error(model: Model, R: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Each model point's distance (m) from the bowl's true surface (its profile about the true axis)."""
    from scipy.spatial import cKDTree

    p = (model.points - c) @ R
    return cKDTree(_bowl_profile()[0]).query(np.stack([np.hypot(p[:, 0], p[:, 2]), p[:, 1]], 1))[0]


def test_a_body_of_revolution_is_spun_about_its_own_axis_and_a_hand_does_not_bulge_its_ring():
    rng = np.random.default_rng(3)
    model, R, c = _bowl_model((2.0, -1.5), (3.0, -2.0), rng, hand=True)
    axis = revolution_axis(model.points, model.normals, 0.004, 9.0, 0.015)
    spun = revolved(model, 0.004, axis)
    assert spun is not None
    error = _profile_error(spun, R, c)
    # the profile's bins are a voxel (4 mm) wide: a slanted wall's mean lies within a fraction of a millimetre
    assert np.percentile(error, 95) < 0.0008 and error.max() < 0.002
    # the spun model's points are spread around the whole circle, a point every voxel
    angles = np.arctan2(spun.points[:, 2] - c[2], spun.points[:, 0] - c[0])
    assert np.histogram(angles, bins=36, range=(-np.pi, np.pi))[0].min() > 0
    assert np.allclose(np.linalg.norm(spun.normals, axis=1), 1.0)


def test_an_axis_further_from_y_than_the_boxes_can_be_off_or_an_oval_is_refused():
    rng = np.random.default_rng(4)
    fit = lambda model: revolution_axis(model.points, model.normals, 0.004, 9.0, 0.015)
    assert fit(_bowl_model((15.0, 0.0), (0.0, 0.0), rng)[0]) is None
    assert fit(_bowl_model((0.0, 0.0), (25.0, 0.0), rng)[0]) is None
    model, R, c = _bowl_model((5.0, 3.0), (8.0, 5.0), rng)
    axis = fit(model)
    assert axis is not None and revolved(model, 0.004, axis) is not None
    fitted, centre = Rotation.from_rotvec([axis[0], 0.0, axis[1]]).as_matrix()[:, 1], np.array([axis[2], 0.0, axis[3]])
    assert np.degrees(np.arccos(fitted @ R[:, 1])) < 0.1
    assert np.linalg.norm(np.cross(centre - c, R[:, 1])) < 0.0003  # the fitted point lies on the true axis
    # an oval 10 % wider one way: its walls lie 2 mm off their profile at the median, half a voxel
    oval = _bowl_model((0.0, 0.0), (0.0, 0.0), rng, oval=1.1)[0]
    assert revolved(oval, 0.004, fit(oval)) is None
    assert revolved(_bowl_model((0.0, 0.0), (0.0, 0.0), rng, oval=1.05)[0], 0.004, np.zeros(4)) is not None


def test_a_round_bowl_is_a_surface_of_revolution_about_its_axis_only_and_a_square_one_about_none():
    rng = np.random.default_rng(5)
    model, _, c = _bowl_model((0.0, 0.0), (3.0, -2.0), rng)
    assert is_revolution(model.points, model.normals, 0.004, np.array([0.0, 0.0, c[0], c[2]]))
    # about a parallel axis 6 mm away its walls lie up to 6 mm off their profile: no surface of revolution
    assert not is_revolution(model.points, model.normals, 0.004, np.array([0.0, 0.0, c[0] + 0.006, c[2]]))
    # a square dish 12 cm wide, 5 cm tall, 2 mm apart: its walls' radius grows by 41 % from the middle to a corner
    t, y = np.meshgrid(np.arange(-0.06, 0.06, 0.002), np.arange(0.0, 0.05, 0.002))
    t, y = t.ravel(), y.ravel()
    half = np.full_like(t, 0.06)
    walls = [np.stack([half, y, t], 1), np.stack([-half, y, t], 1), np.stack([t, y, half], 1), np.stack([t, y, -half], 1)]
    normals = [np.tile(n, (len(t), 1)) for n in ([1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0])]
    square = np.concatenate(walls) + rng.normal(0, 0.0005, (4 * len(t), 3))
    assert not is_revolution(square, np.concatenate(normals).astype(float), 0.004, np.zeros(4))


class _Scene:
    """A depth camera (VGA, 525 px focal length) whose frames' images are given."""

    camera = type("Camera", (), {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5})()

    def __init__(self, *depths: np.ndarray) -> None:
        self._depths = {str(k): d for k, d in enumerate(depths)}
        self.ids = list(self._depths)

    def depth(self, frame_id: str) -> np.ndarray:
        return self._depths[frame_id]


def test_scene_planes_finds_a_table_and_a_noisy_far_wall_once_each():
    rng = np.random.default_rng(3)
    v, u = np.mgrid[:480, :640]
    down = (v - 239.5) / 525.0  # the ray's y per unit depth: the table lies 0.13 m below the camera
    with np.errstate(divide="ignore"):
        table = np.where(down > 0, 0.13 / down, np.inf)
    depth = np.where(table < 2.05, table + rng.normal(0, 0.002, table.shape), 2.05 + rng.normal(0, 0.006, table.shape))
    depth[100:200, 250:350] = rng.uniform(0.5, 1.0, (100, 100))  # clutter: no plane
    depth[rng.random(depth.shape) < 0.3] = 0  # the sensor's holes
    planes = FrameCrops(_Scene(depth.astype(np.float32)), 2, 0.004).planes("0")
    assert len(planes) == 2
    (n_wall, d_wall, _), (n_table, d_table, _) = sorted(planes, key=lambda p: -abs(p[0][2]))
    assert abs(abs(n_wall[2]) - 1) < 1e-3 and abs(abs(d_wall) - 2.05) < 0.002
    assert abs(abs(n_table[1]) - 1) < 2e-3 and abs(abs(d_table) - 0.13) < 0.001


def _slab_on_a_table(shift_px: int, table: float = 1.0) -> np.ndarray:
    """A camera looking straight down at a table ``table`` m away, a 50 mm slab lying on it (its top face 5 cm
    nearer, 0.434 x 0.362 m: large enough to be found as a plane like the scene's), ``shift_px`` pixels right of the
    image's middle."""
    depth = np.full((480, 640), table, dtype=np.float32)
    depth[140:340, 200 + shift_px : 440 + shift_px] = table - 0.05
    return depth


#: the slab's pose (object to camera) and its box grown by 2.5 cm: the table shows around the slab inside it
SLAB_POSE = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.975], [0, 0, 0, 1]])
SLAB_HALF = np.array([0.217, 0.181, 0.025]) + 0.025


def test_a_moving_objects_crop_leaves_out_the_table_and_keeps_its_own_parallel_face():
    crops = FrameCrops(_Scene(_slab_on_a_table(0), _slab_on_a_table(16)), 2, 0.004)
    assert len(crops.planes("0")) == 2  # the table and the slab's face
    assert crops.moving("0", SLAB_POSE, SLAB_HALF)
    points = crops.points_in_box("0", SLAB_POSE, SLAB_HALF)
    assert np.all(points[:, 2] < 0.95 + PLANE_DISTANCE)  # no table point
    face = np.sum(np.abs(points[:, 2] - 0.95) < 1e-6)
    assert face == len(points) == 100 * 120  # every subsampled pixel of the slab's face, which ends within the box


def test_a_crop_keeps_the_table_where_the_camera_moves_against_it():
    # the slab moves in the image, but so does the table (4 mm nearer): the camera moved, and the slab may rest on it
    crops = FrameCrops(_Scene(_slab_on_a_table(0), _slab_on_a_table(16, table=0.996)), 2, 0.004)
    assert crops.moving("0", SLAB_POSE, SLAB_HALF)
    table = [(n, d) for n, d, _ in crops.planes("0") if abs(abs(d) - 1.0) < 0.002]
    assert len(table) == 1 and not crops.still("0", *table[0])
    points = crops.points_in_box("0", SLAB_POSE, SLAB_HALF)
    assert np.sum(np.abs(points[:, 2] - 1.0) < 1e-6) > 1500


def test_a_resting_objects_crop_keeps_the_table_it_rests_on():
    rng = np.random.default_rng(5)
    frames = []
    for _ in range(2):  # the same scene, each reading with the sensor's noise and holes of its own
        depth = _slab_on_a_table(0)
        depth = depth + rng.normal(0, 1, depth.shape).astype(np.float32) * depth_sigma(depth)
        depth[rng.random(depth.shape) < 0.1] = 0
        frames.append(depth.astype(np.float32))
    assert not FrameCrops(_Scene(*frames), 2, 0.004).moving("0", SLAB_POSE, SLAB_HALF)
    crops = FrameCrops(_Scene(_slab_on_a_table(0), _slab_on_a_table(0)), 2, 0.004)
    assert not crops.moving("0", SLAB_POSE, SLAB_HALF)
    points = crops.points_in_box("0", SLAB_POSE, SLAB_HALF)
    assert np.sum(np.abs(points[:, 2] - 1.0) < 1e-6) > 1500  # the table around the slab, within its box


def test_anchors_are_the_boxes_a_person_placed_refined_or_accepted():
    doc = Annotation(sequence="s", frames={
        "1": FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "manual"),
        "2": FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "tracked"),
        "3": FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined"),
        "4": FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "tracked", {"reviewed": "accepted"}),
    })
    assert anchor_frames(doc, ["1", "2", "3", "4", "5"]) == ["1", "3", "4"]


def test_engine_switch(monkeypatch):
    monkeypatch.delenv("REDWOOD_GT_ENGINE", raising=False)
    assert engine_name("graph") == "graph" and tracking_engine("graph").track_sequence is track_sequence
    monkeypatch.setenv("REDWOOD_GT_ENGINE", "graph")
    assert engine_name() == "graph"
    with pytest.raises(ValueError, match="unknown tracking engine"):
        engine_name("nope")
    with pytest.raises(ValueError, match="must be positive"):
        EstimatorConfig(point_sigma=0).check()


FRAMES = 24
ANCHORS = ["0000002", "0000012", "0000021"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("estimator") / "box_0001"
    mesh = trimesh.creation.box(extents=[0.10, 0.06, 0.08])
    truth = render_sequence(root, mesh, frames=FRAMES, seed=4, hand=True)
    rng = np.random.default_rng(7)
    annotation = Annotation(sequence="box_0001", category="other", symmetry="none", extents=mesh.extents * np.array([1.05, 0.96, 1.03]))
    for frame_id in ANCHORS:
        off = retract(truth[frame_id], np.concatenate([rng.normal(0, np.radians(1.2), 3), rng.normal(0, 0.002, 3)]))
        annotation.frames[frame_id] = FramePose.from_matrix(off, "manual")
    return root, truth, annotation


def test_a_chains_model_leaves_out_a_hand_that_moved_where_its_frames_see_through_it(tmp_path):
    """The hand (a sphere) holds the box at one contact until frame 12, then at another. A chain's model of its anchor
    (frame 2) and the frames 14-21, fused alone, keeps the first grasp's points beside the box; the chain's model
    leaves out those that the later frames see through, and keeps the box and the grasp that stays."""
    mesh = trimesh.creation.box(extents=[0.10, 0.06, 0.08])
    truth = render_sequence(tmp_path / "box", mesh, frames=24, seed=5, hand=True)
    ids = sorted(truth)
    annotation = Annotation(sequence="box", category="other", symmetry="none", extents=mesh.extents)
    setup = _Setup(open_sequence(tmp_path / "box"), annotation, ids, EstimatorConfig(workers=1))
    members = [(ids[k], truth[ids[k]], setup.crop(ids[k], truth[ids[k]])) for k in [2, *range(14, 22)]]
    fused = fuse([_object_part(crop, pose) for _, pose, crop in members], setup.crops.voxel)
    chain = _chain_model(setup, members)
    contacts = mesh.sample(50, seed=5)  # the renderer's contacts: the sphere's centre 25 mm out from each
    first, second = (c * (1 + 0.025 / np.linalg.norm(c)) for c in contacts[:2])

    def hand_points(model: Model, centre: np.ndarray) -> int:
        beside = np.max(np.abs(model.points) - mesh.extents / 2, axis=1) > 0.004  # off the box's faces
        return int(np.sum(beside & (np.linalg.norm(model.points - centre, axis=1) < 0.03)))

    assert hand_points(fused, first) >= 6
    assert hand_points(chain, first) <= hand_points(fused, first) // 4
    assert hand_points(chain, second) == hand_points(fused, second) > 0  # held in every frame: no frame sees through it
    on_box = lambda model: int(np.sum(np.max(np.abs(model.points) - mesh.extents / 2, axis=1) <= 0.004))
    assert on_box(chain) >= 0.97 * on_box(fused)


def test_tracks_a_rendered_box_held_by_a_hand(scene):
    root, truth, annotation = scene
    tracked = track_sequence(open_sequence(root), annotation)
    ids = sorted(truth)
    assert set(tracked.frames) == set(ids)
    for frame_id in ANCHORS:  # a person's box stays in the document; the pose is the solved one, within 2 sigmas of it
        anchor = tracked.frames[frame_id]
        assert anchor.source == "manual"
        np.testing.assert_allclose(anchor.placed_matrix, annotation.frames[frame_id].matrix, atol=1e-12)
        assert "placed" in anchor.extra and anchor.extra["manual_correction_deg"] <= 6.0 and anchor.extra["manual_correction_m"] <= 0.010
    placed = np.stack([annotation.frames[f].matrix for f in ANCHORS])
    anchored = np.stack([tracked.frames[f].matrix for f in ANCHORS])
    anchor_truth = np.stack([truth[f] for f in ANCHORS])
    assert np.median(_angles(anchored, anchor_truth)) < np.median(_angles(placed, anchor_truth))  # the boxes' errors average out
    poses = np.stack([tracked.frames[f].matrix for f in ids])
    true = np.stack([truth[f] for f in ids])
    others = [k for k, f in enumerate(ids) if f not in ANCHORS]
    assert np.median(_angles(poses, true)[others]) < 2.0
    assert np.median(np.linalg.norm(poses[others, :3, 3] - true[others, :3, 3], axis=1)) < 0.004
    figures = tracked.frames[ids[5]].extra
    assert {"fitness", "sigma_deg", "sigma_mm", "pull_deg"} <= set(figures)


def test_refine_leaves_a_box_off_the_object_where_it_was_and_says_why(scene):
    root, truth, annotation = scene
    doc = annotation.copy()
    away = truth["0000007"].copy()
    away[:3, 3] += [0.3, 0.0, 0.0]  # 30 cm beside the object
    doc.frames["0000007"] = FramePose.from_matrix(away, "manual")
    result = refine_frame(open_sequence(root), doc, "0000007")
    np.testing.assert_allclose(result.position, away[:3, 3])
    assert result.extra["flagged"] and "move the box onto the object" in result.extra["flag_reason"]
    near = retract(truth["0000007"], np.array([0.03, -0.02, 0.01, 0.003, 0.002, -0.002]))
    doc.frames["0000007"] = FramePose.from_matrix(near, "manual")
    refined = refine_frame(open_sequence(root), doc, "0000007")
    assert np.linalg.norm(refined.position - truth["0000007"][:3, 3]) < np.linalg.norm(near[:3, 3] - truth["0000007"][:3, 3])


def test_annotate_track_with_the_graph_engine(scene, tmp_path):
    root, _, annotation = scene
    path = tmp_path / "doc.yaml"
    save_annotation(annotation, path)
    done = subprocess.run([sys.executable, "-m", "annotate.cli", str(root), "--annotation", str(path), "--track", "--engine", "graph"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert len(load_annotation(path).frames) == FRAMES
    wrong = subprocess.run([sys.executable, "-m", "annotate.cli", str(root), "--engine", "graph"], capture_output=True, text=True, timeout=60)
    assert wrong.returncode == 2 and "--engine applies to --track only" in wrong.stderr


def test_the_same_poses_for_any_worker_count(scene):
    from dataclasses import replace

    root, truth, annotation = scene
    sequence = open_sequence(root)
    ids = sorted(truth)
    one = track_sequence(sequence, annotation, config=EstimatorConfig(workers=1))
    import annotate.estimator.pipeline as pipeline

    floor, pipeline.MIN_FRAMES_FOR_WORKERS = pipeline.MIN_FRAMES_FOR_WORKERS, 1  # the scene is shorter than forking pays for
    try:
        two = track_sequence(sequence, annotation, config=replace(EstimatorConfig(), workers=2))
    finally:
        pipeline.MIN_FRAMES_FOR_WORKERS = floor
    for frame_id in ids:
        np.testing.assert_array_equal(one.frames[frame_id].matrix, two.frames[frame_id].matrix)


@pytest.mark.parametrize("engine", ["graph", "chains"])
def test_refined_and_accepted_boxes_stay_anchors_in_both_engines(scene, engine):
    root, truth, annotation = scene
    doc = annotation.copy()
    refined = retract(truth["0000007"], np.array([0.01, 0.0, 0.0, 0.001, 0.0, 0.0]))
    accepted = retract(truth["0000016"], np.array([0.0, 0.01, 0.0, 0.0, 0.001, 0.0]))
    doc.frames["0000007"] = FramePose.from_matrix(refined, "refined")
    doc.frames["0000016"] = FramePose.from_matrix(accepted, "tracked", {"reviewed": "accepted"})
    tracked = tracking_engine(engine).track_sequence(open_sequence(root), doc)
    # each keeps its source and stays an anchor: its box kept (beside the pose on the track, within the tolerance)
    assert tracked.frames["0000007"].source == "refined"
    np.testing.assert_allclose(tracked.frames["0000007"].placed_matrix, refined, atol=1e-9)
    assert tracked.frames["0000016"].extra.get("reviewed") == "accepted"
    np.testing.assert_allclose(tracked.frames["0000016"].placed_matrix, accepted, atol=1e-9)
    for frame_id in ("0000007", "0000016"):
        assert tracked.frames[frame_id].extra["manual_correction_deg"] <= 6.0 and tracked.frames[frame_id].extra["manual_correction_m"] <= 0.012
    assert tracked.frames["0000005"].source == "tracked"
