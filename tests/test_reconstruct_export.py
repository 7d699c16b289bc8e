"""reconstruct export and CLI: REDWOOD75 format, cpas_toolbox reads it back, atomic merge, failing sequences."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import trimesh
from PIL import Image

from evaluate.geometry import RAW_FROM_SHAPENET, quat_to_matrix
from reconstruct.cli import main
from reconstruct.export import export_redwood, obj_text, raw_mesh
from reconstruct.masks import render_masks
from reconstruct.pipeline import reconstruct_sequence
from sequences.annotation import load_annotation
from sequences.errors import InputError
from sequences.reader import open_sequence
from test_reconstruct_scenes import write_scene


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A small box scene reconstructed and exported into OUT that already holds REDWOOD75-style data."""
    base = tmp_path_factory.mktemp("export")
    scene = write_scene(base / "mug_0007", trimesh.creation.box([0.05, 0.08, 0.03]), n_frames=16, category="mug")
    sequence = open_sequence(scene.root)
    annotation = load_annotation(scene.root / "annotation.yaml")
    rec = reconstruct_sequence(sequence, annotation, voxel_size=0.003)
    out = base / "out"
    out.mkdir()
    (out / "annotations.json").write_text(json.dumps({"other_seq": {"category": "bowl", "mesh": "other_seq.obj", "scale": [1, 2, 3], "pose_anns": []}}))
    path = export_redwood(rec, sequence, annotation, out)
    return scene, sequence, rec, out, path


def test_export_has_redwood75_keys_and_raw_axes(exported, redwood75_dir):
    scene, sequence, rec, out, path = exported
    data = json.loads(path.read_text())
    assert set(data) == {"other_seq", "mug_0007"}  # merged, the other sequence kept
    reference = json.loads((redwood75_dir / "annotations.json").read_text())
    ref_entry = next(iter(reference.values()))
    entry = data["mug_0007"]
    assert set(entry) == set(ref_entry)
    assert set(entry["pose_anns"][0]) == set(ref_entry["pose_anns"][0])
    assert entry["mesh"] == "mug_0007.obj" and entry["category"] == "mug"
    assert len(entry["pose_anns"]) == 16
    first = entry["pose_anns"][0]
    assert first["rgb_file"] == sequence.frames[0].color_path.name and first["depth_file"] == sequence.frames[0].depth_path.name
    # scale = half extents in raw axes (raw x = ShapeNet z, raw y = ShapeNet y, raw z = ShapeNet x in size)
    np.testing.assert_allclose(entry["scale"], rec.extents[[2, 1, 0]] / 2)
    # raw pose and raw mesh put the same points in the camera as our ShapeNet pose and mesh
    raw_mesh = trimesh.load(out / "mug_0007.obj", process=False)
    np.testing.assert_allclose(raw_mesh.vertices, rec.mesh.vertices @ RAW_FROM_SHAPENET.T, atol=1e-7)
    frame_id = sequence.frames[0].id
    R_raw = quat_to_matrix(first["orientation"])
    cam_raw = raw_mesh.vertices @ R_raw.T + first["position"]
    T = rec.poses[frame_id]
    cam_ours = rec.mesh.vertices @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(cam_raw, cam_ours, atol=1e-6)
    np.testing.assert_allclose(raw_mesh.bounds.mean(axis=0), 0, atol=1e-9)  # centred on its tight box
    assert raw_mesh.is_watertight and raw_mesh.volume > 0


def test_export_masks_and_report(exported):
    scene, sequence, rec, out, path = exported
    masks = sorted((out / "masks" / "mug_0007").glob("*.png"))
    assert [m.stem for m in masks] == sequence.ids
    mask = np.asarray(Image.open(masks[0]))
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
    # the mask covers the true box's silhouette up to the reconstruction's accuracy
    from test_reconstruct_scenes import render_depth

    posed = scene.mesh.copy()
    posed.apply_transform(scene.poses[sequence.ids[0]])
    truth = render_depth([posed], scene.camera) < 1.5
    iou = (truth & (mask > 0)).sum() / (truth | (mask > 0)).sum()
    assert iou > 0.85
    report = json.loads((out / "reports" / "mug_0007.json").read_text())
    assert report["frames_used"] == 16 and report["watertight"] is True and "carve" in report["timings"]
    assert report["voxels"] == int(np.prod(report["grid_shape"]))
    preview = Image.open(out / "reports" / "mug_0007.png")
    assert preview.size == (scene.camera.width, scene.camera.height)  # 4 frames at half size, 2 x 2


@pytest.mark.slow  # importing torch takes ~20 s on a loaded 2-core machine
def test_cpas_toolbox_reads_our_poses_and_extents_back(exported, tmp_path):
    pytest.importorskip("torch")
    redwood = pytest.importorskip("cpas_toolbox.datasets.redwood_dataset")
    scene, sequence, rec, out, path = exported
    # cpas_toolbox's layout: ROOT/<category>/rgbd/<sequence>/rgb|depth, ANN/annotations.json, ANN/<mesh>
    root = tmp_path / "redwood"
    shutil.copytree(scene.root, root / "mug" / "rgbd" / "mug_0007")
    ann = tmp_path / "ann"
    ann.mkdir()
    data = json.loads(path.read_text())
    (ann / "annotations.json").write_text(json.dumps({"mug_0007": data["mug_0007"]}))
    shutil.copy(out / "mug_0007.obj", ann / "mug_0007.obj")
    dataset = redwood.AnnotatedRedwoodDataset({"root_dir": str(root), "ann_dir": str(ann), "remap_y_axis": "-y", "remap_x_axis": "z", "camera_convention": "opencv", "scale_convention": "full"})
    assert len(dataset) == 16
    for i, frame_id in enumerate(sequence.ids[:4]):
        raw = dataset._raw_samples[i]
        assert raw["color_path"].endswith(sequence.frames[i].color_path.name)
        q, extents = dataset._change_axis_convention(raw["orientation_q"], raw["extents"])
        np.testing.assert_allclose(extents.numpy(), rec.extents, atol=1e-6)
        np.testing.assert_allclose(quat_to_matrix(q.numpy()), rec.poses[frame_id][:3, :3], atol=1e-6)
        np.testing.assert_allclose(raw["position"].numpy(), rec.poses[frame_id][:3, 3], atol=1e-6)
        # its mesh loader with the same remapping gives our ShapeNet-axes mesh
        mesh = dataset.load_mesh(raw["mesh_path"])
        np.testing.assert_allclose(np.asarray(mesh.vertices), rec.mesh.vertices, atol=1e-6)


def test_corrupt_existing_annotations_is_kept_and_reported(exported, tmp_path):
    scene, sequence, rec, out, path = exported
    bad = tmp_path / "bad_out"
    bad.mkdir()
    (bad / "annotations.json").write_text("{not json")
    with pytest.raises(InputError, match="annotations.json"):
        export_redwood(rec, sequence, load_annotation(scene.root / "annotation.yaml"), bad)
    assert sorted(p.name for p in bad.iterdir()) == ["annotations.json"]
    assert (bad / "annotations.json").read_text() == "{not json"


def test_cli_several_sequences_one_failing(exported, tmp_path, capsys):
    scene = exported[0]
    broken = tmp_path / "broken_seq"
    shutil.copytree(scene.root, broken)
    (broken / "annotation.yaml").write_text("category: mug\nframes: {'0000000': {position: [0, 0, .nan], orientation: [0, 0, 0, 1]}}\n")
    out = tmp_path / "cli_out"
    code = main([str(scene.root), str(broken), "--out", str(out), "--voxel-size", "0.003", "--no-masks"])
    assert code == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "broken_seq/annotation.yaml" in errors[0] and "NaN" in errors[0]
    data = json.loads((out / "annotations.json").read_text())
    assert list(data) == ["mug_0007"]
    assert not (out / "broken_seq.obj").exists() and (out / "mug_0007.obj").exists()
    assert not (out / "masks").exists()
    # all good: exit 0; --annotation with several sequences is refused in one line
    assert main([str(scene.root), "--out", str(out), "--voxel-size", "0.003", "--no-masks"]) == 0
    with pytest.raises(InputError, match="single SEQ"):
        main([str(scene.root), str(broken), "--annotation", str(broken / "annotation.yaml"), "--out", str(out)])


def test_a_reexport_swaps_the_mask_folder_whole_and_another_format_is_refused(exported, tmp_path):
    """Exporting the sequence again with fewer frames leaves none of the old masks; a folder that holds a BOP export
    refuses a REDWOOD75 one (the formats are never mixed), untouched."""

    scene, sequence, rec, out, path = exported
    annotation = load_annotation(scene.root / "annotation.yaml")
    target = tmp_path / "again"
    export_redwood(rec, sequence, annotation, target)
    masks = target / "masks" / rec.sequence
    assert len(list(masks.iterdir())) == len(rec.poses) == 16
    kept = sorted(rec.poses, key=sequence.index)[:3]
    export_redwood(dataclasses.replace(rec, poses={f: rec.poses[f] for f in kept}), sequence, annotation, target)
    assert sorted(p.name for p in masks.iterdir()) == sorted(f"{f}.png" for f in kept)
    assert len(json.loads((target / "annotations.json").read_text())[rec.sequence]["pose_anns"]) == 3
    bop = tmp_path / "bop"
    (bop / "models").mkdir(parents=True)
    (bop / "models" / "models_info.json").write_text("{}")
    with pytest.raises(InputError, match="bop export"):
        export_redwood(rec, sequence, annotation, bop)
    assert sorted(p.name for p in bop.iterdir()) == ["models"]


def test_masks_made_beside_the_labels_are_those_the_export_renders(exported, tmp_path):
    scene, sequence, rec, out, path = exported
    annotation = load_annotation(scene.root / "annotation.yaml")
    with_masks = reconstruct_sequence(sequence, annotation, voxel_size=0.003, masks=True)
    rendered = render_masks(with_masks.mesh, with_masks.poses, sequence.camera, sequence.depth)
    assert list(with_masks.masks()) == list(rendered) == sequence.ids
    for frame_id in sequence.ids:
        np.testing.assert_array_equal(with_masks.masks()[frame_id], rendered[frame_id])
        written = np.asarray(Image.open(out / "masks" / "mug_0007" / f"{frame_id}.png")) > 0  # the fixture's export rendered its own
        np.testing.assert_array_equal(written, rendered[frame_id])
    assert rec.masks() is None  # not asked for
    # poses replaced after the rendering: the masks no longer hold, and an export renders those of its own frames
    fewer = dataclasses.replace(with_masks, poses={f: with_masks.poses[f] for f in sequence.ids[:5]})
    assert fewer.masks() is None
    again = tmp_path / "again"
    export_redwood(fewer, sequence, annotation, again)
    assert sorted(p.stem for p in (again / "masks" / "mug_0007").glob("*.png")) == sequence.ids[:5]
    moved = dataclasses.replace(with_masks, mesh=with_masks.mesh.copy())
    assert moved.masks() is None


def test_obj_text_writes_the_lines_trimesh_writes(exported):
    rec = exported[2]
    mesh = raw_mesh(rec.mesh)
    ours = obj_text(mesh, "mug_0007")
    theirs = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=False, include_texture=False,
                                             header="mug_0007: reconstruct-sequence (REDWOOD75 raw axes, metres)")
    assert ours == theirs.rstrip("\n") + "\n"  # trimesh's lines, without its trailing blank line
    back = trimesh.load(exported[3] / "mug_0007.obj", process=False)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-8)
    np.testing.assert_array_equal(back.faces, mesh.faces)
