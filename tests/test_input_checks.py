"""Every input checked where it is read, the same way in every command (issue 45, items 3 and 6): documents that
duplicate keys, alias or nest too deep; implausible cameras and depth scales; boxes behind the camera, extents out
of range, frames the sequence lacks; methods whose code fails. Each ends in one line and exit 2, or a failed sample."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from test_reconstruct_scenes import write_scene

from sequences.annotation import annotation_from_dict, load_annotation
from sequences.camera import Camera
from sequences.documents import load_document
from sequences.errors import InputError
from sequences.reader import open_sequence

REPO = Path(__file__).resolve().parents[1]


def _cli(module: str, *args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    code = f"import sys; from {module} import entry; sys.argv[0] = {module.split('.')[0]!r}; entry()"
    return subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def _one_line(result: subprocess.CompletedProcess, problem: str) -> None:
    # one error line (reconstruct-sequence adds a count of the sequences written), no traceback
    lines = [line for line in result.stderr.strip().splitlines() if line.startswith("error: ")]
    assert result.returncode == 2, result.stderr[-800:]
    assert len(lines) == 1 and problem in lines[0] and "Traceback" not in result.stderr, result.stderr[-800:]


# ------------------------------------------------------------------------------------------------ documents

@pytest.mark.parametrize("text, problem", [
    ("category: mug\ncategory: bowl\n", "duplicate key 'category'"),
    ('frames:\n  "0000001": {position: [0, 0, 1], orientation: [0, 0, 0, 1]}\n  "0000001": {position: [0, 0, 2], orientation: [0, 0, 0, 1]}\n', "duplicate key"),
    ("x: " + "[" * 50_000 + "]" * 50_000 + "\n", "nesting deeper"),
])
def test_yaml_documents_refuse_what_no_document_needs(tmp_path, text, problem):
    path = tmp_path / "annotation.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=problem):
        load_annotation(path)
    with pytest.raises(InputError, match=problem):
        load_document(path, "config")


def test_an_anchor_bomb_is_refused_at_once(tmp_path):
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"] + [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}]" for i in range(1, 12)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="aliases expand"):
        load_document(path, "config")
    path.write_text("a: &a [1, 2]\nb: *a\n")  # an alias as PyYAML's dumper writes for a shared list: fine
    assert load_document(path, "config") == {"a": [1, 2], "b": [1, 2]}


@pytest.mark.parametrize("text, problem", [('{"a": 1, "a": 2}', "duplicate key"), ("[" * 50_000 + "]" * 50_000, "nesting deeper")])
def test_json_documents_too(tmp_path, text, problem):
    path = tmp_path / "doc.json"
    path.write_text(text)
    with pytest.raises(InputError, match=problem):
        load_document(path, "document")


@pytest.mark.parametrize("change, problem", [
    ({"extents": [100.0, 0.1, 0.1]}, "extents"),
    ({"extents": [1e-9, 0.1, 0.1]}, "extents"),
    ({"frames": {"0000001": {"position": [0.0, 0.0, -0.5], "orientation": [0, 0, 0, 1]}}}, "not in front of the camera"),
])
def test_documents_out_of_range_are_refused(change, problem):
    with pytest.raises(InputError, match=problem):
        annotation_from_dict({"category": "mug", "extents": [0.1, 0.1, 0.1], **change}, "doc.yaml", "seq")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.recursive(st.none() | st.booleans() | st.floats(allow_nan=True) | st.integers() | st.text(max_size=8),
                    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4), max_leaves=30))
def test_any_document_loads_or_is_refused_in_one_line(value):
    """Generated documents: each is either an annotation or an InputError (one line), never another exception."""
    document = {"category": "mug", "frames": value} if not isinstance(value, dict) else value
    try:
        annotation_from_dict(document, "doc.yaml", "seq")
    except InputError as error:
        assert "\n" not in str(error)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.sampled_from(["fx", "fy", "cx", "cy", "width", "height", "depth_scale", "other"]),
                       st.none() | st.booleans() | st.floats(allow_nan=True, allow_infinity=True) | st.integers(-10**12, 10**12) | st.text(max_size=5), max_size=7))
def test_any_camera_file_loads_plausibly_or_is_refused(tmp_path_factory, values):
    path = tmp_path_factory.mktemp("camera") / "camera.yaml"
    path.write_text(yaml.safe_dump(values))
    try:
        camera = Camera.from_yaml(path)
    except InputError as error:
        assert "\n" not in str(error)
        return
    assert 100 <= camera.fx <= 5000 and 0 <= camera.cx <= camera.width <= 8192 and 1e-5 <= camera.depth_scale <= 0.1


# ------------------------------------------------------------------------------------------------ cameras and sequences

@pytest.mark.parametrize("values, problem", [
    ({"fx": 1e30}, "fx"), ({"fx": 1.0}, "fx"), ({"cx": 1e30}, "principal point"), ({"width": 100_000_000}, "width"),
])
def test_implausible_cameras_are_refused(tmp_path, values, problem):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(values))
    with pytest.raises(InputError, match=problem):
        Camera.from_yaml(path)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    import trimesh

    return write_scene(tmp_path_factory.mktemp("checks") / "box_0001", trimesh.creation.box([0.05, 0.08, 0.03]), n_frames=8)


def _copy(scene, tmp_path) -> Path:
    import shutil

    root = tmp_path / "box_0001"
    shutil.copytree(scene.root, root)
    return root


def test_a_depth_scale_ten_times_off_is_refused_by_every_command(scene, tmp_path):
    root = _copy(scene, tmp_path)
    camera = yaml.safe_load((root / "camera.yaml").read_text())
    camera["depth_scale"] = 0.01  # the files are millimetres: every depth reads ten times too far
    (root / "camera.yaml").write_text(yaml.safe_dump(camera))
    with pytest.raises(InputError, match="depth scale"):
        open_sequence(root).check_depth_scale()
    _one_line(_cli("reconstruct.cli", str(root), "--out", str(tmp_path / "out")), "depth scale")
    _one_line(_cli("annotate.cli", str(root), "--track"), "depth scale")
    assert not (tmp_path / "out" / "annotations.json").exists()


@pytest.mark.parametrize("damage", ["empty", "truncated", "colour"])
def test_broken_frames_are_refused_before_any_work(scene, tmp_path, damage):
    root = _copy(scene, tmp_path)
    before = (root / "annotation.yaml").read_bytes()
    if damage == "colour":
        victim = sorted((root / "rgb").iterdir())[3]
        victim.write_bytes(b"")
    else:
        victim = sorted((root / "depth").iterdir())[3]
        if damage == "empty":
            Image.fromarray(np.zeros((240, 320), np.uint16)).save(victim)
        else:
            victim.write_bytes(victim.read_bytes()[:200])
    _one_line(_cli("annotate.cli", str(root), "--track"), victim.name)
    _one_line(_cli("reconstruct.cli", str(root), "--out", str(tmp_path / "out")), victim.name)
    assert (root / "annotation.yaml").read_bytes() == before


def test_a_frame_the_sequence_lacks_is_refused(scene, tmp_path):
    root = _copy(scene, tmp_path)
    document = yaml.safe_load((root / "annotation.yaml").read_text())
    document["frames"]["0000999"] = dict(next(iter(document["frames"].values())))
    (root / "annotation.yaml").write_text(yaml.safe_dump(document))
    _one_line(_cli("reconstruct.cli", str(root), "--out", str(tmp_path / "out")), "0000999")


# ------------------------------------------------------------------------------------------------ methods

def _tiny_dataset(redwood75_dir: Path, tmp_path: Path) -> Path:
    data = json.loads((redwood75_dir / "annotations.json").read_text())
    name = next(iter(data))
    out = tmp_path / "dataset"
    out.mkdir()
    (out / "annotations.json").write_text(json.dumps({name: data[name]}))
    return out


@pytest.mark.parametrize("body, problem", [("raise RuntimeError('boom')", "RuntimeError: boom"), ("raise SystemExit(7)", "SystemExit: 7")])
def test_a_method_module_that_fails_to_import_ends_in_one_line(redwood75_dir, tmp_path, body, problem):
    (tmp_path / "badmethod.py").write_text(body + "\n")
    dataset = _tiny_dataset(redwood75_dir, tmp_path)
    result = _cli("evaluate.cli", "--dataset", str(dataset), "--method", "bad=badmethod:Method", "--out", str(tmp_path / "out"), cwd=tmp_path)
    _one_line(result, problem)


def test_a_method_that_raises_or_exits_fails_its_samples(redwood75_dir, tmp_path):
    (tmp_path / "flaky.py").write_text(
        "from evaluate.methods.sample_method import SampleMethod\n"
        "class Exits(SampleMethod):\n"
        "    def __init__(self, config=None):\n"
        "        pass\n"
        "    def predict(self, sample, inputs):\n"
        "        raise SystemExit(7)\n"
        "class Raises(Exits):\n"
        "    def predict(self, sample, inputs):\n"
        "        raise ZeroDivisionError('bug')\n")
    dataset = _tiny_dataset(redwood75_dir, tmp_path)
    out = tmp_path / "out"
    result = _cli("evaluate.cli", "--dataset", str(dataset), "--method", "exits=flaky:Exits", "--method", "raises=flaky:Raises",
                  "--method", "oracle", "--out", str(out), cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-800:]
    methods = json.loads((out / "results.json").read_text())["methods"]
    assert all("SystemExit" in f["reason"] for f in methods["exits"]["failed"]) and len(methods["exits"]["failed"]) == methods["exits"]["samples"]
    assert all("ZeroDivisionError: bug" in f["reason"] for f in methods["raises"]["failed"])
    assert methods["oracle"]["failed"] == []


def test_a_broken_frame_is_said_before_a_failed_import(scene, tmp_path, monkeypatch):
    from reconstruct.units import prepare

    root = _copy(scene, tmp_path)
    victim = sorted((root / "depth").iterdir())[3]
    victim.write_bytes(victim.read_bytes()[:200])
    monkeypatch.setitem(sys.modules, "open3d", None)  # its import fails while the frames are checked
    with pytest.raises(InputError, match=victim.name):
        prepare(root, None, "redwood75", ahead=True)
    victim.write_bytes((scene.root / "depth" / victim.name).read_bytes())  # mended: the import's own error then
    with pytest.raises(ImportError):
        prepare(root, None, "redwood75", ahead=True)
