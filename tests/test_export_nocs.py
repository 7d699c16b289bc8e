"""NOCS export (reconstruct-sequence --format nocs): REAL275's layout and NOCS's conventions against analytic truth
(a cube of known size at a known pose), the real REAL275 sample (its poses, masks and NOCS maps) exported again and
read back, and evaluation through our NOCS reader giving the numbers of the truth it came from.

NOCS's conventions are restated here from hughw19/NOCS_CVPR2019 (dataset.py's process_data, utils.py's
get_3d_bbox / transform_coordinates_3d / extract_bboxes / draw_coord_mask, detect_eval.py's pickles)."""

from __future__ import annotations

import io
import json
import pickle
import shutil

import numpy as np
import pytest
import trimesh
from PIL import Image

from evaluate.datasets import open_dataset
from evaluate.datasets.nocs import NOCS_CAMERA, SHAPENET_FROM_NOCS, decompose_scaled_rotation, load_gts
from evaluate.geometry import box_corners
from reconstruct.cli import main
from reconstruct.export import export_redwood
from reconstruct.export_nocs import HANDLE_MIN_PIXELS, export_nocs, nocs_pose, reproject
from reconstruct.masks import MeshRenderer
from reconstruct.pipeline import Reconstruction
from sequences.annotation import load_annotation
from sequences.camera import Camera
from sequences.errors import InputError
from sequences.reader import FrameFiles, Sequence, open_sequence
from test_export_bop import disturbed_predictions, killed_exports_leave_a_whole_export, truth_reconstruction
from test_reconstruct_scenes import write_scene
from test_tracking_render import mug_mesh

#: The keys of detect_eval.py's results pickles (ground-truth part), and the key it reads from gts pickles.
NOCS_GT_KEYS = {"image_id", "image_path", "gt_class_ids", "gt_bboxes", "gt_RTs", "gt_scales", "gt_handle_visibility", "handle_visibility"}


def nocs_box_corners(scales: np.ndarray) -> np.ndarray:
    """(3, 8) corners of NOCS's box of side lengths ``scales`` centred on the origin (get_3d_bbox's box)."""
    signs = np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)], dtype=np.float64)
    return (signs * np.asarray(scales) / 2).T


def decode_coord(path) -> np.ndarray:
    """A NOCS map decoded as process_data does: channels in R, G, B order, / 255, z = 1 - z."""
    coord = np.asarray(Image.open(path).convert("RGB")).astype(np.float32) / 255.0
    coord[..., 2] = 1.0 - coord[..., 2]
    return coord


def test_pose_scale_and_box_follow_nocs():
    """A 4 x 6 x 12 cm box turned 30 degrees about y, 0.5 m away: sRT's columns have the norm |extents| = 14 cm,
    and NOCS's box of gt_scales mapped by sRT is our box in the camera."""
    extents = np.array([0.04, 0.06, 0.12])
    pose = np.eye(4)
    pose[:3, :3] = trimesh.transformations.rotation_matrix(np.radians(30), [0, 1, 0])[:3, :3]
    pose[:3, 3] = [0.02, -0.01, 0.5]
    sRT = nocs_pose(pose, extents)
    np.testing.assert_allclose(np.linalg.norm(sRT[:3, :3], axis=0), np.linalg.norm(extents))
    assert np.linalg.norm(extents) == pytest.approx(0.14)
    R, scale, t = decompose_scaled_rotation(None, sRT)  # our reader's inverse
    np.testing.assert_allclose(R @ SHAPENET_FROM_NOCS.T, pose[:3, :3], atol=1e-12)
    nocs_sides = np.abs(SHAPENET_FROM_NOCS.T @ extents)  # NOCS x = -ShapeNet z, y = y, z = ShapeNet x
    np.testing.assert_allclose(nocs_sides, [0.12, 0.06, 0.04])
    corners = sRT[:3, :3] @ nocs_box_corners(nocs_sides / np.linalg.norm(nocs_sides)) + sRT[:3, 3:]
    ours = box_corners(extents, pose)
    assert max(np.linalg.norm(ours - c, axis=1).min() for c in corners.T) < 1e-12  # the same eight points


@pytest.fixture(scope="module")
def cube_export(tmp_path_factory):
    """A 10 cm cube ('can', symmetry y) 0.5 m away in REAL275's own camera, 3 frames, exported as NOCS."""
    base = tmp_path_factory.mktemp("nocs_cube")
    cube = trimesh.creation.box([0.1, 0.1, 0.1])
    scene = write_scene(base / "can_0001", cube, n_frames=3, camera=NOCS_CAMERA, category="can", symmetry="y")
    sequence = open_sequence(scene.root)
    rec = truth_reconstruction(scene, "can_0001", "can", "y")
    out = base / "nocs"
    export_nocs(rec, sequence, out)
    return scene, sequence, rec, out


def test_layout_and_pickle_fields(cube_export):
    scene, sequence, rec, out = cube_export
    folder = out / "real_test" / "scene_1"
    for frame_id, pose in rec.poses.items():
        stem = f"{sequence.index(frame_id):04d}"
        assert (folder / f"{stem}_meta.txt").read_text() == "1 4 can_0001\n"  # can = 4; the line ends with a newline
        mask = np.asarray(Image.open(folder / f"{stem}_mask.png"))
        assert mask.dtype == np.uint8 and set(np.unique(mask)) == {1, 255}
        depth = Image.open(folder / f"{stem}_depth.png")
        assert depth.mode in ("I;16", "I;16B", "I;16L") and (folder / f"{stem}_depth.png").read_bytes() == sequence.frames[sequence.index(frame_id)].depth_path.read_bytes()
        raw = (out / "gts" / "real_test" / f"results_real_test_scene_1_{stem}.pkl").read_bytes()
        assert b"numpy._core" not in raw  # readable by NumPy 1.x as NOCS's code ran on
        gts = pickle.loads(raw)
        assert set(gts) == NOCS_GT_KEYS
        assert gts["image_path"] == f"real_test/scene_1/{stem}" and gts["image_id"] == sequence.index(frame_id)
        for key, dtype, shape in (("gt_class_ids", np.int64, (1,)), ("gt_bboxes", np.int32, (1, 4)), ("gt_RTs", np.float64, (1, 4, 4)),
                                  ("gt_scales", np.float32, (1, 3)), ("gt_handle_visibility", np.int64, (1,)), ("handle_visibility", np.int64, (1,))):
            assert gts[key].dtype == dtype and gts[key].shape == shape, key
        assert gts["gt_class_ids"].tolist() == [4] and gts["gt_handle_visibility"].tolist() == [1]  # only a mug's handle can hide
        np.testing.assert_allclose(gts["gt_RTs"][0], nocs_pose(pose, rec.extents), atol=1e-15)
        np.testing.assert_allclose(gts["gt_scales"][0], np.full(3, 1 / np.sqrt(3)), rtol=1e-6)  # a cube's sides over its diagonal
        ys, xs = np.nonzero(mask == 1)  # extract_bboxes: y1, x1, y2, x2 with y2 and x2 exclusive
        assert gts["gt_bboxes"][0].tolist() == [ys.min(), xs.min(), ys.max() + 1, xs.max() + 1]
        load_gts(out / "gts" / "real_test" / f"results_real_test_scene_1_{stem}.pkl")  # our reader's NumPy-only unpickler takes it
    assert (out / "obj_models" / "real_test" / "can_0001.txt").read_text().split() == ["%.18e" % 0.1] * 3
    lines = (out / "obj_models" / "real_test" / "can_0001.obj").read_text().splitlines()
    vertices = np.array([line.split(" ")[1:] for line in lines if line.startswith("v ")], dtype=np.float64)  # load_mesh splits on single spaces
    faces = np.array([line.split(" ")[1:] for line in lines if line.startswith("f ")], dtype=np.int64) - 1
    np.testing.assert_allclose(vertices, rec.mesh.vertices @ SHAPENET_FROM_NOCS, atol=1e-9)
    assert (faces == rec.mesh.faces).all()


def test_coord_maps_decode_to_the_object_surface(cube_export):
    """Each NOCS map pixel, decoded as process_data does and mapped by gt_RT, lands on the cube's surface where the
    mesh is hit along that pixel's ray: within the 8-bit quantisation (half a level of the 17.3 cm diagonal)."""
    scene, sequence, rec, out = cube_export
    folder = out / "real_test" / "scene_1"
    for frame_id, pose in rec.poses.items():
        stem = f"{sequence.index(frame_id):04d}"
        coord = decode_coord(folder / f"{stem}_coord.png")
        mask = np.asarray(Image.open(folder / f"{stem}_mask.png")) == 1
        sRT = pickle.loads((out / "gts" / "real_test" / f"results_real_test_scene_1_{stem}.pkl").read_bytes())["gt_RTs"][0]
        camera_points = (sRT[:3, :3] @ (coord[mask] - 0.5).T.astype(np.float64) + sRT[:3, 3:]).T
        rendered = MeshRenderer(rec.mesh, NOCS_CAMERA).depth(pose)
        surface, _ = NOCS_CAMERA.backproject(rendered, mask)
        error = np.linalg.norm(camera_points - surface, axis=1)
        assert error.max() <= np.sqrt(3) * 0.5 / 255 * np.linalg.norm(rec.extents) + 1e-6
        # the points lie on the cube: one object coordinate at +-5 cm, the others within it
        local = np.abs((surface - pose[:3, 3]) @ pose[:3, :3])
        assert np.allclose(local.max(axis=1), 0.05, atol=1e-4)


def test_round_trip_through_our_nocs_reader(cube_export):
    scene, sequence, rec, out = cube_export
    data = open_dataset(out)
    index = json.loads((out / "annotations.json").read_text())["can_0001"]
    assert index["format"] == "nocs" and index["skipped"] == [] and index["reprojected_from"] is None
    assert len(data) == len(rec.poses)
    for sample in data:
        assert (sample.sequence, sample.instance, sample.category, sample.symmetry) == ("real_test/scene_1", "1", "can", "y")
        np.testing.assert_allclose(sample.pose, rec.poses[index["frames"][sample.frame]], atol=1e-12)
        np.testing.assert_allclose(sample.extents, rec.extents, atol=1e-12)
        assert np.array_equal(data.color(sample), sequence.color(index["frames"][sample.frame]))
    np.testing.assert_allclose(data.mesh(data.samples[0]).vertices, rec.mesh.vertices, atol=1e-9)


def test_the_real_sample_exported_again_reads_back_the_same(nocs_dir, tmp_path):
    """Each REAL275 instance with a mesh, exported as its own scene from the real frame: poses, boxes and classes come
    back exactly; our NOCS maps equal REAL275's own on the pixels both masks hold (median difference 0 levels; at
    most 2 levels on 89-97 % of them, measured); our masks lie inside REAL275's (98.9-100 %) and hold every pixel of
    it where the true mesh meets the measured depth within the mask's 1 cm (the can's true pose lies 1.4 cm behind
    its measured surface, so its mask is small)."""
    source = open_dataset(nocs_dir)
    scene_dir = nocs_dir / "real_test" / "scene_1"
    frame = Sequence.from_frames(scene_dir, [FrameFiles("0000", scene_dir / "0000_color.png", scene_dir / "0000_depth.png")], NOCS_CAMERA, "nocs")
    out = tmp_path / "nocs"
    originals = {}
    for sample in source:
        mesh = source.mesh(sample)
        if mesh is None:  # the sample lacks the laptop's mesh
            continue
        name = f"{sample.category}_{sample.instance}"
        originals[name] = sample
        export_nocs(Reconstruction(name, sample.category, sample.symmetry, mesh, sample.extents.copy(), {"0000": sample.pose}, {}, {}), frame, out)
    index = json.loads((out / "annotations.json").read_text())
    back = open_dataset(out)
    assert len(back) == len(originals) == 4
    real_mask = np.asarray(Image.open(scene_dir / "0000_mask.png"))
    real_coord = np.asarray(Image.open(scene_dir / "0000_coord.png")).astype(int)
    depth = frame.depth(0)
    gts = load_gts(nocs_dir / "gts" / "real_test" / "results_real_test_scene_1_0000.pkl")["gt_RTs"]
    for sample in back:
        name = next(k for k, v in index.items() if f"real_test/{v['scene']}" == sample.sequence)
        original = originals[name]
        assert (sample.category, sample.symmetry, sample.frame) == (original.category, original.symmetry, "0000")
        np.testing.assert_allclose(sample.pose, original.pose, atol=1e-12)
        np.testing.assert_allclose(sample.extents, original.extents, atol=1e-12)
        ours_pickle = load_gts(out / "gts" / "real_test" / f"results_real_test_{index[name]['scene']}_0000.pkl")
        np.testing.assert_allclose(ours_pickle["gt_RTs"][0], gts[int(original.instance) - 1], atol=1e-9)  # REAL275's own sRT
        folder = out / sample.sequence
        assert (folder / "0000_color.png").read_bytes() == (scene_dir / "0000_color.png").read_bytes()
        ours = np.asarray(Image.open(folder / "0000_mask.png")) == 1
        real = real_mask == int(original.instance)
        both = ours & real
        level = np.abs(np.asarray(Image.open(folder / "0000_coord.png")).astype(int)[both] - real_coord[both]).max(axis=1)
        assert np.median(level) == 0 and (level <= 2).mean() >= 0.85, name
        assert both.sum() / ours.sum() >= 0.98, name
        rendered = MeshRenderer(source.mesh(original), NOCS_CAMERA).depth(original.pose)
        agreeing = real & (rendered > 0) & (depth > 0) & (np.abs(depth - rendered) <= 0.01)
        assert (ours & agreeing).sum() / agreeing.sum() >= 0.99, name


def test_evaluate_gives_the_truths_numbers_through_our_nocs_reader(tmp_path):
    """One set of disturbed predictions, keyed for each dataset, evaluated on the REDWOOD75 export and on the NOCS
    export of the same truth (a bowl seen by Redwood's camera, re-projected into REAL275's): the same results."""
    from evaluate.cli import main as evaluate_main

    scene = write_scene(tmp_path / "bowl_0002", trimesh.creation.cylinder(0.05, 0.06, sections=64).apply_transform(
        trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])), n_frames=6, camera=Camera(), category="bowl", symmetry="y")
    sequence = open_sequence(scene.root)
    rec = truth_reconstruction(scene, "bowl_0002", "bowl", "y")
    redwood, nocs = tmp_path / "redwood", tmp_path / "nocs"
    export_redwood(rec, sequence, load_annotation(scene.root / "annotation.yaml"), redwood)
    export_nocs(rec, sequence, nocs)
    index = json.loads((nocs / "annotations.json").read_text())["bowl_0002"]
    assert index["reprojected_from"] == Camera().to_dict() and index["skipped"] == []
    stem = {frame_id: stem for stem, frame_id in index["frames"].items()}
    files = {
        "redwood": disturbed_predictions(rec, tmp_path / "redwood.jsonl", lambda f: ("bowl_0002", f, None)),
        "nocs": disturbed_predictions(rec, tmp_path / "nocs.jsonl", lambda f: ("real_test/scene_1", stem[f], "1")),
    }
    results = {}
    for name, dataset in (("redwood", redwood), ("nocs", nocs)):
        assert evaluate_main(["--dataset", str(dataset), "--method", f"p={files[name]}", "--out", str(tmp_path / f"eval_{name}"), "--quiet"]) == 0
        results[name] = json.loads((tmp_path / f"eval_{name}" / "results.json").read_text())["methods"]["p"]
    assert results["redwood"]["samples"] == results["nocs"]["samples"] == 6
    assert results["redwood"]["precision"] == results["nocs"]["precision"]
    assert results["redwood"].get("nocs_map") == results["nocs"].get("nocs_map")
    assert any(0 < row["overall"] < 1 for row in results["nocs"]["precision"] if row["overall"] is not None)


def test_reprojection_keeps_each_rays_depth():
    """A plane 0.8 m away tilted about y, seen by Redwood's camera, re-projected into REAL275's: each target pixel's
    depth is the plane's along its own ray (nearest source pixel: within one source pixel's depth step)."""
    source = Camera()
    rays = source.pixel_rays()
    slope = 0.3  # z = 0.8 + 0.3 x on the plane
    z = 0.8 / (1 - slope * rays[..., 0])
    color = np.zeros(source.shape + (3,), np.uint8)
    color[..., 0] = np.round(0.39 * np.arange(source.width))  # a ramp: 0.39 levels per column
    colour, depth = reproject(color, z.astype(np.float32), source, NOCS_CAMERA)
    target_rays = NOCS_CAMERA.pixel_rays()
    expected = 0.8 / (1 - slope * target_rays[..., 0])
    step = 0.8 * slope / source.fx  # depth change per source pixel, about
    assert np.abs(depth - expected).max() <= step
    u_source = source.fx * target_rays[..., 0] + source.cx  # where each target ray meets the source image
    assert np.abs(colour[..., 0].astype(float) - 0.39 * u_source).max() <= 1.0  # bilinear on a ramp, rounded twice


def test_mug_handle_visibility(tmp_path):
    """A mug (handle along -z) facing the camera with its handle, then with the handle behind its body."""
    mug = mug_mesh()
    mug.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [0, 1, 0]))  # the test mug's handle is along +z
    root = tmp_path / "mug_0009"
    scene = write_scene(root, mug, n_frames=2, camera=NOCS_CAMERA, category="mug")
    towards, away = np.eye(4), np.eye(4)
    towards[2, 3] = away[2, 3] = 0.3
    away[:3, :3] = trimesh.transformations.rotation_matrix(np.pi, [0, 1, 0])[:3, :3]
    # the frames' depth shows the mug as posed here
    from test_reconstruct_scenes import render_depth

    for frame_id, pose in zip(sorted(scene.poses), (towards, away)):
        posed = mug.copy().apply_transform(pose)
        Image.fromarray(np.rint(render_depth([posed], NOCS_CAMERA) * 1000).astype(np.uint16)).save(root / "depth" / f"{frame_id}.png")
        scene.poses[frame_id] = pose
    out = tmp_path / "nocs"
    export_nocs(truth_reconstruction(scene, "mug_0009", "mug", "none"), open_sequence(root), out)
    seen = [int(load_gts(p)["gt_handle_visibility"][0]) for p in sorted((out / "gts" / "real_test").glob("*.pkl"))]
    assert seen == [1, 0]
    assert HANDLE_MIN_PIXELS == 10


def test_re_export_leaves_no_stale_frames(cube_export, tmp_path):
    scene, sequence, rec, out = cube_export
    target = tmp_path / "nocs"
    shutil.copytree(out, target)
    fewer = truth_reconstruction(scene, "can_0001", "can", "y")
    fewer.poses = dict(sorted(rec.poses.items())[:1])
    export_nocs(fewer, sequence, target)
    assert sorted(p.name for p in (target / "gts" / "real_test").iterdir()) == ["results_real_test_scene_1_0000.pkl"]
    assert len(list((target / "real_test" / "scene_1").glob("*_color.png"))) == 1
    export_nocs(truth_reconstruction(scene, "bottle_0001", "bottle", "y"), sequence, target)
    assert [(s.sequence, s.category) for s in open_dataset(target)] == [("real_test/scene_1", "can")] + [("real_test/scene_2", "bottle")] * 3


def test_bad_input_ends_in_one_line(cube_export, tmp_path, capsys):
    scene, sequence, rec, out = cube_export
    other = write_scene(tmp_path / "thing_0001", trimesh.creation.box([0.05, 0.05, 0.05]), n_frames=2, category="other")
    assert main([str(other.root), "--out", str(tmp_path / "o"), "--format", "nocs"]) == 2
    error = capsys.readouterr().err.splitlines()[0]
    assert error == f"error: {other.root / 'annotation.yaml'}: category 'other' has no NOCS class id (NOCS knows bottle, bowl, camera, can, laptop, mug)"
    assert not (tmp_path / "o" / "gts").exists()
    with pytest.raises(InputError, match="--no-masks does not apply"):
        main([str(scene.root), "--out", str(tmp_path / "o"), "--format", "nocs", "--no-masks"])
    target = tmp_path / "nocs"
    shutil.copytree(out, target)
    pkl = target / "gts" / "real_test" / "results_real_test_scene_1_0000.pkl"
    pkl.write_bytes(pickle.dumps({"gt_RTs": np.zeros((1, 4, 4)), "hook": shutil.rmtree}))
    with pytest.raises(InputError, match="refusing"):
        open_dataset(target)
    # an object no frame shows: nothing written, one line
    hidden = truth_reconstruction(scene, "can_0002", "can", "y")
    behind = np.eye(4)
    behind[2, 3] = -1.0  # a metre behind the camera
    hidden.poses = {k: behind for k in rec.poses}
    before = sorted(p.relative_to(target) for p in target.rglob("*"))
    with pytest.raises(InputError, match="shows no pixel"):
        export_nocs(hidden, sequence, target)
    assert sorted(p.relative_to(target) for p in target.rglob("*")) == before


def test_cli_writes_nocs(tmp_path):
    scene = write_scene(tmp_path / "mug_0003", trimesh.creation.box([0.06, 0.09, 0.08]), n_frames=10, category="mug")
    out = tmp_path / "out"
    assert main([str(scene.root), "--out", str(out), "--format", "nocs", "--voxel-size", "0.004"]) == 0
    data = open_dataset(out)
    assert len(data) == 10 and {s.category for s in data} == {"mug"}
    assert np.allclose(data.samples[0].extents, [0.06, 0.09, 0.08], atol=0.012)
    buffer = io.BytesIO((out / "gts" / "real_test" / "results_real_test_scene_1_0000.pkl").read_bytes())
    assert pickle.load(buffer)["gt_class_ids"].tolist() == [6]


@pytest.mark.slow
def test_a_killed_nocs_export_leaves_the_old_or_the_new_export_whole(tmp_path):
    assert killed_exports_leave_a_whole_export(tmp_path, "nocs", kills=4)
