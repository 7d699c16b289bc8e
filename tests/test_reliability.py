"""Reliability (issue 45): names are never paths, one writer per document, whole exports or none, files keep the umask."""

from __future__ import annotations

import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from test_app_fixtures import make_sequence
from test_reconstruct_scenes import write_scene

from sequences.annotation import annotation_from_dict, load_annotation, save_annotation
from sequences.errors import InputError
from sequences.lock import DocumentLock, DocumentLocked, fingerprint
from sequences.names import check_name, inside, is_name, safe_name
from sequences.reader import open_sequence

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------------ names

@pytest.mark.parametrize("bad", ["../../thesis", "/home/me", "a/b", "a\\b", ".hidden", "..", "", "x" * 129, "a b", "seq\x00", "mug..1", "-rf"])
def test_unsafe_names_are_refused(bad):
    assert not is_name(bad)
    with pytest.raises(InputError, match="not a plain name"):
        check_name(bad, "sequence name", "doc.yaml")


@pytest.mark.parametrize("good", ["00015", "mug_0001", "scene-1.v2", "A+B", "0000012"])
def test_plain_names_pass(good):
    assert check_name(good, "sequence name", None) == good


def test_folder_names_are_made_plain():
    assert safe_name("my seq (2)") == "my_seq__2" and safe_name("..") == "sequence" and safe_name("ok-1") == "ok-1"


def test_inside_refuses_escapes_and_symlinks(tmp_path):
    root = tmp_path / "out"
    root.mkdir()
    (tmp_path / "elsewhere").mkdir()
    (root / "link").symlink_to(tmp_path / "elsewhere")
    assert inside(root, "a", "b.obj") == root / "a" / "b.obj"
    for parts in (("..", "x"), ("/etc", "passwd"), ("link", "f.obj")):
        with pytest.raises(InputError, match="outside"):
            inside(root, *parts)


@pytest.mark.parametrize("document, problem", [
    ({"sequence": "../../thesis"}, "sequence name"),
    ({"sequence": "/home/me/thesis"}, "sequence name"),
    ({"sequence": 15}, "must be text"),
    ({"frames": {"../x": {"position": [0, 0, 1], "orientation": [0, 0, 0, 1]}}}, "frame id"),
])
def test_documents_with_path_names_are_refused(document, problem):
    with pytest.raises(InputError, match=problem):
        annotation_from_dict(document, "doc.yaml", "seq")


def test_a_folder_with_spaces_names_its_document_plainly(tmp_path):
    root, _ = make_sequence(tmp_path / "my seq", frames=2)
    assert open_sequence(root).name == "my_seq"
    assert annotation_from_dict({}, root / "annotation.yaml", "my seq").sequence == "my_seq"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    base = tmp_path_factory.mktemp("reliability")
    return write_scene(base / "box_0001", trimesh.creation.box([0.05, 0.08, 0.03]), n_frames=10, category="other")


def run_cli(*args: str, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "import sys; from reconstruct.cli import entry; sys.argv[0] = 'reconstruct-sequence'; entry()", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=300, **kwargs)


def test_reconstruct_refuses_a_document_whose_name_is_a_path(scene, tmp_path):
    document = yaml.safe_load((scene.root / "annotation.yaml").read_text())
    document["sequence"] = "../../thesis"
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(document))
    (tmp_path / "thesis").mkdir()
    (tmp_path / "thesis" / "chapter1.tex").write_text("mine")
    out = tmp_path / "a" / "b" / "out"
    result = run_cli(str(scene.root), "--annotation", str(bad), "--out", str(out))
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "sequence name" in errors[0] and "bad.yaml" in errors[0]
    assert (tmp_path / "thesis" / "chapter1.tex").read_text() == "mine" and sorted(os.listdir(tmp_path / "thesis")) == ["chapter1.tex"]
    assert not (tmp_path / "a" / "thesis.obj").exists() and not (tmp_path / "a" / "masks").exists()


# ------------------------------------------------------------------------------------------------ one writer

def test_a_second_writer_is_refused_and_named(tmp_path):
    document = tmp_path / "annotation.yaml"
    with DocumentLock(document, "annotate (browser)"):
        with pytest.raises(DocumentLocked) as caught:
            DocumentLock(document, "annotate --track").acquire()
        assert f"pid {os.getpid()}" in str(caught.value) and "annotate (browser)" in str(caught.value)
    assert not (tmp_path / "annotation.yaml.lock").exists()
    DocumentLock(document, "annotate --track").acquire().release()


def test_a_killed_holders_lock_is_stale(tmp_path):
    document = tmp_path / "annotation.yaml"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from sequences.lock import DocumentLock; "
                               f"DocumentLock({str(document)!r}, 'holder').acquire(); print('held', flush=True); time.sleep(60)"],
                              cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(DocumentLocked, match=f"pid {holder.pid}"):
        DocumentLock(document, "me").acquire()
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert (tmp_path / "annotation.yaml.lock").exists()  # left behind by the kill
    lock = DocumentLock(document, "me").acquire()  # the kernel dropped the flock: stale, taken over
    assert json.loads((tmp_path / "annotation.yaml.lock").read_text())["pid"] == os.getpid()
    lock.release()


def test_track_refuses_a_locked_document(scene, tmp_path):
    root = tmp_path / "seq"
    shutil.copytree(scene.root, root)
    before = (root / "annotation.yaml").read_bytes()
    with DocumentLock(root / "annotation.yaml", "annotate (browser)"):
        result = subprocess.run([sys.executable, "-c", "import sys; from annotate.cli import entry; sys.argv[0] = 'annotate'; entry()",
                                 str(root), "--track"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "open for writing by annotate (browser)" in lines[0] and f"pid {os.getpid()}" in lines[0]
    assert (root / "annotation.yaml").read_bytes() == before


def test_browser_session_is_read_only_when_locked_and_never_overwrites_a_change(tmp_path):
    from annotate.app_state import AppState

    root, _ = make_sequence(tmp_path / "box_seq", frames=3)
    sequence = open_sequence(root)
    first = AppState(sequence)
    first.set_pose([0.0, 0.0, 0.7], [0, 0, 0, 1])
    second = AppState(sequence)  # a second server on the same document
    assert second.read_only and "annotate (browser)" in second.read_only and first.read_only is None
    with pytest.raises(InputError, match="open for writing"):
        second.set_pose([0.0, 0.0, 0.9], [0, 0, 0, 1])
    second.close()
    # another program edits the file: the session refuses to overwrite it and keeps its own version beside it
    path = root / "annotation.yaml"
    edited = path.read_text().replace("0.7", "0.75")
    path.write_text(edited)
    with pytest.raises(InputError, match="changed on disk by another program"):
        first.set_pose([0.0, 0.0, 0.8], [0, 0, 0, 1])
    assert path.read_text() == edited
    refused = list(tmp_path.glob("box_seq/annotation.refused-*.yaml"))
    assert len(refused) == 1 and load_annotation(refused[0]).frames["0000001"].position[2] == pytest.approx(0.8)
    first.close()
    assert not (root / "annotation.yaml.lock").exists()


def test_first_save_keeps_the_original_and_files_keep_the_umask(tmp_path):
    from annotate.app_state import AppState

    root, _ = make_sequence(tmp_path / "box_seq", frames=3)
    sequence = open_sequence(root)
    original = AppState(sequence)
    original.set_pose([0.0, 0.0, 0.7], [0, 0, 0, 1])
    original.close()
    before = (root / "annotation.yaml").read_bytes()
    state = AppState(sequence)
    for z in (0.71, 0.72, 0.73):
        state.set_pose([0.0, 0.0, z], [0, 0, 0, 1])
    state.close()
    assert (root / "annotation.yaml.orig").read_bytes() == before  # as the session found it
    assert load_annotation(root / "annotation.yaml.bak").frames["0000001"].position[2] == pytest.approx(0.72)
    from sequences.atomic import FILE_MODE

    for name in ("annotation.yaml", "annotation.yaml.orig", "annotation.yaml.bak"):
        assert stat.S_IMODE((root / name).stat().st_mode) == FILE_MODE
    assert FILE_MODE == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


# ------------------------------------------------------------------------------------------------ whole exports

def _state(out: Path) -> dict[str, bytes]:
    """Every visible file of an export folder (hidden staging, backups, journals and locks left out)."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(out).parts)}


def _export(out: Path, name: str, version: int) -> None:
    from reconstruct.transaction import ExportTransaction, OutLock, recover

    with OutLock(out):
        recover(out)
        transaction = ExportTransaction(out, name)
        for k in range(3):
            transaction.stage(f"masks/{name}/{k:07d}.png", f"mask {k} v{version}".encode())
        transaction.stage(f"{name}.obj", f"mesh v{version}".encode())
        transaction.stage(f"reports/{name}.json", f"report v{version}".encode())
        annotations = json.loads((out / "annotations.json").read_text()) if (out / "annotations.json").exists() else {}
        annotations[name] = {"version": version}
        transaction.commit(annotations)


@pytest.mark.parametrize("existed", [True, False])
def test_an_export_killed_at_any_step_leaves_the_old_or_the_new_export_whole(tmp_path, monkeypatch, existed):
    """A kill simulated at each rename of the swap; the next export's recovery restores the old or keeps the new."""
    import reconstruct.transaction as transaction

    reference = tmp_path / "reference"
    reference.mkdir()
    _export(reference, "other", 1)
    if existed:
        _export(reference, "seq", 1)
    old = _state(reference)
    _export(reference, "seq", 2)
    new = _state(reference)
    real_replace = os.replace
    for step in range(60):  # until the export runs through without dying: every rename and write it makes
        out = tmp_path / f"out{step}"
        out.mkdir()
        _export(out, "other", 1)
        if existed:
            _export(out, "seq", 1)
        calls = {"n": 0}

        def dying_replace(a, b, calls=calls, step=step):
            calls["n"] += 1
            if calls["n"] > step:
                raise SystemExit("killed")  # nothing after this point runs: as a SIGKILL
            return real_replace(a, b)

        monkeypatch.setattr(transaction.os, "replace", dying_replace)
        monkeypatch.setattr("sequences.atomic.os.replace", dying_replace)
        try:
            _export(out, "seq", 2)
            finished = True
        except SystemExit:
            finished = False
        monkeypatch.setattr(transaction.os, "replace", real_replace)
        monkeypatch.setattr("sequences.atomic.os.replace", real_replace)
        if finished:
            assert _state(out) == new and step >= 6
            break
        with transaction.OutLock(out):
            transaction.recover(out)  # what the next run does first
        state = _state(out)
        assert state in (old, new), (step, sorted(state))
        assert not [p for p in out.iterdir() if p.name.startswith((".staging", ".backup", ".journal"))]
    else:
        raise AssertionError("the export never ran through")


def _comparable(state: dict[str, bytes]) -> dict[str, bytes]:
    """An export's files with the reports' timings left out (they differ from run to run)."""
    out = dict(state)
    for name, data in state.items():
        if name.startswith("reports/") and name.endswith(".json"):
            report = json.loads(data)
            report.pop("timings", None)
            out[name] = json.dumps(report, sort_keys=True).encode()
    return out


@pytest.mark.slow
def test_reconstruct_killed_at_random_moments_leaves_a_whole_export(scene, tmp_path):
    """reconstruct-sequence SIGKILLed at random moments of a re-export: after the next run's recovery the export
    folder holds the previous or the new export, whole."""
    from reconstruct.transaction import OutLock, recover

    out = tmp_path / "out"
    first = run_cli(str(scene.root), "--out", str(out))
    assert first.returncode == 0, first.stderr
    old = _comparable(_state(out))
    document = load_annotation(scene.root / "annotation.yaml")
    document.extents = document.extents * 1.1  # another carving: another mesh, masks and report
    changed = tmp_path / "changed.yaml"
    save_annotation(document, changed, backup=False)
    reference = tmp_path / "reference"
    shutil.copytree(out, reference)
    assert run_cli(str(scene.root), "--annotation", str(changed), "--out", str(reference)).returncode == 0
    new = _comparable(_state(reference))
    assert new != old
    rng = np.random.default_rng(0)
    seen = set()
    for attempt in range(6):
        process = subprocess.Popen([sys.executable, "-c", "import sys; from reconstruct.cli import entry; entry()", str(scene.root),
                                    "--annotation", str(changed), "--out", str(out)], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(1.0, 6.0))
        process.send_signal(signal.SIGKILL)
        process.wait()
        with OutLock(out):
            recover(out)
        state = _comparable(_state(out))
        assert state in (old, new), attempt
        seen.add("new" if state == new else "old")
        if state == new:  # start again from the previous export
            shutil.rmtree(out)
            assert run_cli(str(scene.root), "--out", str(out)).returncode == 0
    assert seen  # (which of the two depends on when the kill came)
