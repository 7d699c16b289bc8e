"""Registration backends, the object model, symmetry helpers: against known transforms and bad inputs."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from annotate.tracking import BACKENDS, closest_about_y, estimate_symmetry_axis, snap_upright
from annotate.tracking.model import ObjectModel
from annotate.tracking.quality import pose_difference
from annotate.tracking.registration import ModelTarget, RegistrationParams, register
from annotate.symmetry_axis import fit_symmetry_axis
from evaluate.geometry import invert, rotation_about_y, transform


def _known_transform(deg: float, mm: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(deg)).as_matrix()
    direction = rng.normal(size=3)
    T[:3, 3] = direction / np.linalg.norm(direction) * mm / 1000
    return T


def _box_like_object(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) on an asymmetric object (a box with a bump), object frame, and colours (N, 3)."""
    box = trimesh.creation.box(extents=[0.09, 0.06, 0.04])
    bump = trimesh.creation.icosphere(radius=0.02)
    bump.apply_translation([0.03, 0.03, 0.0])
    mesh = trimesh.util.concatenate([box, bump])
    points, _ = trimesh.sample.sample_surface_even(mesh, 4000, seed=seed)
    colors = 0.2 + 0.6 * (points - points.min(0)) / np.ptp(points, axis=0)
    return np.asarray(points), colors


@pytest.mark.parametrize("backend", BACKENDS)
def test_backends_recover_a_known_transform(backend):
    model_points, colors = _box_like_object()
    target = ModelTarget(model_points, colors, voxel_size=0.003)
    truth = _known_transform(4.0, 4.0, seed=1)  # T_obj_cam to recover
    rng = np.random.default_rng(2)
    # a camera-frame view: the model seen at pose inv(truth), with 0.5 mm noise, a subset of the points
    view = rng.choice(len(model_points), 2500, replace=False)
    points_cam = transform(invert(truth), model_points[view]) + rng.normal(size=(2500, 3)) * 0.0005
    result = register(points_cam, target, np.eye(4), backend=backend, colors=colors[view])
    assert result.ok, result.reason
    deg, metres = pose_difference(result.transform, truth)
    assert deg < 0.7 and metres < 0.001, (backend, deg, metres)
    assert result.fitness > 0.9 and result.inlier_rmse < 0.0015


@pytest.mark.parametrize("backend", BACKENDS)
def test_backends_refuse_degenerate_input_without_crashing(backend):
    model_points, colors = _box_like_object()
    target = ModelTarget(model_points, colors)
    bad_init = np.eye(4)
    bad_init[0, 3] = np.nan
    cases = [
        (np.zeros((0, 3)), np.eye(4), "only 0 points"),
        (model_points[:5], np.eye(4), "only 5 points"),
        (np.full((500, 3), np.nan), np.eye(4), "only 0 points"),
        (model_points, bad_init, "not a finite"),
    ]
    for points, init, reason in cases:
        result = register(points, target, init, backend=backend)
        assert not result.ok and reason in result.reason
    empty = register(model_points, ModelTarget(np.zeros((0, 3))), np.eye(4), backend=backend)
    assert not empty.ok and "model" in empty.reason


def test_kiss_guards_keep_the_process_alive():
    """kiss-icp aborts the process on a zero kernel or NaN input; the guarded call must return instead (checked in a child)."""
    code = (
        "import numpy as np\n"
        "from annotate.tracking.registration import ModelTarget, RegistrationParams, register\n"
        "rng = np.random.default_rng(0)\n"
        "model = ModelTarget(rng.normal(size=(2000, 3)) * 0.03)\n"
        "pts = rng.normal(size=(2000, 3)) * 0.03\n"
        "r1 = register(pts, model, np.eye(4), 'kiss', RegistrationParams(kernel=0.0))\n"
        "pts[::2] = np.nan\n"
        "r2 = register(pts, model, np.eye(4), 'kiss')\n"
        "r3 = register(np.tile([[0.0, 0.0, 0.6]], (100, 1)), model, np.eye(4), 'kiss')\n"
        "print(r1.ok, r2.ok, np.isfinite(r3.transform).all())\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-500:]
    assert run.stdout.split() == ["False", "True", "True"]


def test_model_counts_frames_per_voxel_and_rejects_rarely_seen_voxels():
    model = ObjectModel(voxel_size=0.01, extents=np.array([0.2, 0.2, 0.2]), margin=0.0)
    surface = np.array([[0.005, 0.005, 0.005], [0.015, 0.005, 0.005]])
    hand = np.array([[0.055, 0.055, 0.055]])
    for k in range(4):
        model.add(np.vstack([surface, hand * (1 + k)]) if k < 2 else surface)  # the "hand" moves, then leaves
    points, _ = model.points(min_hits=3)
    assert np.allclose(np.sort(points[:, 0]), [0.005, 0.015])
    assert len(model.points(min_hits=1)[0]) == 3  # 2 surface voxels + the hand once (at 0.11 m it is outside the 0.1 m half box)
    assert model.hits.max() == 4
    # a pose: points seen from the camera land back in the object frame
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 0.5]
    model2 = ObjectModel(0.01)
    model2.add_frame(surface + [0, 0, 0.5], None, pose)
    assert np.allclose(np.sort(model2.points()[0][:, 0]), [0.005, 0.015])


def test_frames_added_at_once_make_the_model_of_frames_added_one_by_one():
    """add_frames merges once: the same voxels, sums (to the last bit), counts and hits as one add_frame per frame;
    and the voxel means and hits agree with a direct count per voxel."""
    rng = np.random.default_rng(4)
    frames = []
    for k in range(6):
        pose = _known_transform(20.0 * k, 40.0, k)
        pose[2, 3] += 0.6
        points_obj = rng.uniform(-0.049, 0.049, size=(300 + 50 * k, 3))  # inside the half box
        frames.append((transform(pose, points_obj), rng.uniform(0, 1, size=points_obj.shape), pose, 1 + k % 2))
    frames.append((np.zeros((0, 3)), None, np.eye(4), 1))  # a frame with no points still counts as a frame
    one_by_one = ObjectModel(0.01, np.array([0.1, 0.1, 0.1]), margin=0.0)
    for points, colors, pose, weight in frames:
        one_by_one.add_frame(points, colors, pose, weight)
    at_once = ObjectModel(0.01, np.array([0.1, 0.1, 0.1]), margin=0.0)
    at_once.add_frames(frames[:2])
    at_once.add_frames(frames[2:])
    for name in ("keys", "sum_xyz", "sum_rgb", "sum_view", "count", "hits"):
        assert np.array_equal(getattr(one_by_one, name), getattr(at_once, name)), name
    assert at_once.frames == one_by_one.frames == 7
    # direct count: each frame's points in the object frame, voxel by voxel
    obj = [transform(invert(pose), points) for points, _, pose, _ in frames[:-1]]
    voxels = [np.floor(p / 0.01).astype(int) for p in obj]
    every = np.concatenate(voxels)
    unique, inverse = np.unique(every, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    means = np.stack([np.bincount(inverse, weights=np.concatenate(obj)[:, k]) for k in range(3)], axis=1) / np.bincount(inverse)[:, None]
    hits = sum(np.isin(np.arange(len(unique)), np.unique(inverse[sum(map(len, voxels[:i])):sum(map(len, voxels[: i + 1]))])) * frames[i][3]
               for i in range(len(voxels)))
    points, _ = at_once.points()
    order = np.lexsort(np.floor(points / 0.01).astype(int).T[::-1])
    assert len(points) == len(unique)
    np.testing.assert_allclose(points[order], means, atol=1e-12)
    assert np.array_equal(at_once.hits[order], hits)


def test_closest_about_y_picks_the_consistent_turn():
    reference = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    turned = reference @ rotation_about_y(np.radians(77))
    assert np.allclose(closest_about_y(turned, reference), reference, atol=1e-9)
    tilted = Rotation.from_rotvec([0.02, 0, 0]).as_matrix() @ turned
    picked = closest_about_y(tilted, reference)
    assert np.allclose(picked[:, 1], tilted[:, 1])  # the axis is kept
    assert pose_difference(_as4(picked), _as4(reference))[0] < 1.5


def _as4(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def test_symmetry_axis_of_a_tilted_bottle_shape_and_snap_upright():
    profile = np.array([[0.0, -0.1], [0.035, -0.1], [0.035, 0.03], [0.015, 0.07], [0.015, 0.1], [0.0, 0.1]])
    mesh = trimesh.creation.revolve(profile, sections=64)  # about +z
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # +z to +y
    points, faces = trimesh.sample.sample_surface_even(mesh, 6000, seed=0)
    normals = mesh.face_normals[faces]
    tilt = Rotation.from_rotvec([np.radians(6), 0, np.radians(-4)])
    offset = np.array([0.004, 0.0, -0.003])
    axis, point, rms = estimate_symmetry_axis(tilt.apply(points) + offset, tilt.apply(normals))
    true_axis = tilt.apply([0.0, 1.0, 0.0])
    assert np.degrees(np.arccos(np.clip(axis @ true_axis, -1, 1))) < 0.3
    # the line found passes through the offset centre (distance from it to the line)
    d = (offset - point) - axis * (axis @ (offset - point))
    assert np.linalg.norm(d) < 0.0005 and rms < 0.001
    # estimated normals (no normals given) still find it within a degree
    axis2, _, _ = estimate_symmetry_axis(tilt.apply(points) + offset, normal_radius=0.01)
    assert np.degrees(np.arccos(np.clip(axis2 @ true_axis, -1, 1))) < 1.0
    # snap: a pose whose object frame is the tilted one becomes upright on the axis
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 0.6]
    snapped = snap_upright(pose, axis, point)
    assert np.allclose(snapped[:3, 1], axis, atol=1e-9)
    assert np.linalg.norm(snapped[:3, 3] - (pose[:3, 3] + point - axis * (axis @ point))) < 1e-9


def test_symmetry_axis_conditioning_tells_a_sphere_cap_from_a_cylinder():
    """A spherical cap's normal lines all meet at the sphere's centre: every axis through it fits, so the
    fit must say the direction is undetermined (conditioning far from 0); a cylinder's axis is sharp.
    Normals carry ~1 deg of noise, as estimated normals do (noise-free, the sphere's fit is 0 = 0)."""
    rng = np.random.default_rng(0)

    def noisy(normals):
        normals = normals + rng.normal(scale=0.02, size=normals.shape)
        return normals / np.linalg.norm(normals, axis=1, keepdims=True)

    # a shallow cap of a 10 cm sphere centred at the origin (a bowl's inside), normals radial
    directions = rng.normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    cap = directions[directions[:, 1] < -0.7]
    _, _, _, cap_conditioning = fit_symmetry_axis(0.1 * cap, noisy(cap))
    theta = rng.uniform(0, 2 * np.pi, 3000)
    radial = np.stack([np.cos(theta), np.zeros_like(theta), np.sin(theta)], axis=1)
    cylinder = 0.035 * radial + np.stack([np.zeros_like(theta), rng.uniform(-0.06, 0.06, 3000), np.zeros_like(theta)], axis=1)
    axis, _, _, cylinder_conditioning = fit_symmetry_axis(cylinder, noisy(radial))
    assert cap_conditioning > 0.4
    assert cylinder_conditioning < 0.1 and abs(axis[1]) > 0.999


def test_axis_point_of_a_sphere_cap_with_its_direction_known():
    """A shallow cap (a bowl's inside) leaves the axis direction free, but with the direction known the axis passes
    through the sphere's centre: fit_axis_point finds it (independent truth: the centre the cap was made about),
    also with a fifth of the points a hand's (a flat palm beside the cap) and ~1 deg of normal noise."""
    from annotate.symmetry_axis import fit_axis_point

    rng = np.random.default_rng(1)
    directions = rng.normal(size=(6000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    cap = directions[directions[:, 1] < -0.7]
    centre = np.array([0.004, 0.02, -0.003])  # m: 5 mm off the box's y axis
    normals = cap + rng.normal(scale=0.02, size=cap.shape)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    palm = np.stack([rng.uniform(0.06, 0.12, 300), rng.uniform(-0.08, -0.02, 300), rng.uniform(-0.04, 0.04, 300)], axis=1)
    points = np.concatenate([centre + 0.08 * cap, palm])
    normals = np.concatenate([normals, np.tile([1.0, 0.0, 0.0], (300, 1))])
    point, rms = fit_axis_point(points, normals, [0.0, 1.0, 0.0])
    assert np.allclose(point, [centre[0], 0.0, centre[2]], atol=3e-4)  # the axis point nearest the origin: y = 0
    # a tilted direction: the point nearest the origin of the line through the centre along it
    tilted = np.array([0.1, 1.0, 0.05]) / np.linalg.norm([0.1, 1.0, 0.05])
    point, _ = fit_axis_point(centre + 0.08 * cap, cap, tilted)
    assert np.allclose(point, centre - tilted * (tilted @ centre), atol=1e-9)
    assert rms >= 0
    with pytest.raises(ValueError):
        fit_axis_point(np.zeros((5, 3)), np.ones((5, 3)), [0.0, 1.0, 0.0])


def test_symmetry_axis_rejects_too_few_points():
    with pytest.raises(ValueError):
        estimate_symmetry_axis(np.zeros((5, 3)))
    with pytest.raises(ValueError):
        estimate_symmetry_axis(np.full((100, 3), np.nan))


def test_smooth_with_neighbours_catches_a_pose_that_jumped():
    """The recheck of chain flags keeps a flag when the refined pose leaves its neighbours' midpoint."""
    from annotate.tracking.config import TrackingConfig
    from annotate.tracking.refine import _smooth_with_neighbours
    from annotate.tracking.tracker import FrameResult

    config = TrackingConfig()
    # a steady turn of 4 deg and 5 mm per frame about a tilted axis: every inner frame is its neighbours' midpoint
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    poses = []
    for k in range(5):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(axis * np.radians(4.0 * k)).as_matrix()
        T[:3, 3] = [0.005 * k, 0.0, 0.6]
        poses.append(T)
    ids = [str(k) for k in range(5)]
    results = {f: FrameResult(T, True, {}) for f, T in zip(ids, poses)}
    for symmetric in (False, True):
        assert all(_smooth_with_neighbours(results, ids, f, symmetric, config) for f in ids[1:-1])
        assert not _smooth_with_neighbours(results, ids, ids[0], symmetric, config)  # an end frame is not judged
        assert not _smooth_with_neighbours(results, ids, ids[-1], symmetric, config)
    slid = dict(results)
    moved = poses[2].copy()
    moved[:3, 3] += [0.0, 0.02, 0.0]  # 20 mm off, rotation kept
    slid["2"] = FrameResult(moved, True, {})
    assert not _smooth_with_neighbours(slid, ids, "2", False, config)
    tipped = poses[2].copy()
    tipped[:3, :3] = Rotation.from_rotvec([np.radians(8.0), 0, 0]).as_matrix() @ tipped[:3, :3]
    slid["2"] = FrameResult(tipped, True, {})
    assert not _smooth_with_neighbours(slid, ids, "2", True, config)  # a tilt of the axis counts for symmetric objects
    # a turn about the object's own y (unobservable for symmetry y) does not
    turned = poses[2].copy()
    turned[:3, :3] = turned[:3, :3] @ rotation_about_y(np.radians(40.0))
    slid["2"] = FrameResult(turned, True, {})
    assert _smooth_with_neighbours(slid, ids, "2", True, config)
    assert not _smooth_with_neighbours(slid, ids, "2", False, config)


def _plate(axis: int, at: float, ranges: list[tuple[float, float]], step: float = 0.003) -> np.ndarray:
    """Grid points (N, 3) m on the plane coordinate[axis] = at, the other two coordinates over ``ranges``."""
    a, b = (np.arange(lo, hi + 1e-9, step) for lo, hi in ranges)
    u, v = (g.ravel() for g in np.meshgrid(a, b))
    columns = [u, v]
    columns.insert(axis, np.full(len(u), at))
    return np.stack(columns, axis=1)


def test_facing_pairs_keep_a_slab_seen_from_below_off_its_model_top():
    # a 6 mm slab (a laptop's base) with two walls; the model saw only the slab's top, the frame sees only its
    # bottom: plain point-to-plane pairs the bottom with the top and slides by the thickness
    half = 0.003
    top = _plate(1, half, [(-0.1, 0.1), (-0.06, 0.06)])
    bottom = _plate(1, -half, [(-0.1, 0.1), (-0.06, 0.06)])
    back = _plate(2, -0.06, [(-0.1, 0.1), (half, 0.08)])  # faces +z
    side = _plate(0, -0.1, [(half, 0.08), (-0.06, 0.06)])  # faces +x
    model = np.concatenate([top, back, side])
    views = np.concatenate([np.tile([0.0, 1.0, 0.0], (len(top), 1)), np.tile([0.0, 0.0, 1.0], (len(back), 1)), np.tile([1.0, 0.0, 0.0], (len(side), 1))])
    target = ModelTarget(model, None, voxel_size=0.003, views=views)
    assert target.oriented
    normals = np.asarray(target.cloud.normals)
    assert np.all(np.einsum("ij,ij->i", normals, views) > 0)  # each turned to the side its cameras saw (edges: in between)
    camera = np.array([0.3, -0.4, 0.3])  # object frame: below the slab, in front of both walls
    frame = np.concatenate([bottom, back, side]) - camera  # camera frame (no rotation), noise-free
    init = np.eye(4)
    init[:3, 3] = camera  # camera -> object: the true pose
    plain = register(frame, target, init, params=RegistrationParams(facing=False))
    facing = register(frame, target, init)  # the default
    assert plain.ok and facing.ok
    slide_plain = (plain.transform[:3, 3] - camera)[1]
    slide_facing = (facing.transform[:3, 3] - camera)[1]
    assert slide_plain == pytest.approx(2 * half, abs=0.001)  # the bottom face pulled onto the model's top
    assert abs(slide_facing) < 1e-4  # no pair across the slab: the walls keep the true pose
    assert pose_difference(facing.transform, init)[0] < 0.05
    # the figures: on the facing pairs by default, on all pairs within the quality distance with facing_figures off
    # (Open3D's evaluate_registration, a second implementation); the pose is the same either way
    every = register(frame, target, init, params=RegistrationParams(facing_figures=False))
    assert np.allclose(every.transform, facing.transform, atol=1e-12)
    import open3d as o3d
    expected = o3d.pipelines.registration.evaluate_registration(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(frame)), target.cloud, RegistrationParams().quality_distance, every.transform)
    assert every.fitness == pytest.approx(expected.fitness, abs=1e-12) and every.inlier_rmse == pytest.approx(expected.inlier_rmse, abs=1e-12)
    assert every.fitness >= facing.fitness


def test_model_targets_face_the_cameras_that_saw_them():
    plane = _plate(2, 0.0, [(-0.05, 0.05), (-0.05, 0.05)], step=0.002)  # object frame z = 0
    for side in (-1.0, 1.0):  # the camera on the -z side of the plane, then (turned half a turn about x) on the +z side
        pose = np.eye(4)
        pose[:3, :3] = np.diag([1.0, -side, -side])  # object -> camera
        pose[:3, 3] = [0.0, 0.0, 0.5]
        model = ObjectModel(0.004)
        model.add_frame(transform(pose, plane), None, pose)
        target = model.target()
        camera_obj = invert(pose)[:3, 3]
        assert camera_obj[2] * side > 0
        towards = camera_obj - target.points
        assert target.oriented and np.all(np.einsum("ij,ij->i", np.asarray(target.cloud.normals), towards) > 0)


def test_open3d_threads_holds_one_thread_until_the_last_overlapping_body_ends():
    """A refinement in the browser may start and end while a track runs on another thread: the track keeps one thread."""
    import threading

    import open3d as o3d

    from annotate.tracking.registration import open3d_threads

    before = o3d.utility.get_max_threads()
    entered, leave = threading.Event(), threading.Event()

    def refinement() -> None:
        with open3d_threads(1):
            entered.set()
            leave.wait(10)

    worker = threading.Thread(target=refinement)
    worker.start()
    assert entered.wait(10)
    with open3d_threads(1):  # the track starts while the refinement runs ...
        leave.set()
        worker.join(10)  # ... and the refinement ends first
        assert o3d.utility.get_max_threads() == 1
        with open3d_threads(0):  # 0 leaves the setting as it is
            assert o3d.utility.get_max_threads() == 1
    assert o3d.utility.get_max_threads() == before
