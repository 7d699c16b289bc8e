"""BOP export (reconstruct-sequence --format bop): field for field as bop_toolkit's format document defines it, against
analytic truth (a cube of known size at a known pose), an independent re-computation of scene_gt_info from the
written files, and round trips through our BOP reader and through ``evaluate``.

The expectations are written from the format document (docs/bop_datasets_format.md) and from what bop_toolkit's
scripts compute (calc_gt_info.py, calc_gt_masks.py, calc_model_info.py), restated here in our own code."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh
from PIL import Image

from evaluate.datasets import open_dataset
from evaluate.geometry import matrix_to_quat, quat_to_matrix
from reconstruct.cli import main
from reconstruct.export import export_redwood
from reconstruct.export_bop import DELTA_MM, SilhouetteRenderer, bop_json, diameter, export_bop, gt_info
from reconstruct.pipeline import Reconstruction
from sequences.annotation import load_annotation
from sequences.bop import SHAPENET_FROM_BOP, load_bop_truth, read_models_info, read_scene_gt, read_scene_gt_info
from sequences.camera import Camera
from sequences.errors import InputError
from sequences.reader import open_sequence
from test_reconstruct_scenes import cup_mesh, write_scene

#: The fields the format document lists, per file.
DOC_SCENE_CAMERA = {"cam_K", "depth_scale"}
DOC_SCENE_GT = {"obj_id", "cam_R_m2c", "cam_t_m2c"}
DOC_SCENE_GT_INFO = {"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract"}
DOC_MODEL_INFO = {"diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"}
REDWOOD = Camera()  # 640x480, fx = fy = 525, cx = 319.5, cy = 239.5


def cube(camera: Camera, side: float = 0.1, distance: float = 1.0) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int]]:
    """(depth (mm) in the image, whole silhouette or None, offset) of a cube on the optical axis, axis-aligned, as the
    export renders it (the 3x canvas only where the silhouette leaves the image)."""
    pose = np.eye(4)
    pose[2, 3] = distance
    return SilhouetteRenderer(trimesh.creation.box([side] * 3), camera)(pose)


def test_cube_gt_info_against_analytic_truth():
    """A 10 cm cube 1 m away, facing the camera: its silhouette is the front face (0.95 m), |u - cx| <= 0.05 / 0.95
    * 525 = 27.6 px: 56 x 56 pixels from (292, 212); BOP's box is [x, y, max - min, max - min] = [292, 212, 55, 55]."""
    measured = np.zeros(REDWOOD.shape)
    measured[:, :310] = 940.0  # 10 mm in front of the face: within 15 mm, visible
    measured[:, 310:330] = 930.0  # 20 mm in front: occluded
    # from column 330 on no measurement: visible (bop19 rule)
    depth, whole, offset = cube(REDWOOD)
    assert whole is None  # inside the image: the image alone is rendered
    entry, mask, visib = gt_info(depth, measured, REDWOOD.K)
    assert set(entry) == DOC_SCENE_GT_INFO
    assert entry["px_count_all"] == 56 * 56 == mask.sum()
    assert entry["bbox_obj"] == [292, 212, 55, 55]
    assert entry["px_count_valid"] == (330 - 292) * 56  # silhouette pixels with a measurement
    assert entry["px_count_visib"] == 56 * 56 - 20 * 56 == visib.sum()
    assert entry["visib_fract"] == pytest.approx((56 * 56 - 20 * 56) / (56 * 56))
    assert entry["bbox_visib"] == [292, 212, 55, 55]
    assert not visib[:, 310:330].any() and visib[212:268, 292:310].all() and visib[212:268, 330:348].all()
    assert all(isinstance(v, int) for k, v in entry.items() if k.startswith("px_")) and isinstance(entry["visib_fract"], float)


def test_truncated_cube_counts_its_whole_silhouette():
    """With the principal point at x = 10.5 the cube's 56 columns run from -17 to 38: px_count_all counts all of
    them (the export renders on a 3x canvas), the mask only the 39 inside the image, and bbox_obj starts at -17."""
    camera = Camera(fx=525, fy=525, cx=10.5, cy=239.5)
    depth, whole, offset = cube(camera)
    assert offset == (640, 480) and whole.shape == (1440, 1920)
    entry, mask, visib = gt_info(depth, np.zeros(camera.shape), camera.K, whole, offset)
    assert entry["px_count_all"] == 56 * 56
    assert mask.sum() == 39 * 56 == entry["px_count_visib"]
    assert entry["bbox_obj"] == [-17, 212, 55, 55] and entry["bbox_visib"] == [0, 212, 38, 55]
    assert entry["visib_fract"] == pytest.approx(39 / 56)
    # nothing visible: BOP leaves both boxes at -1
    far = np.full(camera.shape, 500.0)  # a wall half a metre in front of the cube
    entry, _, _ = gt_info(depth, far, camera.K, whole, offset)
    assert entry["px_count_visib"] == 0 and entry["bbox_obj"] == [-1, -1, -1, -1] and entry["bbox_visib"] == [-1, -1, -1, -1]


def test_visibility_tolerance_is_on_distances_not_depths():
    """BOP compares distances from the camera centre: off-axis, a 14 mm depth gap is a larger distance gap."""
    model = np.full((1, 2), 1000.0)
    measured = np.full((1, 2), 986.0)  # 14 mm in front in depth
    K = np.array([[100.0, 0, 0], [0, 100.0, 0], [0, 0, 1]])  # column 0 on the axis, column 1 off it by 0.01 rad
    entry, _, visib = gt_info(model, measured, K)
    assert visib.tolist() == [[True, True]]
    K[0, 0] = 1.0  # column 1 now 45 degrees off axis: the gap is 14 * sqrt(2) = 19.8 mm > 15 mm
    entry, _, visib = gt_info(model, measured, K)
    assert visib.tolist() == [[True, False]]
    assert DELTA_MM == 15.0


def test_diameter_is_the_farthest_vertex_pair():
    cube = trimesh.creation.box([30.0, 40.0, 120.0])
    assert diameter(cube.vertices) == pytest.approx(np.sqrt(30**2 + 40**2 + 120**2))
    points = np.random.default_rng(0).normal(size=(400, 3)) * [10, 20, 5]
    brute = max(np.linalg.norm(points[i] - points, axis=1).max() for i in range(len(points)))
    assert diameter(points) == pytest.approx(brute)


def test_json_layout_is_bop_toolkits():
    """One line per image, keys in numeric order (10 after 9), each value's keys sorted."""
    text = bop_json({10: [{"b": 1, "a": 2}], 9: {"z": [1.5], "c": 0}}).decode()
    assert text == '{\n  "9": {"c": 0, "z": [1.5]},\n  "10": [{"a": 2, "b": 1}]\n}'
    assert json.loads(text) == {"9": {"c": 0, "z": [1.5]}, "10": [{"a": 2, "b": 1}]}


def truth_reconstruction(scene, name: str, category: str, symmetry: str) -> Reconstruction:
    """The scene's true mesh and poses as a reconstruction (no carving: the export alone is under test)."""
    mesh = scene.mesh.copy()
    return Reconstruction(name, category, symmetry, mesh, mesh.extents.copy(), dict(scene.poses), {}, {})


@pytest.fixture(scope="module")
def bowl(tmp_path_factory):
    """A box-shaped 'bowl' (symmetry y), 6 frames rendered at 320x240, and its truth exported as BOP."""
    base = tmp_path_factory.mktemp("bop")
    box = trimesh.creation.box([0.06, 0.1, 0.04])
    scene = write_scene(base / "bowl_0003", box, n_frames=6, category="bowl", symmetry="y")
    sequence = open_sequence(scene.root)
    rec = truth_reconstruction(scene, "bowl_0003", "bowl", "y")
    out = base / "bop"
    export_bop(rec, sequence, out)
    return scene, sequence, rec, out


def read_ply(path):
    """(vertices (N, 3), faces (M, 3)) of an ASCII PLY whose header declares what bop_toolkit's load_ply reads:
    float x y z nx ny nz and 'list uchar int vertex_indices' triangles."""
    lines = path.read_text().splitlines()
    end = lines.index("end_header")
    header = lines[:end]
    assert header[0] == "ply" and header[1] == "format ascii 1.0"
    assert [h for h in header if h.startswith("property")] == [f"property float {p}" for p in ("x", "y", "z", "nx", "ny", "nz")] + ["property list uchar int vertex_indices"]
    n = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    m = int(next(h for h in header if h.startswith("element face")).split()[-1])
    rows = np.array([line.split() for line in lines[end + 1 : end + 1 + n]], dtype=np.float64)
    faces = np.array([line.split() for line in lines[end + 1 + n : end + 1 + n + m]], dtype=np.int64)
    assert (faces[:, 0] == 3).all()
    np.testing.assert_allclose(np.linalg.norm(rows[:, 3:], axis=1), 1.0, atol=1e-6)  # unit vertex normals
    return rows[:, :3], faces[:, 1:]


def test_files_and_fields_follow_the_document(bowl):
    scene, sequence, rec, out = bowl
    root = out / "test" / "000001"
    ids = [sequence.index(f) for f in sorted(rec.poses, key=sequence.index)]
    cameras = json.loads((root / "scene_camera.json").read_text())
    gts = json.loads((root / "scene_gt.json").read_text())
    infos = json.loads((root / "scene_gt_info.json").read_text())
    assert list(cameras) == list(gts) == list(infos) == [str(i) for i in ids]
    assert sorted(read_scene_gt_info(root / "scene_gt_info.json")) == ids  # our reader checks every field is there
    for im_id in ids:
        key = str(im_id)
        assert set(cameras[key]) == DOC_SCENE_CAMERA
        assert cameras[key]["cam_K"] == scene.camera.K.reshape(-1).tolist()  # saved row-wise
        assert cameras[key]["depth_scale"] == 1.0  # millimetre depth images: x 1 gives mm
        assert len(gts[key]) == 1 and set(gts[key][0]) == DOC_SCENE_GT and gts[key][0]["obj_id"] == 1
        assert len(infos[key]) == 1 and set(infos[key][0]) == DOC_SCENE_GT_INFO
        for sub in ("rgb", "depth"):  # the sequence's own files, byte for byte
            frame = sequence.frames[im_id]
            source = frame.color_path if sub == "rgb" else frame.depth_path
            assert (root / sub / f"{im_id:06d}.png").read_bytes() == source.read_bytes()
        for sub in ("mask", "mask_visib"):  # IMID_GTID.png, uint8 0 / 255
            image = np.asarray(Image.open(root / sub / f"{im_id:06d}_000000.png"))
            assert image.dtype == np.uint8 and set(np.unique(image)) <= {0, 255}
    info = json.loads((out / "models" / "models_info.json").read_text())["1"]
    assert set(info) == DOC_MODEL_INFO | {"symmetries_continuous"}
    # millimetres, z up: the model's z size is the object's height (ShapeNet y), the box centred on the origin
    assert [info["size_x"], info["size_y"], info["size_z"]] == pytest.approx([60.0, 40.0, 100.0])
    assert [info["min_x"], info["min_y"], info["min_z"]] == pytest.approx([-30.0, -20.0, -50.0])
    assert info["diameter"] == pytest.approx(np.sqrt(60**2 + 40**2 + 100**2))
    assert info["symmetries_continuous"] == [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]
    vertices, faces = read_ply(out / "models" / "obj_000001.ply")
    np.testing.assert_allclose(vertices, rec.mesh.vertices @ SHAPENET_FROM_BOP * 1000.0, atol=1e-5)
    assert (faces == rec.mesh.faces).all()


def test_poses_project_the_model_onto_its_mask(bowl):
    """The document's P_m2i = K [R_m2c, t_m2c] maps the model (mm) onto the image: every vertex projects into the
    silhouette's box, and the translation is the true one in millimetres."""
    scene, sequence, rec, out = bowl
    root = out / "test" / "000001"
    gts = read_scene_gt(root / "scene_gt.json")
    infos = json.loads((root / "scene_gt_info.json").read_text())
    vertices, _ = read_ply(out / "models" / "obj_000001.ply")
    for frame_id, pose in rec.poses.items():
        im_id = sequence.index(frame_id)
        gt = gts[im_id][0]
        np.testing.assert_allclose(gt["cam_t_m2c"], pose[:3, 3] * 1000.0, atol=1e-9)
        p = scene.camera.K @ (gt["cam_R_m2c"] @ vertices.T + gt["cam_t_m2c"][:, None])
        u, v = p[0] / p[2], p[1] / p[2]
        x, y, w, h = infos[str(im_id)][0]["bbox_obj"]
        assert (u > x - 1).all() and (u < x + w + 1).all() and (v > y - 1).all() and (v < y + h + 1).all()


def recomputed_gt_info(out, scene_dir, im_id: int, delta: float = 15.0) -> tuple[dict, np.ndarray, np.ndarray]:
    """scene_gt_info's entry and the two masks recomputed from the written files alone, as calc_gt_info.py and
    calc_gt_masks.py define them, with another renderer (every canvas pixel cast, camera frame, the PLY in mm)."""
    cam = json.loads((scene_dir / "scene_camera.json").read_text())[str(im_id)]
    gt = json.loads((scene_dir / "scene_gt.json").read_text())[str(im_id)][0]
    K = np.array(cam["cam_K"]).reshape(3, 3)
    depth = np.asarray(Image.open(scene_dir / "depth" / f"{im_id:06d}.png")).astype(np.float64) * cam["depth_scale"]
    h, w = depth.shape
    vertices, faces = read_ply(out / "models" / f"obj_{gt['obj_id']:06d}.ply")
    posed = vertices @ np.array(gt["cam_R_m2c"]).reshape(3, 3).T + np.array(gt["cam_t_m2c"])
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(posed.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    us, vs = np.meshgrid(np.arange(-w, 2 * w), np.arange(-h, 2 * h))
    directions = np.stack([(us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1], np.ones(us.shape)], axis=-1)
    rays = np.concatenate([np.zeros(directions.shape), directions], axis=-1).reshape(-1, 6).astype(np.float32)
    t = rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(us.shape)
    model_depth = np.where(np.isfinite(t), t, 0.0)  # z = t for rays with z = 1
    ray_length = np.linalg.norm(directions, axis=-1)
    model_dist = (model_depth * ray_length)[h : 2 * h, w : 2 * w]
    measured_dist = depth * ray_length[h : 2 * h, w : 2 * w]
    mask = model_dist > 0
    visib = mask & ((measured_dist == 0) | (model_dist - measured_dist <= delta))
    whole = model_depth > 0

    def box(m, dx=0, dy=0):
        ys, xs = np.nonzero(m)
        return [int(xs.min()) - dx, int(ys.min()) - dy, int(xs.max() - xs.min()), int(ys.max() - ys.min())] if len(xs) else [-1, -1, -1, -1]

    entry = {"px_count_all": int(whole.sum()), "px_count_valid": int((mask & (measured_dist > 0)).sum()), "px_count_visib": int(visib.sum()),
             "bbox_obj": box(whole, w, h), "bbox_visib": box(visib)}
    return entry, mask, visib


def test_gt_info_and_masks_match_a_recomputation_from_the_files(tmp_path):
    """A cup held by a 'hand' (a sphere), with depth noise: scene_gt_info and both masks as recomputed from the
    written files. Measured: equal to the pixel in all 8 frames (visible fractions 0.86-1.0); a pixel of slack
    allows for the two renderers' float32 rays."""
    scene = write_scene(tmp_path / "bowl_0004", cup_mesh(), n_frames=8, hand=True, noise=True, category="bowl", symmetry="y")
    sequence = open_sequence(scene.root)
    out = tmp_path / "bop"
    export_bop(truth_reconstruction(scene, "bowl_0004", "bowl", "y"), sequence, out)
    root = out / "test" / "000001"
    infos = json.loads((root / "scene_gt_info.json").read_text())
    assert min(entries[0]["visib_fract"] for entries in infos.values()) < 0.95  # the hand occludes
    for key, entries in infos.items():
        ours = entries[0]
        theirs, mask, visib = recomputed_gt_info(out, root, int(key))
        for field in ("px_count_all", "px_count_valid", "px_count_visib"):
            assert abs(ours[field] - theirs[field]) <= 1, (key, field, ours[field], theirs[field])
        assert ours["visib_fract"] == pytest.approx(ours["px_count_visib"] / ours["px_count_all"])
        assert np.abs(np.subtract(ours["bbox_obj"], theirs["bbox_obj"])).max() <= 1
        assert np.abs(np.subtract(ours["bbox_visib"], theirs["bbox_visib"])).max() <= 1
        for sub, expected in (("mask", mask), ("mask_visib", visib)):
            written = np.asarray(Image.open(root / sub / f"{int(key):06d}_000000.png")) > 0
            assert (written != expected).sum() <= 1


def test_round_trip_through_our_reader(bowl):
    scene, sequence, rec, out = bowl
    data = open_dataset(out)
    assert data.__class__.__name__ == "BopDataset" and len(data) == len(rec.poses)
    for sample in data:
        assert (sample.sequence, sample.instance, sample.category, sample.symmetry) == ("bowl_0003", None, "bowl", "y")
        np.testing.assert_allclose(sample.pose, rec.poses[sample.frame], atol=1e-9)
        np.testing.assert_allclose(sample.extents, rec.extents, atol=1e-9)
        assert sample.camera == scene.camera
        written = np.asarray(Image.open(out / "test" / "000001" / "mask_visib" / f"{sequence.index(sample.frame):06d}_000000.png")) > 0
        assert np.array_equal(data.mask(sample), written)
        assert np.array_equal(data.color(sample), sequence.color(sample.frame))
        np.testing.assert_allclose(data.depth(sample), sequence.depth(sample.frame))
    mesh = data.mesh(data.samples[0])
    np.testing.assert_allclose(mesh.vertices, rec.mesh.vertices, atol=1e-8)
    assert (np.asarray(mesh.faces) == rec.mesh.faces).all()
    # the toolkit's own BOP scene reader (benchmarks) reads the scene as a sequence with its truth, in BOP's axes
    truth = load_bop_truth(out / "test" / "000001", "obj_000001")
    for frame_id, pose in rec.poses.items():
        bop_pose = truth.poses[f"{sequence.index(frame_id):06d}"]
        np.testing.assert_allclose(bop_pose[:3, :3] @ SHAPENET_FROM_BOP.T, pose[:3, :3], atol=1e-9)
        np.testing.assert_allclose(bop_pose[:3, 3], pose[:3, 3], atol=1e-9)


def disturbed_predictions(rec: Reconstruction, path: Path, key) -> Path:
    """A predictions file of the truth disturbed more and more, frame after frame: the k-th frame's position off by
    4.5 k mm, its orientation turned by 2.3 k degrees about the camera's x axis, its extents scaled by 1 + 0.03 k;
    ``key(frame id)`` gives the line's (sequence, frame, instance)."""
    lines = []
    for k, (frame_id, pose) in enumerate(sorted(rec.poses.items())):
        sequence, frame, instance = key(frame_id)
        turn = trimesh.transformations.rotation_matrix(np.radians(2.3 * k), [1.0, 0.0, 0.0])[:3, :3]
        line = {"sequence": sequence, "frame": frame, "position": (pose[:3, 3] + [0.0045 * k, 0.0, 0.0]).tolist(),
                "orientation": matrix_to_quat(turn @ pose[:3, :3]).tolist(), "extents": (rec.extents * (1 + 0.03 * k)).tolist()}
        if instance is not None:
            line["instance"] = instance
        lines.append(json.dumps(line))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_evaluate_gives_the_same_numbers_on_the_redwood75_and_bop_exports(bowl, tmp_path):
    """One predictions file (disturbed truth) evaluated on the REDWOOD75 export and on the BOP export of the same
    truth: the same samples (names), the same precision table."""
    from evaluate.cli import main as evaluate_main

    scene, sequence, rec, out = bowl
    redwood = tmp_path / "redwood"
    export_redwood(rec, sequence, load_annotation(scene.root / "annotation.yaml"), redwood)
    predictions = disturbed_predictions(rec, tmp_path / "p.jsonl", lambda frame_id: ("bowl_0003", frame_id, None))
    results = {}
    for name, dataset in (("redwood", redwood), ("bop", out)):
        assert evaluate_main(["--dataset", str(dataset), "--method", f"p={predictions}", "--out", str(tmp_path / f"eval_{name}"), "--quiet"]) == 0
        results[name] = json.loads((tmp_path / f"eval_{name}" / "results.json").read_text())["methods"]
    assert results["redwood"]["p"]["samples"] == results["bop"]["p"]["samples"] == len(rec.poses)
    assert results["redwood"] == results["bop"]
    overall = [row["overall"] for row in results["bop"]["p"]["precision"]]
    assert any(0 < v < 1 for v in overall if v is not None)  # the disturbances make some samples fail: a real comparison


def test_re_export_replaces_the_scene_whole_and_adds_objects(bowl, tmp_path):
    scene, sequence, rec, out = bowl
    target = tmp_path / "bop"
    shutil.copytree(out, target)
    fewer = truth_reconstruction(scene, "bowl_0003", "bowl", "y")
    fewer.poses = dict(list(rec.poses.items())[:2])
    export_bop(fewer, sequence, target)
    assert sorted(p.name for p in (target / "test" / "000001" / "rgb").iterdir()) == ["000000.png", "000001.png"]
    assert len(json.loads((target / "test" / "000001" / "scene_gt.json").read_text())) == 2
    other = truth_reconstruction(scene, "can_0001", "can", "none")
    export_bop(other, sequence, target)
    info = read_models_info(target / "models" / "models_info.json")
    assert sorted(info) == [1, 2] and info[2]["symmetries_continuous"] == [] and len(info[1]["symmetries_continuous"]) == 1
    index = json.loads((target / "annotations.json").read_text())
    assert {k: (v["format"], v["scene_id"], v["obj_id"]) for k, v in index.items()} == {"bowl_0003": ("bop", 1, 1), "can_0001": ("bop", 2, 2)}
    assert [s.category for s in open_dataset(target)] == ["bowl"] * 2 + ["can"] * 6
    assert sorted(p.name for p in target.iterdir() if p.name.startswith(".") and p.name != ".export.lock") == []  # no staging left


def test_a_failing_export_leaves_the_previous_one_whole(bowl, tmp_path, monkeypatch):
    scene, sequence, rec, out = bowl
    target = tmp_path / "bop"
    shutil.copytree(out, target)
    before = {p.relative_to(target): p.read_bytes() for p in target.rglob("*") if p.is_file()}
    import reconstruct.export_bop as export_bop_module

    calls = []

    def failing(mask):
        calls.append(1)
        if len(calls) > 5:
            raise OSError("disk full")
        return b"png"

    monkeypatch.setattr(export_bop_module, "mask_png_bytes", failing)
    with pytest.raises(OSError, match="disk full"):
        export_bop(truth_reconstruction(scene, "bowl_0003", "bowl", "y"), sequence, target)
    after = {p.relative_to(target): p.read_bytes() for p in target.rglob("*") if p.is_file()}
    assert after == before


def test_cli_writes_bop_and_refuses_to_mix_formats(tmp_path, capsys):
    box = trimesh.creation.box([0.05, 0.08, 0.03])
    scene = write_scene(tmp_path / "camera_0002", box, n_frames=10, category="camera")
    out = tmp_path / "out"
    assert main([str(scene.root), "--out", str(out), "--format", "bop", "--voxel-size", "0.004"]) == 0
    data = open_dataset(out)
    assert len(data) == 10 and {s.category for s in data} == {"camera"} and {s.symmetry for s in data} == {"none"}
    assert np.allclose(data.samples[0].extents, box.extents, atol=0.012)  # carved at 4 mm voxels
    assert np.degrees(np.arccos(np.clip((np.trace(quat_to_matrix(data.samples[0].orientation).T @ scene.poses[data.samples[0].frame][:3, :3]) - 1) / 2, -1, 1))) < 1e-6
    # a REDWOOD75 export folder is not written into as BOP, nor a BOP one as REDWOOD75: one line naming the folder
    redwood = tmp_path / "redwood"
    assert main([str(scene.root), "--out", str(redwood), "--voxel-size", "0.004", "--no-masks"]) == 0
    capsys.readouterr()
    with pytest.raises(InputError, match="holds a redwood75 export"):
        main([str(scene.root), "--out", str(redwood), "--format", "bop"])
    with pytest.raises(InputError, match="holds a bop export") as error:
        main([str(scene.root), "--out", str(out)])
    assert str(out) in str(error.value) and "\n" not in str(error.value)


def test_bad_bop_files_end_in_one_line(bowl, tmp_path):
    scene, sequence, rec, out = bowl
    target = tmp_path / "bop"
    shutil.copytree(out, target)
    gt = target / "test" / "000001" / "scene_gt.json"
    gt.write_text(gt.read_text().replace('"cam_t_m2c"', '"cam_t"', 1))
    with pytest.raises(InputError, match="scene_gt.json.*cam_t_m2c"):
        open_dataset(target)
    shutil.copy(out / "test" / "000001" / "scene_gt.json", gt)
    info = target / "models" / "models_info.json"
    info.write_text("{not json")
    with pytest.raises(InputError, match="models_info.json"):
        open_dataset(target)
    with pytest.raises(InputError, match="models_info.json"):  # the export refuses to overwrite it
        export_bop(truth_reconstruction(scene, "can_0009", "can", "y"), sequence, target)


EXPORT_SCRIPT = """
import sys, numpy as np, trimesh
from reconstruct.pipeline import Reconstruction
from sequences.annotation import load_annotation
from sequences.reader import open_sequence
root, out, fmt, scale = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
document = load_annotation(root + "/annotation.yaml")
mesh = trimesh.creation.box(document.extents * scale)
poses = {f: p.matrix for f, p in document.frames.items()}
rec = Reconstruction(document.sequence, document.category, document.symmetry, mesh, mesh.extents.copy(), poses, {}, {})
if fmt == "bop":
    from reconstruct.export_bop import export_bop
    export_bop(rec, open_sequence(root), out)
else:
    from reconstruct.export_nocs import export_nocs
    export_nocs(rec, open_sequence(root), out)
"""


def killed_exports_leave_a_whole_export(tmp_path: Path, fmt: str, kills: int, seed: int = 0) -> list[str]:
    """Export a sequence (a box), then SIGKILL re-exports of a 10 % larger box at random moments: after the next
    export's recovery, the folder must hold the first export or the second, file for file. Returns the state after
    each kill ("old" or "new")."""
    import signal
    import subprocess
    import sys
    import time

    from reconstruct.transaction import OutLock, recover

    repo = Path(__file__).resolve().parents[1]
    scene = write_scene(tmp_path / "can_0005", trimesh.creation.box([0.05, 0.08, 0.05]), n_frames=30, camera=REDWOOD, category="can", symmetry="y")
    script = tmp_path / "export.py"
    script.write_text(EXPORT_SCRIPT)

    def run(out, scale):
        return subprocess.Popen([sys.executable, str(script), str(scene.root), str(out), fmt, str(scale)], cwd=repo, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def state(out):
        return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file() and p.name != ".export.lock"}

    out, reference = tmp_path / "out", tmp_path / "reference"
    assert run(out, 1.0).wait() == 0
    old = state(out)
    shutil.copytree(out, reference)
    start = time.perf_counter()
    assert run(reference, 1.1).wait() == 0
    duration = time.perf_counter() - start  # the kills fall within a re-export's run time
    new = state(reference)
    assert new != old
    rng = np.random.default_rng(seed)
    seen = []
    for attempt in range(kills):
        process = run(out, 1.1)
        time.sleep(rng.uniform(0.3, 1.0) * duration)
        process.send_signal(signal.SIGKILL)
        process.wait()
        with OutLock(out):
            recover(out)
        found = state(out)
        assert found in (old, new), attempt
        seen.append("new" if found == new else "old")
        if found == new:  # start again from the first export
            shutil.rmtree(out)
            assert run(out, 1.0).wait() == 0
    return seen


@pytest.mark.slow
def test_a_killed_bop_export_leaves_the_old_or_the_new_export_whole(tmp_path):
    assert killed_exports_leave_a_whole_export(tmp_path, "bop", kills=4)


# ------------------------------------------------------------------------------------------------ test targets

TARGET_FIELDS = {"im_id", "inst_count", "obj_id", "scene_id"}  # enumerate_test_targets.py's entry


def test_targets_keep_the_objects_at_least_a_tenth_visible():
    """enumerate_test_targets.py's rule: visib_fract >= min_visib_fract (0.1), images in id order."""
    from reconstruct.export_bop import targets_bop19

    infos = {"7": [{"visib_fract": 0.0999}], "3": [{"visib_fract": 0.1}], "12": [{"visib_fract": 1.0}], "0": [{"visib_fract": 0.0}]}
    assert targets_bop19(infos, obj_id=4, scene_id=9) == [{"im_id": 3, "inst_count": 1, "obj_id": 4, "scene_id": 9},
                                                          {"im_id": 12, "inst_count": 1, "obj_id": 4, "scene_id": 9}]


def test_test_targets_follow_the_frames_and_objects_written(bowl, tmp_path):
    """OUT/test_targets_bop19.json, field by field: per scene (ids ascending) and image (ids ascending), the object of
    scene_gt.json where scene_gt_info.json says it is at least 10 % visible, as {im_id, inst_count, obj_id,
    scene_id}; laid out as inout.save_json writes a list; a second scene adds its targets, a re-export replaces its
    own; an existing file that is not a target list is refused in one line and kept."""
    scene, sequence, rec, _ = bowl
    ids = sorted(rec.poses, key=sequence.index)
    behind = {frame: pose.copy() for frame, pose in rec.poses.items()}
    behind[ids[2]][2, 3] = -1.0  # behind the camera: no pixel, visib_fract 0
    hidden = Reconstruction("bowl_0003", "bowl", "y", rec.mesh, rec.extents, behind, {}, {})
    other = Reconstruction("bowl_0004", "bowl", "y", rec.mesh, rec.extents, dict(rec.poses), {}, {})
    out = tmp_path / "bop"
    export_bop(hidden, sequence, out, masks=False)
    export_bop(other, sequence, out, masks=False)

    def expected() -> list[dict]:
        index = json.loads((out / "annotations.json").read_text())
        rows = []
        for name in sorted(index, key=lambda n: index[n]["scene_id"]):
            scene_id = index[name]["scene_id"]
            root = out / "test" / f"{scene_id:06d}"
            gts = json.loads((root / "scene_gt.json").read_text())
            infos = json.loads((root / "scene_gt_info.json").read_text())
            for im_id in sorted(gts, key=int):
                for gt, info in zip(gts[im_id], infos[im_id]):
                    if info["visib_fract"] >= 0.1:
                        rows.append({"im_id": int(im_id), "inst_count": 1, "obj_id": gt["obj_id"], "scene_id": scene_id})
        return rows

    path = out / "test_targets_bop19.json"
    text = path.read_text()
    targets = json.loads(text)
    assert text == "[\n" + ",\n".join("  " + json.dumps(t, sort_keys=True) for t in targets) + "\n]"
    assert all(set(t) == TARGET_FIELDS and all(type(v) is int for v in t.values()) for t in targets)
    assert targets == expected()
    positions = [sequence.index(f) for f in ids]
    assert [t["im_id"] for t in targets if t["scene_id"] == 1] == [p for p in positions if p != positions[2]]
    assert [t["im_id"] for t in targets if t["scene_id"] == 2] == positions
    assert {t["obj_id"] for t in targets if t["scene_id"] == 2} == {2}
    export_bop(rec, sequence, out, masks=False)  # bowl_0003 again, every frame in view
    targets = json.loads(path.read_text())
    assert targets == expected() and [t["scene_id"] for t in targets] == [1] * len(ids) + [2] * len(ids)
    path.write_text('{"not": "a list"}')
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != ".export.lock"}
    with pytest.raises(InputError, match="test_targets_bop19.json.*not a list"):
        export_bop(other, sequence, out, masks=False)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != ".export.lock"} == before


# ------------------------------------------------------------------------------------------------ side by side

def test_frames_render_before_the_lock_and_only_the_swap_waits_for_it(bowl, tmp_path):
    """An export renders and stages every frame while another holds OUT's lock, and swaps them in once it is free;
    a recovery run meanwhile (another export's) leaves the staging alone, as its claim is held."""
    import threading
    import time

    from reconstruct.transaction import OutLock, recover

    scene, sequence, rec, _ = bowl
    out = tmp_path / "bop"
    out.mkdir()
    finished = []
    with OutLock(out):
        thread = threading.Thread(target=lambda: finished.append(export_bop(rec, sequence, out)), daemon=True)
        thread.start()
        deadline = time.monotonic() + 120
        while not list(out.glob(".staging-*/models/pending.ply")) and time.monotonic() < deadline:  # staged last
            time.sleep(0.02)
        staged = sorted(p.name for p in out.glob(".staging-*/test/pending/mask_visib/*.png"))
        assert staged == [f"{sequence.index(f):06d}_000000.png" for f in sorted(rec.poses, key=sequence.index)]
        assert thread.is_alive() and not (out / "annotations.json").exists()
        recover(out)
        assert len(list(out.glob(".staging-*/test/pending/mask_visib/*.png"))) == len(staged)
    thread.join(120)
    assert finished and json.loads((out / "annotations.json").read_text())["bowl_0003"]["scene_id"] == 1
    assert len(list((out / "test" / "000001" / "mask_visib").iterdir())) == len(staged)
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [".export.lock"]  # no staging, claim or journal left


def test_a_batch_reserves_scene_numbers_in_its_order():
    """A sequence keeps its number; the others get the least free ones in the batch's order (numbers of the index and
    scenes on disk taken); a reserved number taken meanwhile gives way to the least free one."""
    from reconstruct.export_index import reserve_numbers, scene_number

    index = {"a": {"scene_id": 2}, "b": {"scene_id": 5}}
    taken = {1, 2, 5}  # scene folders on disk
    assert reserve_numbers(index, ["c", "b", "d", "e"], "scene_id", taken) == {"c": 3, "b": 5, "d": 4, "e": 6}
    assert scene_number(index, "c", "scene_id", taken, reserved=4) == 4
    assert scene_number({**index, "x": {"scene_id": 4}}, "c", "scene_id", taken, reserved=4) == 3
    assert scene_number(index, "b", "scene_id", taken, reserved=9) == 5
    assert scene_number(index, "c", "scene_id", taken, reserved=0) == 3
