"""The ``evaluate`` command end to end: real REDWOOD75 annotations, predictions files written here
(truth, known wrong poses, a NaN, a missing line), the oracle, the outputs, and bad input."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image
from scipy.spatial.transform import Rotation

from evaluate.cli import main
from evaluate.methods import Method, Prediction
from sequences.errors import run_cli

REPO = Path(__file__).resolve().parents[1]


def _truth(redwood75_dir: Path) -> dict:
    """The truth in ShapeNet axes, remapped by hand from the raw file (independently of evaluate.geometry):
    ShapeNet x = raw z, ShapeNet y = -raw y, ShapeNet z = raw x."""
    raw = json.loads((redwood75_dir / "annotations.json").read_text())
    truth = {}
    for sequence, entry in raw.items():
        for ann in entry["pose_anns"]:
            R_raw = Rotation.from_quat(ann["orientation"]).as_matrix()
            R = np.stack([R_raw[:, 2], -R_raw[:, 1], R_raw[:, 0]], axis=1)
            truth[(sequence, ann["rgb_file"])] = {
                "category": entry["category"],
                "position": np.array(ann["position"]),
                "R": R,
                "extents": 2 * np.array(entry["scale"])[[2, 1, 0]],
            }
    return truth


def _mesh_points(redwood75_dir: Path, sequence: str) -> np.ndarray:
    import trimesh

    v = np.asarray(trimesh.load(redwood75_dir / "meshes" / f"{sequence}.obj", force="mesh", process=False).vertices)
    return np.stack([v[:, 2], -v[:, 1], v[:, 0]], axis=1)


def _line(sequence, rgb_file, position, R, extents, reconstruction=None) -> str:
    entry = {"sequence": sequence, "frame": rgb_file.split("-")[0], "position": list(map(float, position)), "orientation": Rotation.from_matrix(R).as_quat().tolist(), "extents": list(map(float, extents))}
    if reconstruction:
        entry["reconstruction"] = reconstruction
    return json.dumps(entry)


WITH_MESH = {"00015", "00340", "00517", "00591", "00595", "00675"}


@pytest.fixture(scope="module")
def predictions(redwood75_dir, tmp_path_factory) -> Path:
    """Truth everywhere except: 00340 (mug) moved 1.5 cm along camera x, no reconstruction; 00345 (mug)
    turned 90 degrees about its y axis; 00595 (bowl, symmetric) turned 90 degrees about y (still right);
    00517 (bottle): first frame NaN position, second frame missing. Reconstructions (the true mesh's
    vertices) for the other sequences with a mesh."""
    folder = tmp_path_factory.mktemp("predictions")
    for sequence in WITH_MESH - {"00340"}:
        np.save(folder / f"{sequence}.npy", _mesh_points(redwood75_dir, sequence))
    turn = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    lines, seen = [], {}
    for (sequence, rgb), t in _truth(redwood75_dir).items():
        index = seen[sequence] = seen.get(sequence, -1) + 1
        position, R = t["position"].copy(), t["R"]
        recon = f"{sequence}.npy" if sequence in WITH_MESH - {"00340"} else None
        if sequence == "00340":
            position = position + [0.015, 0.0, 0.0]
        if sequence in ("00345", "00595"):
            R = R @ turn
        if sequence == "00517" and index == 0:
            position[1] = float("nan")
        if sequence == "00517" and index == 1:
            continue
        lines.append(_line(sequence, rgb, position, R, t["extents"], recon))
    path = folder / "predictions.jsonl"
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(argv) -> int:
    return run_cli(main, [*argv, "--quiet"])


@pytest.mark.slow  # about 10 s on the loaded 2-core machine
def test_end_to_end_numbers(redwood75_dir, predictions, tmp_path):
    out = tmp_path / "out"
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump({"surface_samples": 3000, "seed": 1}))
    assert _run(["--dataset", str(redwood75_dir), "--method", f"mine={predictions}", "--out", str(out), "--config", str(config)]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["dataset"] == "redwood75"
    mine = results["methods"]["mine"]
    assert mine["samples"] == 75
    anns = json.loads((redwood75_dir / "annotations.json").read_text())["00517"]["pose_anns"]
    nan_frame, missing_frame = (a["rgb_file"].split("-")[0] for a in anns[:2])
    failed = {(f["sequence"], f["frame"]): f["reason"] for f in mine["failed"]}
    assert set(failed) == {("00517", nan_frame), ("00517", missing_frame)}
    assert failed[("00517", missing_frame)] == "no prediction"
    assert "position is not finite" in failed[("00517", nan_frame)]
    # hand counts (see the fixture): 75 samples; 30 with a mesh
    expected = [
        ({"position": 0.02, "degrees": 10.0, "iou": None, "fscore": None}, 68 / 75, {"mug": 20 / 25, "bottle": 23 / 25, "bowl": 1.0}),
        ({"position": 0.01, "degrees": 5.0, "iou": None, "fscore": None}, 63 / 75, {"mug": 15 / 25, "bottle": 23 / 25, "bowl": 1.0}),
        ({"position": 0.02, "degrees": 10.0, "iou": None, "fscore": 0.6}, 23 / 30, {"mug": 5 / 10, "bottle": 8 / 10, "bowl": 1.0}),
        ({"position": 0.01, "degrees": 5.0, "iou": None, "fscore": 0.8}, 23 / 30, {"mug": 5 / 10, "bottle": 8 / 10, "bowl": 1.0}),
    ]
    assert len(mine["precision"]) == 4
    for entry, (thresholds, overall, per_category) in zip(mine["precision"], expected):
        assert {k: entry[k] for k in thresholds} == thresholds
        assert entry["overall"] == pytest.approx(overall, abs=1e-12)
        assert entry["per_category"] == pytest.approx(per_category, abs=1e-12)
        assert set(entry) == {"position", "degrees", "iou", "fscore", "overall", "per_category"}

    # tables: Markdown with the percentages, CSV that parses back to the same numbers
    markdown = (out / "table.md").read_text()
    assert "| mine | 90.7 | 84.0 | 76.7 | 76.7 | 2 / 75 |" in markdown
    assert "| mug | mine | 80.0 | 60.0 | 50.0 | 50.0 |" in markdown
    rows = list(csv.DictReader((out / "table.csv").open()))
    overall = {r["label"]: float(r["precision"]) for r in rows if r["category"] == "all"}
    assert overall["10°, 2 cm"] == pytest.approx(68 / 75) and overall["5°, 1 cm, F ≥ 0.8"] == pytest.approx(23 / 30)
    assert len(rows) == 4 * (1 + 3)
    # per-sample errors
    errors = list(csv.DictReader((out / "errors.csv").open()))
    assert len(errors) == 75
    by_sample = {(r["sequence"], r["frame"]): r for r in errors}
    moved = [r for r in errors if r["sequence"] == "00340"]
    assert all(float(r["translation"]) == pytest.approx(0.015, abs=1e-9) and float(r["rotation"]) < 1e-3 for r in moved)
    assert all(r["fscore"] == "" for r in moved)  # no reconstruction
    turned_mug = [r for r in errors if r["sequence"] == "00345"]
    assert all(float(r["rotation"]) == pytest.approx(90.0, abs=1e-4) for r in turned_mug)
    turned_bowl = [r for r in errors if r["sequence"] == "00595"]
    assert all(float(r["rotation"]) < 1e-3 and float(r["iou"]) > 0.999 and float(r["fscore"]) > 0.9 for r in turned_bowl)
    exact = [r for r in errors if r["sequence"] == "00015"]
    assert all(float(r["iou"]) == pytest.approx(1.0, abs=1e-6) and float(r["fscore"]) > 0.9 for r in exact)
    assert by_sample[("00517", missing_frame)]["failure"] == "no prediction"
    assert sum(1 for r in errors if r["failure"]) == 2
    # the plot is a PNG of the Fig. 5 layout
    with Image.open(out / "precision_curves.png") as image:
        assert image.format == "PNG" and image.size[0] > 3 * image.size[1]
    curves = json.loads((out / "curves.json").read_text())["methods"]["mine"]
    assert curves["position"]["thresholds"][:3] == [0.0, 0.005, 0.01]
    assert curves["position"]["overall"][4] == pytest.approx(73 / 75)  # position alone at 2 cm: only the 2 failed fail
    assert curves["position"]["overall"][2] == pytest.approx(68 / 75)  # at 1 cm, 00340 (moved 1.5 cm) fails too
    assert curves["fscore"]["overall"][0] == pytest.approx(23 / 30)  # F >= 0 over the 30 with a mesh: not 00340 (no reconstruction), not the 2 failed
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left behind


def test_oracle_exact_and_noisy(redwood75_dir, tmp_path):
    """A small dataset (two sequences, one with a mesh): the exact oracle is right everywhere; a 1.5 cm
    shift passes (10 deg, 2 cm) and fails (5 deg, 1 cm); a 7 degree turn likewise."""
    raw = json.loads((redwood75_dir / "annotations.json").read_text())
    small = tmp_path / "small"
    small.mkdir()
    (small / "annotations.json").write_text(json.dumps({k: raw[k] for k in ("00517", "00694")}))
    (small / "00517.obj").symlink_to(redwood75_dir / "meshes" / "00517.obj")
    config = tmp_path / "config.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "dataset": "small",
                "out": "out",
                "surface_samples": 2000,
                "methods": [
                    "oracle",
                    {"name": "shifted", "spec": "oracle", "config": {"position_error": 0.015}},
                    {"name": "turned", "spec": "oracle", "config": {"rotation_error": 7.0, "seed": 5}},
                ],
                "thresholds": [{"position": 0.02, "degrees": 10}, {"position": 0.01, "degrees": 5}, {"iou": 0.9}, {"fscore": 0.99}],
            }
        )
    )
    assert _run(["--config", str(config)]) == 0
    results = json.loads((tmp_path / "out" / "results.json").read_text())["methods"]
    exact = results["oracle"]
    assert [p["overall"] for p in exact["precision"]] == [1.0, 1.0, 1.0, 1.0]
    assert [p["per_category"] for p in exact["precision"][:3]] == [{"bottle": 1.0, "bowl": 1.0}] * 3
    assert exact["failed"] == [] and exact["samples"] == 10
    assert [p["overall"] for p in results["shifted"]["precision"][:2]] == [1.0, 0.0]
    assert [p["overall"] for p in results["turned"]["precision"][:2]] == [1.0, 0.0]
    # the symmetric IoU of boxes 1.5 cm apart is below 1; F-score counts only 00517, which has a mesh
    assert results["shifted"]["precision"][2]["overall"] < 1.0
    assert exact["precision"][3]["per_category"] == {"bottle": 1.0, "bowl": None}
    errors = list(csv.DictReader((tmp_path / "out" / "errors.csv").open()))
    assert all(float(r["chamfer"]) < 1e-12 for r in errors if r["method"] == "oracle" and r["has_mesh"] == "1")


def _error_line(capsys, argv) -> str:
    with pytest.raises(SystemExit) as info:
        _run(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    return err


@pytest.mark.parametrize(
    "text, message",
    [
        ("dataset: [unclosed", "malformed YAML"),
        ("- just\n- a list\n", "config must be a mapping"),
        ("datset: x\n", "unknown config keys ['datset']"),
        ("thresholds: [{position: -1}]\n", "must be non-negative"),
        ("thresholds: [{degree: 5}]\n", "unknown keys ['degree']"),
        ("surface_samples: 0\n", "positive integer"),
        ("methods: []\n", "non-empty list"),
        ("fscore_threshold: .nan\n", "finite number"),
    ],
)
def test_bad_config_is_one_line(capsys, tmp_path, redwood75_dir, text, message):
    config = tmp_path / "bad.yaml"
    config.write_text(text)
    err = _error_line(capsys, ["--config", str(config), "--dataset", str(redwood75_dir), "--out", str(tmp_path / "o"), "--method", "oracle"])
    assert message in err and "bad.yaml" in err


def test_bad_command_lines(capsys, tmp_path, redwood75_dir):
    out = str(tmp_path / "o")
    assert "needs the RGB-D frames: give --frames" in _error_line(capsys, ["--dataset", str(redwood75_dir), "--method", "box", "--out", out])
    assert "no method" in _error_line(capsys, ["--dataset", str(redwood75_dir), "--out", out])
    assert "no dataset" in _error_line(capsys, ["--method", "oracle", "--out", out])
    assert "not a dataset folder" in _error_line(capsys, ["--dataset", str(tmp_path), "--method", "oracle", "--out", out])
    assert "predictions file not found" in _error_line(capsys, ["--dataset", str(redwood75_dir), "--method", f"x={tmp_path / 'none.jsonl'}", "--out", out])
    assert "two methods are named 'oracle'" in _error_line(capsys, ["--dataset", str(redwood75_dir), "--method", "oracle", "--method", "oracle", "--out", out])
    assert not (tmp_path / "o").exists()
    (tmp_path / "file").write_text("not a folder")
    assert "not a folder" in _error_line(capsys, ["--dataset", str(redwood75_dir), "--method", "oracle", "--out", str(tmp_path / "file")])


def test_console_entry_exit_code(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("seed: -3\n")
    run = subprocess.run([sys.executable, "-c", "from evaluate.cli import entry; entry()", "--config", str(bad)], capture_output=True, text=True, cwd=REPO)
    assert run.returncode == 2
    assert run.stderr.strip().count("\n") == 0 and "bad.yaml" in run.stderr and "seed" in run.stderr


CALLS: list = []


class Recorder(Method):
    """Stands in for a method run here: records what it was given, answers the masked points' centroid."""

    def __init__(self, config=None):
        self.config = config

    def inference(self, color, depth, mask, category, camera):
        CALLS.append((color, depth, mask, category, camera))
        points, _ = camera.backproject(depth, mask)
        return Prediction(points.mean(axis=0), [0, 0, 0, 1], [0.1, 0.1, 0.1])


@pytest.mark.slow  # about 10 s on the loaded 2-core machine
def test_methods_run_here_on_frames(redwood75_dir, tmp_path):
    """Frames in both layouts (ours for 00517, cpas_toolbox's for 00595): the method gets the colour
    image, the depth in metres and the instance mask of the visible object (the posed true mesh,
    rendered here in front of a wall at 2 m)."""
    from evaluate.datasets.masks import render_depth
    from evaluate.datasets.redwood75 import Redwood75Dataset

    raw = json.loads((redwood75_dir / "annotations.json").read_text())
    small = tmp_path / "small"
    small.mkdir()
    (small / "annotations.json").write_text(json.dumps({k: raw[k] for k in ("00517", "00595")}))
    for k in ("00517", "00595"):
        (small / f"{k}.obj").symlink_to(redwood75_dir / "meshes" / f"{k}.obj")
    frames = tmp_path / "frames"
    data = Redwood75Dataset(small)
    expected = {}
    for i, sample in enumerate(data):
        mesh = data.mesh(sample)
        ann = next(a for a in raw[sample.sequence]["pose_anns"] if a["rgb_file"].startswith(sample.frame))
        seq = frames / sample.sequence if sample.sequence == "00517" else frames / "bowl" / "rgbd" / sample.sequence
        (seq / "rgb").mkdir(parents=True, exist_ok=True)
        (seq / "depth").mkdir(parents=True, exist_ok=True)
        rendered = render_depth(np.asarray(mesh.vertices) @ sample.pose[:3, :3].T + sample.position, mesh.faces, sample.camera)
        depth_mm = np.where(rendered > 0, np.round(rendered * 1000), 2000).astype(np.uint16)
        Image.fromarray(depth_mm).save(seq / "depth" / ann["depth_file"])
        Image.fromarray(np.full((480, 640, 3), 10 * i, np.uint8)).save(seq / "rgb" / ann["rgb_file"])
        expected[10 * i] = depth_mm < 2000
    CALLS.clear()
    out = tmp_path / "out"
    # --workers 1: the methods run in this process (by default on local processes, whose calls this list would not see)
    assert _run(["--dataset", str(small), "--frames", str(frames), "--method", f"rec={__name__}:Recorder", "--method", "box", "--out", str(out), "--surface-samples", "500",
                 "--workers", "1"]) == 0
    assert len(CALLS) == 10
    for color, depth, mask, category, camera in CALLS:
        shade = int(color[0, 0, 0])
        assert color.shape == (480, 640, 3) and color.dtype == np.uint8
        assert depth.dtype == np.float32 and float(depth[0, 0]) == pytest.approx(2.0)
        assert category in ("bottle", "bowl")
        # the mask is the object's pixels (those nearer than the wall), but for the mesh's silhouette
        # edge, where the rounded depth can still be within 1 cm of the wall
        silhouette = expected[shade]
        assert (mask & ~silhouette).sum() == 0
        assert mask.sum() >= 0.98 * silhouette.sum()
    results = json.loads((out / "results.json").read_text())["methods"]
    assert results["rec"]["samples"] == 10 and results["rec"]["failed"] == []
    assert results["box"]["samples"] == 10
    errors = [r for r in csv.DictReader((out / "errors.csv").open()) if r["method"] == "rec"]
    # the visible surface's centroid lies within the object's box: within half its diagonal of the centre
    for r in errors:
        sample = next(s for s in data if s.frame == r["frame"] and s.sequence == r["sequence"])
        assert 0 < float(r["translation"]) < np.linalg.norm(sample.extents) / 2


@pytest.mark.slow  # about 10 s on the loaded 2-core machine
def test_correctness_agrees_with_cpas_toolbox(redwood75_dir, tmp_path):
    """Per sample, our correctness at the paper's thresholds equals cpas_toolbox's correct_thresh on the
    same predictions and the same posed surface points, for mugs (no symmetry: where cpas_toolbox's
    rotation error is right). Noisy oracles put errors on both sides of every threshold."""
    cpas_metrics = pytest.importorskip("cpas_toolbox.metrics")
    from evaluate.datasets.redwood75 import Redwood75Dataset
    from evaluate.metrics import ShapeIndex, sample_surface
    from evaluate.methods.oracle import OracleMethod

    raw = json.loads((redwood75_dir / "annotations.json").read_text())
    small = tmp_path / "mugs"
    small.mkdir()
    (small / "annotations.json").write_text(json.dumps({k: raw[k] for k in ("00015", "00340")}))
    for k in ("00015", "00340"):
        (small / f"{k}.obj").symlink_to(redwood75_dir / "meshes" / f"{k}.obj")
    n, seed = 1500, 4
    noises = {f"n{s}": {"position_noise": 0.006, "rotation_noise": 4.0, "extents_noise": 0.05, "seed": s} for s in range(3)}
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump({"dataset": "mugs", "out": "out", "surface_samples": n, "seed": seed, "methods": [{"name": k, "spec": "oracle", "config": v} for k, v in noises.items()]}))
    assert _run(["--config", str(config)]) == 0
    ours = {(r["method"], r["sequence"], r["frame"]): r for r in csv.DictReader((tmp_path / "out" / "errors.csv").open())}
    thresholds = [(0.02, 10, None), (0.01, 5, None), (0.02, 10, 0.6), (0.01, 5, 0.8)]
    data = Redwood75Dataset(small)
    agreements, outcomes = 0, set()
    for name, options in noises.items():
        oracle = OracleMethod(options, data, name)
        for sample in data:
            p = oracle.predict(sample)
            gt_points = ShapeIndex.from_mesh(data.mesh(sample), n, seed).points @ quat_matrix(sample.orientation).T + sample.position
            pred_points = sample_surface(p.reconstruction, n, seed) @ quat_matrix(p.orientation).T + p.position
            row = ours[(name, sample.sequence, sample.frame)]
            for position, degrees, f in thresholds:
                theirs = cpas_metrics.correct_thresh(
                    sample.position, p.position, Rotation.from_quat(sample.orientation), Rotation.from_quat(p.orientation),
                    points_gt=gt_points, points_prediction=pred_points,
                    position_threshold=position, degree_threshold=degrees, fscore_threshold=f,
                )
                mine = float(row["translation"]) <= position and float(row["rotation"]) <= degrees and (f is None or float(row["fscore"]) >= f)
                assert mine == bool(theirs), (name, sample.label, position, degrees, f, row)
                agreements += 1
                outcomes.add(mine)
    assert agreements == 3 * 10 * 4 and outcomes == {True, False}


def quat_matrix(q) -> np.ndarray:
    return Rotation.from_quat(q).as_matrix()
