"""The synthetic generator: determinism, Redwood pairing, truth consistent with an independent render, noise model,
orientation coverage, hand occlusion and regrasp, bad inputs, the sample sequence."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh
from PIL import Image

from sequences.annotation import Annotation
from sequences.camera import Camera
from sequences.errors import InputError
from sequences.reader import open_sequence
from sequences.synth import generate_sequence, load_truth, truth_annotation
from sequences.synth.options import CaptureOptions, SensorOptions

REPO = Path(__file__).resolve().parents[1]
FRAMES = 8
IDEAL = CaptureOptions(sensor=SensorOptions.ideal())


def sigma(z):
    """PrimeSense axial noise model (the issue's formula), written out independently of the generator."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


@pytest.fixture(scope="module")
def mug(tmp_path_factory) -> Path:
    """A mug seen by the ideal sensor (noise and holes only): the noise model's tests compare against it; the
    other sensor options are tested in test_synth_options.py."""
    return generate_sequence(tmp_path_factory.mktemp("synth") / "mug", "mug", frames=FRAMES, seed=3, capture=IDEAL)


def independent_depth(mesh: trimesh.Trimesh, pose: np.ndarray, camera: Camera) -> np.ndarray:
    """Depth z (H, W) of the mesh alone at the pose, inf where missed: our own minimal ray cast."""
    vertices = np.asarray(mesh.vertices) @ pose[:3, :3].T + pose[:3, 3]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    d = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u, dtype=float)], -1).reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(d), d], 1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return t.reshape(camera.height, camera.width)  # direction z = 1, so t is z


def test_reader_pairs_every_frame_with_its_truth(mug):
    seq = open_sequence(mug)
    truth = load_truth(mug)
    assert len(seq) == FRAMES and not seq.unpaired_color and not seq.unpaired_depth
    assert seq.ids == truth.ids
    for frame in seq.frames:
        colour_number = int(frame.color_path.stem.split("-")[0])
        depth_number = int(frame.depth_path.stem.split("-")[0])
        assert depth_number != colour_number  # numbered separately, as in Redwood
        assert frame.depth_time_us == frame.color_time_us  # the ideal sensor takes depth with colour (test_synth_options: offsets)
        assert frame.id == f"{colour_number:07d}"
    assert seq.color(0).shape == (480, 640, 3) and seq.depth_raw(0).dtype == np.uint16
    assert (mug / "truth" / "mesh.obj").is_file()
    assert sorted(p.stem for p in (mug / "truth" / "masks").glob("*.png")) == truth.ids


def test_truth_document_and_mesh(mug):
    truth = load_truth(mug)
    assert truth.category == "mug" and truth.symmetry == "none"
    np.testing.assert_allclose(truth.extents, truth.mesh.extents, atol=1e-6)
    np.testing.assert_allclose(truth.mesh.bounds.mean(axis=0), 0.0, atol=1e-6)
    # a mug 8-12 cm tall, its handle along -z: the box reaches further along z than the body's radius along x
    assert 0.08 <= truth.extents[1] <= 0.125
    assert truth.extents[2] > truth.extents[0] + 0.015
    vertices = np.asarray(truth.mesh.vertices)
    assert vertices[:, 2].max() - vertices[:, 2].min() == pytest.approx(truth.extents[2], abs=1e-6)
    for T in truth.poses.values():
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
        assert 0.45 <= T[2, 3] <= 0.9


def test_depth_matches_independent_render_of_the_true_mesh(mug):
    seq = open_sequence(mug)
    truth = load_truth(mug)
    camera = seq.camera
    medians, ious = [], []
    for frame_id in truth.ids:
        depth = seq.depth(frame_id).astype(np.float64)
        rendered = independent_depth(truth.mesh, truth.poses[frame_id], camera)
        mask = truth.mask(frame_id)
        valid = depth > 0
        on_object = mask & valid
        assert on_object.sum() > 500
        z = rendered[on_object]
        assert np.all(np.isfinite(z))  # the mask lies inside the object's silhouette
        ratio = np.abs(depth[on_object] - z) / (sigma(z) + 0.0005)
        medians.append(np.median(ratio))
        assert np.percentile(ratio, 95) < 4.0
        # visible object pixels: the object is hit and the measurement agrees with it (not occluded)
        visible = np.isfinite(rendered) & valid & (np.abs(depth - np.where(np.isfinite(rendered), rendered, 0)) < 4 * sigma(rendered) + 0.001)
        ious.append((visible & mask).sum() / (visible | (mask & valid)).sum())
    assert np.median(medians) < 1.0  # Gaussian: median |x| / sigma = 0.67
    assert min(ious) > 0.95, ious


def test_dropout_grows_at_grazing_angles(mug):
    seq = open_sequence(mug)
    truth = load_truth(mug)
    camera = seq.camera
    grazing, head_on = [], []
    for frame_id in truth.ids:
        T = truth.poses[frame_id]
        vertices = np.asarray(truth.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(np.asarray(truth.mesh.faces, dtype=np.uint32)))
        d = camera.pixel_rays().reshape(-1, 3)
        answer = scene.cast_rays(o3d.core.Tensor(np.concatenate([np.zeros_like(d), d], 1).astype(np.float32)))
        normals = answer["primitive_normals"].numpy()
        cos = np.abs(np.einsum("ij,ij->i", normals, d / np.linalg.norm(d, axis=1, keepdims=True))).reshape(camera.shape)
        mask = truth.mask(frame_id)
        missing = seq.depth_raw(frame_id) == 0
        grazing.append(missing[mask & (cos < 0.08)])
        head_on.append(missing[mask & (cos > 0.5)])
    grazing, head_on = np.concatenate(grazing), np.concatenate(head_on)
    assert grazing.size > 50 and grazing.mean() > 0.7  # nearly always lost beyond ~85 degrees
    assert head_on.mean() < 0.06  # only speckle, blobs and edges where the surface faces the camera


def test_wall_noise_matches_the_model(mug):
    seq = open_sequence(mug)
    truth = load_truth(mug)
    for frame_id in truth.ids[:3]:
        depth = seq.depth(frame_id).astype(np.float64)
        patch = depth[:60, :100]  # top-left corner: the wall
        v, u = np.mgrid[0:60, 0:100]
        valid = patch > 0
        # a plane is linear in 1/z over the image: fit it, then look at the residual in z
        A = np.column_stack([u[valid], v[valid], np.ones(valid.sum())])
        coef, *_ = np.linalg.lstsq(A, 1.0 / patch[valid], rcond=None)
        fitted = 1.0 / (A @ coef)
        residual = patch[valid] - fitted
        robust_std = 1.4826 * np.median(np.abs(residual - np.median(residual)))
        expected = np.sqrt(sigma(np.median(fitted)) ** 2 + 0.001**2 / 12)
        assert robust_std == pytest.approx(expected, rel=0.3)


def test_deterministic_per_seed(mug, tmp_path):
    again = generate_sequence(tmp_path / "again", "mug", frames=FRAMES, seed=3, capture=IDEAL)
    other = generate_sequence(tmp_path / "other", "mug", frames=FRAMES, seed=4, capture=IDEAL)
    first = sorted((mug / "depth").iterdir())
    assert [p.name for p in first] == [p.name for p in sorted((again / "depth").iterdir())]
    for a, b in zip(first, sorted((again / "depth").iterdir())):
        assert a.read_bytes() == b.read_bytes()
    assert json.loads((mug / "truth" / "truth.json").read_text()) == json.loads((again / "truth" / "truth.json").read_text())
    different = [np.asarray(Image.open(a)) for a in first[:2]], [np.asarray(Image.open(b)) for b in sorted((other / "depth").iterdir())[:2]]
    assert all(np.mean(x != y) > 0.1 for x, y in zip(*different))
    assert load_truth(other).extents.tolist() != load_truth(mug).extents.tolist()


def test_every_orientation_is_visited(tmp_path):
    truth = load_truth(generate_sequence(tmp_path / "bottle", "bottle", frames=10, seed=1))
    assert truth.symmetry == "y" and 0.2 <= truth.extents[1] <= 0.3
    up = np.array([T[:3, 1] for T in truth.poses.values()])  # object +y in the camera frame
    assert up[:, 1].min() < -0.8  # pointing up (camera -y)
    assert up[:, 1].max() > 0.8  # pointing down
    assert np.abs(up[:, 1]).min() < 0.45  # sideways
    steps = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", up[1:], up[:-1]), -1, 1)))
    assert steps.max() < 90  # smooth, not jumping


def test_hand_occludes_the_object_and_regrasps(mug):
    seq = open_sequence(mug)
    truth = load_truth(mug)
    hand = truth.notes["hand"]
    assert any(not h["holding"] for h in hand.values())  # released at least once
    assert len({h["grasp"] for h in hand.values()}) >= 2
    occluder_centres, fractions = {}, []
    for frame_id in truth.ids:
        T = truth.poses[frame_id]
        rendered = independent_depth(truth.mesh, T, seq.camera)
        depth = seq.depth(frame_id).astype(np.float64)
        silhouette = np.isfinite(rendered)
        occluded = silhouette & ~truth.mask(frame_id) & (depth > 0) & (depth < rendered - 0.01)
        if hand[frame_id]["holding"]:
            fractions.append(occluded.sum() / silhouette.sum())
            points, _ = seq.camera.backproject(depth, occluded)
            occluder_centres.setdefault(hand[frame_id]["grasp"], []).append((points - T[:3, 3]) @ T[:3, :3])
    # the hand covers part of the object in most held frames (from behind, in some views, it hides nothing)
    assert np.mean(np.array(fractions) > 0.01) >= 0.5, fractions
    assert max(fractions) < 0.9
    # what covers the object while it is held is mostly the hand touching it: near the object's surface
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(truth.mesh.vertices, np.float32)), o3d.core.Tensor(np.asarray(truth.mesh.faces, np.uint32)))
    occluders = np.concatenate([np.concatenate(v) for v in occluder_centres.values()])
    assert np.median(scene.compute_distance(o3d.core.Tensor(occluders.astype(np.float32))).numpy()) < 0.03
    centres = {k: np.concatenate(v).mean(axis=0) for k, v in occluder_centres.items()}
    assert len(centres) >= 2
    a, b = list(centres.values())[:2]
    assert np.linalg.norm(a - b) > 0.02  # in the object's frame the hand sits elsewhere after the regrasp


def test_truth_annotation_perturbs_within_bounds(mug):
    truth = load_truth(mug)
    ids = truth.ids[::3]
    ann = truth_annotation(truth, ids, rotation_deg=5, translation_m=0.01, extents_rel=0.1, seed=2)
    assert isinstance(ann, Annotation) and sorted(ann.frames) == ids
    assert ann.category == "mug" and ann.symmetry == "none"
    assert np.all(np.abs(ann.extents / truth.extents - 1) <= 0.1 + 1e-9)
    for frame_id in ids:
        T, P = truth.poses[frame_id], ann.frames[frame_id].matrix
        angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ P[:3, :3]) - 1) / 2, -1, 1)))
        assert angle <= 5 + 1e-6 and np.linalg.norm(T[:3, 3] - P[:3, 3]) <= 0.01 + 1e-9
        assert ann.frames[frame_id].source == "manual"
    with pytest.raises(InputError, match="no true pose"):
        truth_annotation(truth, ["9999999"])
    with pytest.raises(InputError, match="no truth file"):
        load_truth(mug.parent)
    exact = truth_annotation(truth, ids)
    for frame_id in ids:
        np.testing.assert_allclose(exact.frames[frame_id].matrix, truth.poses[frame_id], atol=1e-9)


def run_synth(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sequences.synth", *args, "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("case", ["category", "existing", "mesh", "frames"])
def test_bad_input_exits_2_with_one_line(case, tmp_path):
    out = tmp_path / "out"
    if case == "category":
        result = run_synth(str(out), "--category", "teapot", "--frames", "2")
        problem = "teapot"
    elif case == "existing":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
        result = run_synth(str(out), "--category", "mug", "--frames", "2")
        problem = "not an empty folder"
        assert (out / "keep.txt").read_text() == "mine" and sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    elif case == "mesh":
        bad = tmp_path / "broken.obj"
        bad.write_bytes(b"\x00\xff garbage")
        result = run_synth(str(out), "--category", "mug", "--frames", "2", "--mesh", str(bad))
        problem = "broken.obj"
    else:
        result = run_synth(str(out), "--category", "mug", "--frames", "0")
        problem = "frames"
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and problem in lines[0], result.stderr
    assert not out.exists() or case == "existing"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.tmp")]  # no temporary left behind


def test_given_redwood75_mesh_in_raw_axes(redwood75_dir, tmp_path):
    source = redwood75_dir / "meshes" / "00015.obj"  # a mug, REDWOOD75 raw axes (raw x = ShapeNet z)
    out = generate_sequence(tmp_path / "r75", "mug", frames=3, seed=0, mesh=source, mesh_axes="redwood75")
    truth = load_truth(out)
    raw = trimesh.load(source, force="mesh", process=False)
    raw_extents = np.ptp(np.asarray(raw.vertices), axis=0)
    np.testing.assert_allclose(truth.extents, raw_extents[[2, 1, 0]], atol=1e-6)  # ShapeNet x, y, z = raw z, y, x
    expected = np.asarray(raw.vertices) @ np.array([[0, 0, 1], [0, -1, 0], [1, 0, 0]], float).T  # shapenet = M^T raw, M symmetric
    expected -= (expected.min(axis=0) + expected.max(axis=0)) / 2
    np.testing.assert_allclose(np.sort(np.asarray(truth.mesh.vertices), axis=0), np.sort(expected, axis=0), atol=1e-6)
    assert truth.symmetry == "none" and len(open_sequence(out)) == 3
    assert truth.mask(truth.ids[0]).sum() > 300


@pytest.mark.parametrize("category", ["bottle", "bowl", "can", "mug", "camera", "laptop"])
def test_procedural_shapes_have_realistic_sizes_and_symmetry(category):
    from sequences.synth.shapes import procedural_mesh

    ranges = {  # box side lengths x, y, z in metres (ShapeNet axes, y up)
        "bottle": ((0.05, 0.1), (0.2, 0.3), (0.05, 0.1)), "bowl": ((0.12, 0.18), (0.03, 0.1), (0.12, 0.18)),
        "can": ((0.06, 0.08), (0.1, 0.13), (0.06, 0.08)), "mug": ((0.07, 0.1), (0.08, 0.12), (0.09, 0.15)),
        "camera": ((0.09, 0.15), (0.06, 0.1), (0.05, 0.12)), "laptop": ((0.27, 0.37), (0.15, 0.3), (0.15, 0.4)),
    }[category]
    sizes = []
    for seed in range(4):
        mesh = procedural_mesh(category, np.random.default_rng(seed))
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
        for side, (low, high) in zip(mesh.extents, ranges):
            assert low <= side <= high, (category, mesh.extents)
        sizes.append(mesh.extents)
        if category in ("bottle", "bowl", "can"):
            # rotationally symmetric about y: the mesh turned by any angle about y lies on itself
            angle = 0.7 + seed
            turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)), o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
            turned = (np.asarray(mesh.vertices) @ turn.T).astype(np.float32)
            assert scene.compute_distance(o3d.core.Tensor(turned)).numpy().max() < 0.001
    assert np.ptp(np.array(sizes), axis=0).max() > 0.005  # the seed varies the shape


def test_motion_is_smooth_and_hand_held():
    from sequences.synth.motion import grasp_schedule, held_frames, object_trajectory

    held = held_frames(100, grasp_schedule(100))
    assert 0.6 < held.mean() < 0.95  # regrasps take a few frames
    trajectory = object_trajectory(100, np.random.default_rng(0), held)
    R = trajectory.rotations
    steps = np.degrees(np.arccos(np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1) / 2, -1, 1)))
    assert 2.0 < np.median(steps) < 8.0 and steps.max() < 15.0  # a few degrees per frame
    assert np.median(steps[~held[1:]]) < 0.5 * np.median(steps[held[1:] & held[:-1]])  # slower while not held
    assert np.linalg.norm(np.diff(trajectory.positions, axis=0), axis=1).max() < 0.015
    assert np.all((trajectory.positions[:, 2] > 0.45) & (trajectory.positions[:, 2] < 0.9))
    up = R[:, :, 1]
    assert up[:, 1].min() < -0.8 and up[:, 1].max() > 0.8 and np.abs(up[:, 1]).min() < 0.3


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_every_face_is_turned_toward_the_camera(seed):
    """Shown from every side: each of the object's six face directions (+-x, +-y, +-z) comes within 55 deg of facing
    the camera, its top (+y) and bottom within 25 deg (v4, seed 0: +x no closer than 97 deg, -z 84 deg, +y 71 deg)."""
    from sequences.synth.motion import grasp_schedule, held_frames, object_trajectory

    R = object_trajectory(100, np.random.default_rng([seed, 2]), held_frames(100, grasp_schedule(100))).rotations
    toward = np.concatenate([-R[:, 2, :], R[:, 2, :]], axis=1)  # cosines of +x, +y, +z, -x, -y, -z to camera -z
    closest = np.degrees(np.arccos(np.clip(toward.max(axis=0), -1, 1)))
    assert closest.max() < 55, closest
    assert closest[1] < 25 and closest[4] < 25, closest


def test_sample_sequence_is_generated_once_atomically(tmp_path, monkeypatch):
    import threading

    from sequences import sample

    monkeypatch.setenv("REDWOOD_GT_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(sample, "SAMPLE_FRAMES", 3)
    results, errors = [], []

    def make():
        try:
            results.append(sample.sample_sequence())
        except Exception as error:  # collected: a thread's exception would otherwise vanish
            errors.append(error)

    threads = [threading.Thread(target=make) for _ in range(2)]  # two racing creators
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(set(results)) == 1
    root = results[0]
    assert root == tmp_path / "cache" / sample.SAMPLE_NAME
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [sample.SAMPLE_NAME]  # no temporary left
    assert not (root / "annotation.yaml").exists()
    truth = load_truth(root)
    assert truth.category == "mug" and open_sequence(root).ids == truth.ids and len(truth.ids) == 3
    stamp = (root / "truth" / "truth.json").stat().st_mtime_ns
    assert sample.sample_sequence() == root and (root / "truth" / "truth.json").stat().st_mtime_ns == stamp  # reused


def test_window_render_equals_full_render():
    """Frames re-cast only the moving parts' window over a still render: the result must equal a full render."""
    from sequences.synth.primitives import capsules, quad
    from sequences.synth.render import projected_window, render

    camera = Camera()
    projector = np.array([0.075, 0.0, 0.0])
    still_parts = [quad([0.0, 0.0, 2.0], [3.0, 0.0, 0.0], [0.0, 3.0, 0.0], 4), quad([0.0, 0.3, 1.4], [0.0, 0.0, 0.6], [1.5, 0.0, 0.0], 5)]
    still = render(still_parts, camera, projector=projector)
    moving = [capsules(np.array([[-0.05, -0.05, 0.6]]), np.array([[0.08, 0.1, 0.7]]), np.array([0.03]), 1)]
    window = projected_window(moving, camera, projector=projector)
    assert (window[1] - window[0]) * (window[3] - window[2]) < 0.5 * camera.width * camera.height
    fast = render(moving + still_parts, camera, still, window, projector)
    full = render(moving + still_parts, camera, projector=projector)
    assert full.shadow.sum() > 500  # the capsule shadows the wall
    for name in ("depth", "label", "shadow"):
        assert np.array_equal(getattr(fast, name), getattr(full, name)), name
    np.testing.assert_allclose(fast.normals, full.normals, atol=1e-6)


def test_other_camera_is_written_to_camera_yaml(tmp_path):
    camera = Camera(fx=400.0, fy=410.0, cx=199.5, cy=151.0, width=400, height=300)
    out = generate_sequence(tmp_path / "small", "can", frames=2, seed=5, camera=camera, capture=IDEAL)
    seq = open_sequence(out)
    assert seq.camera == camera and seq.depth(0).shape == (300, 400)
    truth = load_truth(out)
    frame_id = truth.ids[0]
    rendered = independent_depth(truth.mesh, truth.poses[frame_id], camera)
    depth = seq.depth(frame_id).astype(np.float64)
    on_object = truth.mask(frame_id) & (depth > 0)
    assert on_object.sum() > 300
    assert np.median(np.abs(depth[on_object] - rendered[on_object]) / sigma(rendered[on_object])) < 1.5


def _seen_in_other_grasps(root: Path, radius: float = 0.025) -> list[float]:
    """Per grasp: the share of the surface under its palm (within ``radius`` of its contact, facing its way) that
    some frame held by another grasp shows unobstructed: facing the camera (within 75 deg), in the object mask (no
    hand in front), at the depth of our own ray cast of the true mesh (not behind another part of the object)."""
    truth, camera = load_truth(root), open_sequence(root).camera
    points, face = trimesh.sample.sample_surface(truth.mesh, 20000, seed=0)
    normals = np.asarray(truth.mesh.face_normals)[face]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(truth.mesh.vertices, np.float32)), o3d.core.Tensor(np.asarray(truth.mesh.faces, np.uint32)))
    hand = truth.notes["hand"]
    depth = {f: independent_depth(truth.mesh, truth.poses[f], camera) for f in truth.ids if hand[f]["holding"]}
    shares = []
    for k, grasp in enumerate(truth.notes["grasps"]):
        contact = np.array(grasp["contact"], np.float32)[None]
        outward = scene.compute_closest_points(o3d.core.Tensor(contact))["primitive_normals"].numpy()[0]
        patch = (np.linalg.norm(points - contact, axis=1) < radius) & (normals @ outward > 0.5)
        seen = np.zeros(patch.sum(), bool)
        for frame_id, rendered in depth.items():
            if hand[frame_id]["grasp"] == k:
                continue
            T = truth.poses[frame_id]
            p = points[patch] @ T[:3, :3].T + T[:3, 3]
            u = np.round(camera.fx * p[:, 0] / p[:, 2] + camera.cx).astype(int)
            v = np.round(camera.fy * p[:, 1] / p[:, 2] + camera.cy).astype(int)
            inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
            u, v = np.where(inside, u, 0), np.where(inside, v, 0)
            facing = -np.einsum("ij,ij->i", normals[patch] @ T[:3, :3].T, p / np.linalg.norm(p, axis=1, keepdims=True)) > np.cos(np.radians(75))
            seen |= inside & facing & truth.mask(frame_id)[v, u] & (np.abs(rendered[v, u] - p[:, 2]) < 0.004)
        shares.append(float(seen.mean()))
    return shares


@pytest.mark.parametrize("seed", [0, 1])
def test_capture_shows_the_opening_the_bottom_and_what_each_grasp_covered(seed, tmp_path):
    """Reconstruction-grade capture: the mug is seen into its opening and at its bottom, and the surface under each
    grasp's palm is shown unobstructed while another grasp holds it (v4: seed 0's opening never came within 71 deg)."""
    small = Camera(fx=262.5, fy=262.5, cx=159.5, cy=119.5, width=320, height=240)  # a quarter of the pixels: fast
    root = generate_sequence(tmp_path / "mug", "mug", frames=40, seed=seed, camera=small)
    truth = load_truth(root)
    up = np.array([truth.poses[f][:3, 1] for f in truth.ids])  # object +y (the opening) in the camera frame
    assert np.degrees(np.arccos(np.clip(-up[:, 2], -1, 1))).min() < 25  # toward the camera: into the mug
    assert np.degrees(np.arccos(np.clip(up[:, 2], -1, 1))).min() < 25  # away from it: the bottom
    shares = _seen_in_other_grasps(root)
    assert len(shares) >= 2 and min(shares) > 0.95, shares
