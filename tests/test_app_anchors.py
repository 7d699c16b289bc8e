"""Tracking keeps what people did (issue 49 item 4): placed, refined and accepted boxes stay the anchors, each either
where it was or on the track with the person's box kept beside it; the page says what a run will keep before it runs,
and which frames it moved, by how much, after."""

from __future__ import annotations

import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import viser
from scipy.spatial.transform import Rotation
from test_app_fixtures import TRUE_EXTENTS, make_sequence

import annotate.app_tracking as app_tracking
from annotate.app import App
from annotate.app_anchors import anchors, changes_markdown, keep_markdown, pose_changes
from annotate.app_tracking import tracking_engine
from annotate.engines import anchored_pose
from sequences.annotation import Annotation, FramePose, load_annotation
from sequences.reader import open_sequence


@pytest.fixture(scope="module")
def sequence_root(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("anchors") / "box_seq", frames=5)


def _app(root, tmp_path) -> tuple[App, viser.ViserServer]:
    copy = tmp_path / "box_seq"
    shutil.copytree(root, copy)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    return App(server, open_sequence(copy)), server


def _people_and_tracker(app, poses) -> dict[str, FramePose]:
    """Frame 1 placed, frame 3 tracked and then accepted, frame 5 refined, frame 2 tracked (none of them exactly the
    truth: a run that re-poses them moves them)."""
    ids = app.sequence.ids
    turn = Rotation.from_euler("y", 2.0, degrees=True)
    near = {k: (np.asarray(poses[k][0]) + [0.002, -0.001, 0.001], (Rotation.from_quat(poses[k][1]) * turn).as_quat()) for k in range(5)}
    frames = {
        ids[0]: FramePose(*near[0], "manual"),
        ids[1]: FramePose(*near[1], "tracked", {"fitness": 0.9}),
        ids[2]: FramePose(*near[2], "tracked", {"reviewed": "accepted", "fitness": 0.4}),
        ids[4]: FramePose(*near[4], "refined", {"fitness": 0.95}),
    }
    app.state.set_extents(TRUE_EXTENTS)
    app.state.edit(lambda doc: doc.frames.update({k: FramePose(v.position.copy(), v.orientation.copy(), v.source, dict(v.extra)) for k, v in frames.items()}))
    return frames


@pytest.mark.parametrize("engine", ["chains", "graph"])
def test_a_run_keeps_placed_refined_and_accepted_boxes(engine, sequence_root, tmp_path, monkeypatch):
    monkeypatch.setenv("REDWOOD_GT_ENGINE", engine)
    if tracking_engine() is None:
        pytest.skip(f"tracking engine {engine} not importable")
    root, poses = sequence_root
    app, server = _app(root, tmp_path)
    try:
        frames = _people_and_tracker(app, poses)
        ids = app.sequence.ids
        # before the run, the page says what it keeps
        keeps = app.tracking.keeps.content
        assert "keeps 3 boxes" in keeps and "1 (placed)" in keeps and "3 (accepted)" in keeps and "5 (refined)" in keeps, keeps
        assert app.tracking.start_tracking(0, len(ids) - 1, wait=True)
        doc = load_annotation(app.state.path)
        for frame_id in (ids[0], ids[2], ids[4]):
            kept = doc.frames[frame_id]
            # the person's box: the pose itself, or kept beside the pose on the track (within 2 placement sigmas)
            np.testing.assert_allclose(kept.placed_matrix, frames[frame_id].matrix, atol=1e-9)
            if "placed" not in kept.extra:
                np.testing.assert_array_equal(kept.position, frames[frame_id].position)
            else:
                assert kept.extra["manual_correction_deg"] <= 6.0 and kept.extra["manual_correction_m"] <= 0.012
            assert kept.source == frames[frame_id].source
        assert doc.frames[ids[2]].extra["reviewed"] == "accepted"
        assert doc.frames[ids[1]].source == "tracked" and doc.frames[ids[3]].source == "tracked"
        # after it, which frames moved and by how much; frame 4 had no pose: a first pose
        changes = app.tracking.changes.content
        assert changes.startswith("Last run: ") and "1 frame got a first pose" in changes, changes
        if "moved" in changes:
            assert "2: " in changes and "°" in changes and " mm" in changes
        assert "The 3 boxes placed, refined or accepted stay the anchors" in app.message.content
    finally:
        app.close()
        server.stop()


def test_anchors_come_back_whatever_the_engine_does_and_edits_made_meanwhile_stay(sequence_root, tmp_path, monkeypatch):
    """An engine that re-poses every frame (anchors too), while the annotator fixes frame 2 during the run: the anchors
    and the fix stay, the rest takes the engine's poses, and the page lists the moves in degrees and millimetres."""
    root, poses = sequence_root
    app, server = _app(root, tmp_path)
    try:
        frames = _people_and_tracker(app, poses)
        ids = app.sequence.ids
        fix = (np.array([0.0, 0.0, 0.7]), np.array([0.0, 0.0, 0.0, 1.0]))
        seen = {}

        def track_sequence(sequence, annotation, frames=None, progress=None, config=None):
            seen["sources"] = {f: p.source for f, p in annotation.frames.items()}
            app.state.set_frame(1)
            app.commit_box(*fix)  # the annotator, meanwhile
            out = annotation.copy()
            shift = Rotation.from_euler("z", 3.0, degrees=True)
            for frame_id in frames:
                base = annotation.frames.get(frame_id) or FramePose(np.array([0, 0, 0.7]), np.array([0, 0, 0, 1.0]))
                out.frames[frame_id] = FramePose(base.position + [0.01, 0, 0], (shift * Rotation.from_quat(base.orientation)).as_quat(), "tracked", {"fitness": 0.8})
            return out

        monkeypatch.setattr(app_tracking, "tracking_engine", lambda: SimpleNamespace(track_sequence=track_sequence, refine_frame=None))
        assert app.tracking.start_tracking(0, len(ids) - 1, wait=True)
        # the engine saw every kept box as placed (an engine that anchors placed boxes only anchors them all)
        assert seen["sources"] == {ids[0]: "manual", ids[1]: "tracked", ids[2]: "manual", ids[4]: "manual"}
        doc = load_annotation(app.state.path)
        for frame_id in (ids[0], ids[2], ids[4]):
            np.testing.assert_array_equal(doc.frames[frame_id].position, frames[frame_id].position)
            assert doc.frames[frame_id].source == frames[frame_id].source
        np.testing.assert_array_equal(doc.frames[ids[1]].position, fix[0])  # the annotator's fix
        assert doc.frames[ids[3]].source == "tracked"
        assert "1 frames changed while it ran keep your boxes" in app.message.content
        assert app.tracking.changes.content == "Last run: no posed frame moved; 1 frame got a first pose."
    finally:
        app.close()
        server.stop()


def test_anchors_an_engine_posed_on_the_track_take_that_pose_and_the_next_run_anchors_on_the_persons_box(sequence_root, tmp_path, monkeypatch):
    """An engine that follows the anchor rule (engines.anchored_pose): each anchor takes the engine's pose with the
    person's box beside it; the next run sees that box, not the moved pose; the page counts them."""
    root, poses = sequence_root
    app, server = _app(root, tmp_path)
    try:
        frames = _people_and_tracker(app, poses)
        ids = app.sequence.ids
        seen, follow = [], [True]
        turn = Rotation.from_euler("z", 1.0, degrees=True)

        def track_sequence(sequence, annotation, frames=None, progress=None, config=None):
            seen.append({f: p.placed_matrix for f, p in annotation.frames.items() if p.source == "manual"})
            out = annotation.copy()
            for frame_id in frames:
                base = annotation.frames.get(frame_id) or FramePose(np.array([0, 0, 0.7]), np.array([0, 0, 0, 1.0]), "tracked")
                start = FramePose.from_matrix(base.placed_matrix)  # an anchor's: the person's box
                estimate = FramePose(start.position + [0.002, 0, 0], (turn * Rotation.from_quat(start.orientation)).as_quat()).matrix
                if base.source == "manual":
                    out.frames[frame_id] = anchored_pose(base, estimate, {"fitness": 0.9}, follows=follow[0])
                else:
                    out.frames[frame_id] = FramePose.from_matrix(estimate, "tracked", {"fitness": 0.8})
            return out

        monkeypatch.setattr(app_tracking, "tracking_engine", lambda: SimpleNamespace(track_sequence=track_sequence, refine_frame=None))
        for _ in range(2):
            assert app.tracking.start_tracking(0, len(ids) - 1, wait=True)
        doc = load_annotation(app.state.path)
        for frame_id in (ids[0], ids[2], ids[4]):
            person = frames[frame_id].matrix
            # both runs saw the person's box; the document holds it beside the pose on the track, its source kept
            for run in seen:
                np.testing.assert_allclose(run[frame_id], person, atol=1e-9)
            np.testing.assert_allclose(doc.frames[frame_id].placed_matrix, person, atol=1e-9)
            np.testing.assert_allclose(doc.frames[frame_id].position, frames[frame_id].position + [0.002, 0, 0], atol=1e-9)
            assert doc.frames[frame_id].source == frames[frame_id].source
        assert doc.frames[ids[2]].extra["reviewed"] == "accepted"
        assert "3 took the pose the other frames agree on" in app.message.content
        # a run that finds a box beyond its tolerance gives that box back: the document shows the person's box again
        follow[0] = False
        assert app.tracking.start_tracking(0, len(ids) - 1, wait=True)
        doc = load_annotation(app.state.path)
        for frame_id in (ids[0], ids[2], ids[4]):
            np.testing.assert_allclose(doc.frames[frame_id].matrix, frames[frame_id].matrix, atol=1e-9)
            assert "placed" not in doc.frames[frame_id].extra
        assert "0 took the pose the other frames agree on" in app.message.content
        follow[0] = True
        # a person who moves the box again makes that the box: the kept one goes
        app.state.set_frame(0)
        app.commit_box(frames[ids[0]].position + [0.0, 0.001, 0.0], frames[ids[0]].orientation)
        assert "placed" not in app.state.document().frames[ids[0]].extra
    finally:
        app.close()
        server.stop()


def test_changes_are_measured_in_degrees_and_millimetres_largest_first():
    ids = [f"{k:07d}" for k in range(1, 7)]
    before = Annotation("s", "mug", "none", np.array([0.1, 0.1, 0.1]))
    after = Annotation("s", "mug", "none", np.array([0.1, 0.1, 0.1]))
    q = np.array([0.0, 0.0, 0.0, 1.0])
    for k, frame_id in enumerate(ids[:4]):
        before.frames[frame_id] = FramePose(np.array([0.0, 0.0, 0.7]), q, "tracked")
    after.frames[ids[0]] = FramePose(np.array([0.0, 0.0, 0.7]), q, "tracked")  # unchanged
    after.frames[ids[1]] = FramePose(np.array([0.0, 0.003, 0.7]), q, "tracked")  # 3 mm
    after.frames[ids[2]] = FramePose(np.array([0.0, 0.0, 0.7]), Rotation.from_euler("x", 7.5, degrees=True).as_quat(), "tracked")
    after.frames[ids[3]] = FramePose(np.array([0.02, 0.0, 0.7]), q, "tracked")  # 20 mm
    after.frames[ids[4]] = FramePose(np.array([0.0, 0.0, 0.7]), q, "tracked")  # new
    changes, new = pose_changes(before, after, ids, ids)
    assert [c.frame_id for c in changes] == [ids[2], ids[3], ids[1]] and new == 1  # 7.5 deg before 2 cm before 3 mm
    assert changes[0].degrees == pytest.approx(7.5) and changes[1].metres == pytest.approx(0.02)
    text = changes_markdown(changes, new)
    assert text.startswith("**3 posed frames moved**") and "3: 7.5°, 0 mm; 4: 0.0°, 20 mm; 2: 0.0°, 3 mm" in text and "1 frame got a first pose" in text
    # symmetry y: a turn about y is no change
    before.symmetry = after.symmetry = "y"
    after.frames[ids[2]] = FramePose(np.array([0.0, 0.0, 0.7]), Rotation.from_euler("y", 40, degrees=True).as_quat(), "tracked")
    assert ids[2] not in [c.frame_id for c in pose_changes(before, after, ids, ids)[0]]
    # before a run: the kept boxes
    before.frames[ids[0]].source = "manual"
    before.frames[ids[2]].extra["reviewed"] = "accepted"
    assert anchors(before, ids) == [ids[0], ids[2]]
    text = keep_markdown(before, ids, ids)
    assert "keeps 2 boxes" in text and "as anchors" in text and "1 (placed), 3 (accepted)" in text and "poses the other 4, replacing the 2 tracked ones there" in text
    assert "none yet" in keep_markdown(Annotation("s"), ids, ids)
