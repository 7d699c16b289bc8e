"""The shared session: new documents, frame statuses, edits saved atomically, undo/redo, reopening."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from test_app_fixtures import make_sequence

from annotate.app_state import DEFAULT_BOX_SIZE, AppState, frame_status
from sequences.annotation import FramePose, load_annotation
from sequences.errors import InputError
from sequences.reader import open_sequence


@pytest.fixture(scope="module")
def sequence_root(tmp_path_factory):
    root, _ = make_sequence(tmp_path_factory.mktemp("state") / "box_seq", frames=4)
    return root


@pytest.fixture
def seq(sequence_root, tmp_path):
    # a fresh copy per test: each test writes its own document next to it
    import shutil

    root = tmp_path / "box_seq"
    shutil.copytree(sequence_root, root)
    return open_sequence(root)


def test_new_document_is_not_written_until_the_first_change(seq):
    state = AppState(seq)
    path = seq.root / "annotation.yaml"
    assert state.is_new and not path.exists()
    assert state.annotation.sequence == "box_seq"
    np.testing.assert_allclose(state.annotation.extents, [DEFAULT_BOX_SIZE] * 3)
    pose, own = state.pose()
    assert not own
    # the default box sits on the optical axis at the median depth of the centre pixels
    depth = seq.depth(0)
    v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]]
    near_centre = (np.abs(v - 239.5) <= 20) & (np.abs(u - 319.5) <= 20)
    centre = depth[near_centre]
    assert pose.position[2] == pytest.approx(float(np.median(centre[centre > 0])), abs=1e-6)
    assert pose.position[:2] == pytest.approx([0.0, 0.0])
    # upright: object +y is camera -y (up in the image), object -z (the handle side) towards the camera
    R = pose.matrix[:3, :3]
    np.testing.assert_allclose(R[:, 1], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 2], [0, 0, 1], atol=1e-12)
    state.set_pose(pose.position, pose.orientation)
    assert path.exists() and not state.is_new
    saved = load_annotation(path)
    np.testing.assert_allclose(saved.frames["0000001"].position, pose.position)


def test_every_change_is_saved_with_a_backup_and_reopening_restores(seq):
    state = AppState(seq)
    state.set_pose([0.01, 0.02, 0.7], [0, 0, 0, 1])
    state.set_extents([0.05, 0.06, 0.07])
    state.set_frame(2)
    state.set_pose([0.03, 0.0, 0.8], [0, 1, 0, 0], source="refined")
    path = state.path
    assert state.saves == 3
    backup = path.with_name(path.name + ".bak")
    assert backup.exists()
    # the backup holds the previous version: the extents change, without frame 3's pose
    previous = yaml.safe_load(backup.read_text())
    assert previous["extents"] == [0.05, 0.06, 0.07]
    assert set(previous["frames"]) == {"0000001"}
    # no temporary file is left behind by the atomic writes
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]
    reopened = AppState(seq)
    assert not reopened.is_new
    np.testing.assert_allclose(reopened.annotation.extents, [0.05, 0.06, 0.07])
    assert reopened.annotation.frames["0000003"].source == "refined"
    np.testing.assert_allclose(reopened.annotation.frames["0000001"].position, [0.01, 0.02, 0.7])


def test_undo_and_redo_walk_the_history_and_save(seq):
    state = AppState(seq)
    state.set_extents([0.05, 0.05, 0.05])
    state.set_extents([0.07, 0.07, 0.07])
    assert state.undo()
    np.testing.assert_allclose(load_annotation(state.path).extents, [0.05] * 3)
    assert state.undo()
    np.testing.assert_allclose(state.annotation.extents, [DEFAULT_BOX_SIZE] * 3)
    assert not state.undo()  # nothing left
    assert state.redo() and state.redo()
    np.testing.assert_allclose(load_annotation(state.path).extents, [0.07] * 3)
    assert not state.redo()
    state.undo()
    state.set_extents([0.09, 0.09, 0.09])  # a new change drops the redo branch
    assert not state.redo()


def test_frames_without_a_pose_show_the_nearest_posed_frame(seq):
    state = AppState(seq)
    state.set_frame(3)
    state.set_pose([0.1, 0.0, 0.9], [0, 0, 0, 1])
    state.set_frame(0)
    state.set_pose([-0.1, 0.0, 0.6], [0, 0, 0, 1])
    state.set_frame(2)
    pose, own = state.pose()
    assert not own and pose.position[0] == pytest.approx(0.1)  # index 3 is nearer than 0
    state.set_frame(1)
    assert state.pose()[0].position[0] == pytest.approx(-0.1)


def test_statuses_and_next_flagged(seq):
    state = AppState(seq)
    ids = seq.ids

    def change(doc):
        doc.frames[ids[0]] = FramePose(np.zeros(3) + 0.5, np.array([0, 0, 0, 1.0]), "manual")
        doc.frames[ids[1]] = FramePose(np.zeros(3) + 0.5, np.array([0, 0, 0, 1.0]), "tracked", {"flagged": True, "flag_reason": "low fitness"})
        doc.frames[ids[2]] = FramePose(np.zeros(3) + 0.5, np.array([0, 0, 0, 1.0]), "refined")

    state.edit(change)
    assert state.statuses() == ["manual", "flagged", "refined", "none"]
    assert state.next_flagged() == 1
    state.set_frame(1)
    assert state.next_flagged() == 1  # wraps around to itself when it is the only one
    state.annotation.frames[ids[1]].extra["reviewed"] = "accepted"
    assert frame_status(state.annotation, ids[1]) == "tracked"
    assert state.next_flagged() is None


def test_set_frame_clamps_and_notifies(seq):
    state = AppState(seq)
    seen = []
    state.subscribe(seen.append)
    state.set_frame(99)
    assert state.frame == 3 and seen == ["frame"]
    state.step(-10)
    assert state.frame == 0
    state.set_frame(0)  # no change, no redraw
    assert seen == ["frame", "frame"]


def test_bad_inputs_are_refused(seq):
    state = AppState(seq)
    with pytest.raises(ValueError):
        state.set_extents([0.1, 0.0, 0.1])
    with pytest.raises(ValueError):
        state.set_pose([np.nan, 0, 1], [0, 0, 0, 1])
    assert state.saves == 0 and not state.path.exists()
    path = seq.root / "annotation.yaml"
    path.write_text("sequence: x\nextents: [0.1, 0.1]\n")
    with pytest.raises(InputError, match="extents"):
        AppState(seq)
    path.write_text("frames:\n  '9999999': {position: [0, 0, 1], orientation: [0, 0, 0, 1]}\n")
    with pytest.raises(InputError, match="not in the sequence"):
        AppState(seq)
    with pytest.raises(InputError, match="does not exist"):
        AppState(seq, seq.root / "missing_folder" / "doc.yaml")


def test_a_failed_save_keeps_the_previous_file_and_session(seq, monkeypatch):
    import os

    state = AppState(seq)
    state.set_extents([0.05, 0.05, 0.05])
    on_disk = state.path.read_text()

    def crash(*args, **kwargs):  # the rename of the atomic write never happens (a kill, a full disk)
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError):
        state.set_extents([0.07, 0.07, 0.07])
    with pytest.raises(OSError):
        state.undo()
    assert state.path.read_text() == on_disk
    np.testing.assert_allclose(state.annotation.extents, [0.05] * 3)
    assert len(state.undo_stack) == 1 and not state.redo_stack
    assert not [p for p in state.path.parent.iterdir() if p.name.endswith(".tmp")]
    monkeypatch.undo()
    assert state.undo()
    np.testing.assert_allclose(load_annotation(state.path).extents, [DEFAULT_BOX_SIZE] * 3)


def test_a_kill_during_saves_leaves_a_valid_document_and_backup(seq):
    """SIGKILL a process that saves as fast as it can: the document and its backup both load."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    script = (
        "import sys, numpy as np\n"
        "from annotate.app_state import AppState\n"
        "from sequences.reader import open_sequence\n"
        "state = AppState(open_sequence(sys.argv[1]))\n"
        "k = 0\n"
        "while True:\n"
        "    k += 1\n"
        "    state.set_pose([0.001 * k, 0.0, 0.7], [0, 0, 0, 1])\n"
        "    if k == 5: print('saving', flush=True)\n"
    )
    repo = Path(__file__).resolve().parents[1]
    process = subprocess.Popen([sys.executable, "-c", script, str(seq.root)], cwd=repo, stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout.readline().strip() == "saving"
        time.sleep(0.5)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    path = seq.root / "annotation.yaml"
    document = load_annotation(path)
    backup = load_annotation(path.with_name(path.name + ".bak"))
    x, x_backup = document.frames["0000001"].position[0], backup.frames["0000001"].position[0]
    assert x >= 0.005 and x_backup >= 0.004 and x_backup <= x


def test_panels_read_a_copy_of_the_document_under_the_lock(seq):
    """document() is a copy taken under the state's lock (a panel's edits to it change nothing); has_pose follows
    the frames; a read waits while another thread holds the lock (an edit in progress)."""
    import threading

    state = AppState(seq)
    assert not state.has_pose() and not state.has_pose(seq.ids[1])
    state.set_pose([0.0, 0.0, 0.6], [0.0, 0.0, 0.0, 1.0])
    assert state.has_pose() and state.has_pose(seq.ids[0]) and not state.has_pose(seq.ids[1])
    copy = state.document()
    copy.frames.clear()
    copy.extents[:] = 1.0
    assert state.has_pose() and not np.allclose(state.annotation.extents, 1.0)
    held, read = threading.Event(), []
    with state.lock:
        reader = threading.Thread(target=lambda: (held.set(), read.append(state.document())))
        reader.start()
        held.wait()
        reader.join(0.2)
        assert reader.is_alive() and not read  # blocked until the lock is let go
    reader.join(2.0)
    assert len(read) == 1 and set(read[0].frames) == {seq.ids[0]}


def test_one_side_of_the_box_changes_alone(seq):
    """set_extent changes one side as one undoable step and keeps the others as the document holds them then."""
    state = AppState(seq)
    state.set_extents([0.1, 0.2, 0.3])
    state.edit(lambda doc: setattr(doc, "extents", np.array([0.1, 0.25, 0.3])))  # another tab's change
    state.set_extent(0, 0.12)
    np.testing.assert_allclose(state.annotation.extents, [0.12, 0.25, 0.3])
    assert state.undo() and np.allclose(state.annotation.extents, [0.1, 0.25, 0.3])
    with pytest.raises(ValueError):
        state.set_extent(3, 0.1)
    with pytest.raises(ValueError):
        state.set_extent(1, -0.1)
