"""Method interface: the registry, the predictions file (incl. malformed lines), the oracle, the cpas_toolbox adapter."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluate.datasets import Sample
from evaluate.methods import FrameMethod, Method, Prediction, PredictionFailure, get_method, is_cpas_method
from evaluate.methods.oracle import OracleMethod
from evaluate.methods.predictions import PredictionsFile
from sequences.camera import Camera
from sequences.errors import InputError


def _sample(sequence="s1", frame="0000005", category="mug", symmetry="none", seed=0) -> Sample:
    rng = np.random.default_rng(seed)
    return Sample(
        dataset="test", sequence=sequence, frame=frame, category=category, symmetry=symmetry,
        position=rng.uniform(-0.2, 0.2, 3) + [0, 0, 0.8], orientation=Rotation.random(random_state=seed).as_quat(),
        extents=[0.1, 0.12, 0.08],
    )


def _angle(q_a, q_b) -> float:
    return float(np.degrees((Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude()))


# ---------------------------------------------------------------- predictions file


def _write(path: Path, lines: list) -> Path:
    path.write_text("\n".join(line if isinstance(line, str) else json.dumps(line) for line in lines) + "\n")
    return path


def _line(sequence, frame, **extra):
    entry = {"sequence": sequence, "frame": frame, "position": [0.1, 0.2, 0.9], "orientation": [0, 0, 0, 1], "extents": [0.1, 0.1, 0.1]}
    entry.update(extra)
    return entry


def test_predictions_file_good_and_malformed(tmp_path):
    points = np.random.default_rng(1).normal(size=(50, 3)) * 0.05
    np.save(tmp_path / "cloud.npy", points)
    (tmp_path / "broken.obj").write_text("this is not a mesh\n")
    path = _write(
        tmp_path / "p.jsonl",
        [
            _line("s1", "0000005-000000134064.jpg", reconstruction="cloud.npy"),  # colour file name matches the frame id
            _line("s1", "0000006", position=[0.1, float("nan"), 0.9]),
            _line("s1", "0000007", extents=[0.1, 0.1]),
            _line("s1", "0000008", orientation=[0, 0, 0, 0.5]),
            _line("s1", "0000009"),
            _line("s1", "0000009"),
            _line("s1", "0000010", reconstruction="missing.ply"),
            _line("s1", "0000011", reconstruction="broken.obj"),
            _line("s1", "0000012", extents=[0.1, -0.1, 0.1]),
            _line("s1", "0000013", position="here"),
            _line("s1", 14, position=[1, 1, 1]),  # a frame number matches the zero-padded id
            "{not json",
            json.dumps({"position": [0, 0, 1]}),
            _line("elsewhere", "0000001"),
            "",
        ],
    )
    predictions = PredictionsFile("p", path)
    ok = predictions.predict(_sample(frame="0000005"))
    np.testing.assert_array_equal(ok.position, [0.1, 0.2, 0.9])
    np.testing.assert_array_equal(ok.reconstruction, points)
    expected = {
        "0000006": "position is not finite",
        "0000007": "extents must be a list of 3 numbers",
        "0000008": "not a unit quaternion",
        "0000009": "several predictions (lines [5, 6]",
        "0000010": "missing.ply not found",
        "0000011": "unreadable reconstruction broken.obj",
        "0000012": "extents must be positive",
        "0000013": "position must be a list of 3 numbers",
        "0000099": "no prediction",
    }
    for frame, reason in expected.items():
        with pytest.raises(PredictionFailure) as info:
            predictions.predict(_sample(frame=frame))
        assert reason in str(info.value), (frame, str(info.value))
    np.testing.assert_array_equal(predictions.predict(_sample(frame="0000014")).position, [1, 1, 1])
    assert [number for number, _ in predictions.problems] == [12, 13]
    assert predictions.unmatched([_sample(frame=f"00000{i:02d}") for i in range(5, 15)]) == [("elsewhere", "1", None)]


def test_predictions_file_instances_and_missing_file(tmp_path):
    path = _write(tmp_path / "n.jsonl", [_line("real_test/scene_1", "0000", instance=2, position=[1, 2, 3])])
    sample = _sample(sequence="real_test/scene_1", frame="0000")
    sample.instance = "2"
    np.testing.assert_array_equal(PredictionsFile("n", path).predict(sample).position, [1, 2, 3])
    sample.instance = "3"
    with pytest.raises(PredictionFailure, match="no prediction"):
        PredictionsFile("n", path).predict(sample)
    with pytest.raises(InputError, match="not found"):
        PredictionsFile("n", tmp_path / "absent.jsonl")


# ---------------------------------------------------------------- oracle


def test_oracle_exact_and_noisy():
    samples = [_sample(frame=f"{i:07d}", category=c, symmetry=s, seed=i) for i, (c, s) in enumerate([("mug", "none"), ("bowl", "y")] * 3)]
    exact = OracleMethod()
    for sample in samples:
        p = exact.predict(sample)
        np.testing.assert_array_equal(p.position, sample.position)
        assert _angle(p.orientation, sample.orientation) < 1e-6
        np.testing.assert_array_equal(p.extents, sample.extents)
    noisy = OracleMethod({"position_error": 0.03, "rotation_error": 7.0, "extents_error": 0.1, "seed": 3})
    for sample in samples:
        p = noisy.predict(sample)
        assert np.linalg.norm(p.position - sample.position) == pytest.approx(0.03)
        assert _angle(p.orientation, sample.orientation) == pytest.approx(7.0)
        # the turn is perpendicular to the symmetry axis: the y axes are 7 degrees apart too
        y_true = Rotation.from_quat(sample.orientation).apply([0, 1, 0])
        y_pred = Rotation.from_quat(p.orientation).apply([0, 1, 0])
        assert np.degrees(np.arccos(np.clip(y_true @ y_pred, -1, 1))) == pytest.approx(7.0)
        np.testing.assert_allclose(p.extents, 1.1 * sample.extents)
        # deterministic per sample, whatever the order; another seed differs
        again = OracleMethod({"position_error": 0.03, "rotation_error": 7.0, "extents_error": 0.1, "seed": 3}).predict(sample)
        np.testing.assert_array_equal(again.position, p.position)
        other = OracleMethod({"position_error": 0.03, "seed": 4}).predict(sample)
        assert not np.allclose(other.position, p.position)
    gaussian = [OracleMethod({"position_noise": 0.01, "seed": 0}).predict(s) for s in samples]
    offsets = np.array([p.position - s.position for p, s in zip(gaussian, samples)])
    assert 0.001 < offsets.std() < 0.03
    with pytest.raises(InputError, match="unknown options"):
        OracleMethod({"positon_error": 1})
    with pytest.raises(InputError, match="must not be negative"):
        OracleMethod({"rotation_error": -1})


# ---------------------------------------------------------------- registry


class PlainMethod(Method):
    """An evaluate Method returning the mask's centroid depth as a fixed-orientation box."""

    def __init__(self, config=None):
        self.config = config

    def inference(self, color, depth, mask, category, camera):
        points, _ = camera.backproject(depth, mask)
        if len(points) == 0:
            raise ValueError("no points")
        return Prediction(points.mean(axis=0), [0, 0, 0, 1], [0.1, 0.1, 0.1])


class BrokenMethod(Method):
    def __init__(self, config=None):
        pass

    def inference(self, color, depth, mask, category, camera):
        return {}["position"]


class NeedsWeights(Method):
    def __init__(self, config=None):
        raise FileNotFoundError("weights.pth not found")

    def inference(self, color, depth, mask, category, camera):
        raise AssertionError("never constructed")


class NotAMethod:
    pass


def test_registry(tmp_path):
    assert isinstance(get_method("box"), FrameMethod)
    assert get_method("box").name == "box"
    assert get_method("mine=box").name == "mine"
    oracle = get_method("truth=oracle", {"position_error": 0.01})
    assert isinstance(oracle, OracleMethod) and oracle.name == "truth" and oracle.options["position_error"] == 0.01
    _write(tmp_path / "preds.jsonl", [])
    preds = get_method("spd=preds.jsonl", base=tmp_path)
    assert isinstance(preds, PredictionsFile) and preds.name == "spd"
    plain = get_method(f"p={__name__}:PlainMethod", {"k": 1})
    assert isinstance(plain, FrameMethod) and plain.method.config == {"k": 1}
    for spec, message in [
        ("nonsense", "unknown method"),
        ("x=no_such_module_xyz:Thing", "not available"),
        (f"x={__name__}:Missing", "has no Missing"),
        (f"x={__name__}:NotAMethod", "neither"),
        (f"x={__name__}:NeedsWeights", "could not be constructed .FileNotFoundError: weights.pth not found"),
        ("bad name=box", "must be letters"),
        ("", "non-empty"),
    ]:
        with pytest.raises(InputError, match=message):
            get_method(spec)


def test_frame_method_failures_are_reported():
    class Inputs:
        color = np.zeros((480, 640, 3), np.uint8)
        depth = np.zeros((480, 640), np.float32)
        mask = np.zeros((480, 640), bool)

    method = get_method(f"p={__name__}:PlainMethod")
    with pytest.raises(PredictionFailure, match="empty instance mask"):
        method.predict(_sample(), Inputs())
    Inputs.mask = np.ones((480, 640), bool)
    with pytest.raises(PredictionFailure, match="ValueError: no points"):
        method.predict(_sample(), Inputs())
    Inputs.depth = np.ones((480, 640), np.float32)
    p = method.predict(_sample(), Inputs())
    np.testing.assert_allclose(p.position, [0, 0, 1], atol=1e-9)
    # any exception of a method is a failed sample, named in the reason
    with pytest.raises(PredictionFailure, match="KeyError"):
        get_method(f"b={__name__}:BrokenMethod").predict(_sample(), Inputs())


# ---------------------------------------------------------------- cpas_toolbox adapter


class StandInCpas:
    """A class with cpas_toolbox's CPASMethod signature: constructor (config, camera); inference on torch tensors."""

    def __init__(self, config: dict, camera) -> None:
        self.config, self.camera = config, camera
        self.calls = []

    def inference(self, color_image, depth_image, instance_mask, category_str):
        import torch

        self.calls.append((color_image, depth_image, instance_mask, category_str))
        v, u = torch.nonzero(instance_mask, as_tuple=True)
        z = depth_image[v, u]
        x = (u - self.camera.cx) / self.camera.fx * z
        y = (v - self.camera.cy) / self.camera.fy * z
        points = torch.stack([x, y, z], dim=1)
        centre = points.mean(dim=0)
        orientation = torch.tensor(self.config["orientation"], dtype=torch.float32)
        return {
            "position": centre,
            "orientation": orientation,
            "extents": torch.tensor([0.1, 0.2, 0.3]),
            "reconstructed_pointcloud": points - centre if self.config.get("points", True) else None,
            "reconstructed_mesh": None,
        }


@pytest.mark.slow  # imports torch: 13 s measured on the loaded 2-core machine
def test_cpas_adapter_runs_cpas_class_unchanged():
    torch = pytest.importorskip("torch")
    assert is_cpas_method(StandInCpas) and not is_cpas_method(PlainMethod)
    camera = Camera(fx=500.0, fy=510.0, cx=320.0, cy=240.0)
    q = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_quat()
    method = get_method(f"standin={__name__}:StandInCpas", {"orientation": q.tolist()}, camera)
    wrapped = method.method.wrapped
    assert isinstance(wrapped, StandInCpas) and (wrapped.camera.fx, wrapped.camera.fy, wrapped.camera.cx, wrapped.camera.cy) == (500.0, 510.0, 320.0, 240.0)
    assert (wrapped.camera.width, wrapped.camera.height) == (640, 480)
    try:
        from cpas_toolbox.camera_utils import Camera as CpasCamera

        assert isinstance(wrapped.camera, CpasCamera) and wrapped.camera.pixel_center == 0.0
    except ImportError:
        pass

    class Inputs:
        color = np.full((480, 640, 3), 255, np.uint8)
        depth = np.full((480, 640), 2.0, np.float32)
        mask = np.zeros((480, 640), bool)

    Inputs.mask[240, 320] = True  # the principal point: the point (0, 0, 2)
    Inputs.mask[240, 570] = True  # x = (570 - 320) / 500 * 2 = 1 m
    sample = _sample()
    sample.camera = camera
    p = method.predict(sample, Inputs())
    color, depth, mask, category = wrapped.calls[-1]
    assert color.dtype == torch.float32 and color.shape == (480, 640, 3) and float(color.max()) == 1.0
    assert depth.dtype == torch.float32 and float(depth[0, 0]) == 2.0
    assert mask.dtype == torch.bool and int(mask.sum()) == 2
    assert category == "mug"
    np.testing.assert_allclose(p.position, [0.5, 0, 2], atol=1e-6)
    np.testing.assert_allclose(p.orientation, q / np.linalg.norm(q), atol=1e-6)
    np.testing.assert_allclose(p.extents, [0.1, 0.2, 0.3], atol=1e-7)
    np.testing.assert_allclose(p.reconstruction, [[-0.5, 0, 0], [0.5, 0, 0]], atol=1e-6)
    # a NaN from the wrapped method is a failed sample, not a crash
    Inputs.depth = np.full((480, 640), np.nan, np.float32)
    with pytest.raises(PredictionFailure, match="position is not finite"):
        method.predict(sample, Inputs())


def test_reconstruction_file_formats(tmp_path):
    import trimesh

    from evaluate.methods.predictions import load_reconstruction

    box = trimesh.creation.box(extents=[0.1, 0.2, 0.3])
    box.export(tmp_path / "mesh.ply")
    box.export(tmp_path / "mesh.obj")
    points = np.random.default_rng(0).uniform(-0.05, 0.05, (20, 3))
    trimesh.PointCloud(points).export(tmp_path / "cloud.ply")
    np.savetxt(tmp_path / "cloud.xyz", points)
    for name in ("mesh.ply", "mesh.obj"):
        mesh = load_reconstruction(tmp_path / name)
        assert len(mesh.faces) == 12
        np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [0.1, 0.2, 0.3])
    for name in ("cloud.ply", "cloud.xyz"):
        np.testing.assert_allclose(load_reconstruction(tmp_path / name), points, atol=1e-7)
    np.save(tmp_path / "flat.npy", np.zeros((4, 2)))
    with pytest.raises(ValueError, match="expected \\(N, 3\\)"):
        load_reconstruction(tmp_path / "flat.npy")
