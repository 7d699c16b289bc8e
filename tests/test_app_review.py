"""Review that leads and guidance (issue 49, items 5 and 7): flagged frames worst first with a plain reason, "next
flagged" along that list, a fixed frame marked reviewed, export warns with the count; the on-page guide and hotkeys,
labels that carry their keys and show their state, frames counted from 1."""

from __future__ import annotations

import os
import stat
from types import SimpleNamespace

import numpy as np
import pytest
from test_app_fixtures import served_app, TRUE_EXTENTS, make_sequence

from annotate import app_tracking
from annotate.app_guide import WORKFLOW
from annotate.app_model import reconstruct_module
from annotate.app_review import mark_fixed, next_in_review, review_list, review_markdown, severity
from sequences.annotation import Annotation, FramePose, load_annotation

THRESHOLDS = SimpleNamespace(max_chain_departure_deg=8.0, min_fitness=0.5, max_chain_disagreement_m=0.01, min_points=100)


def _pose(extra: dict | None = None, source: str = "tracked") -> FramePose:
    return FramePose(np.array([0.0, 0.0, 0.7]), np.array([0.0, 0.0, 0.0, 1.0]), source, dict(extra or {}))


def _flagged_document(ids: list[str]) -> Annotation:
    """Frame 1 placed, 2 a little beyond a threshold, 3 far beyond one, 4 flagged without a figure beyond any."""
    doc = Annotation("box_seq", extents=TRUE_EXTENTS.copy())
    doc.frames[ids[0]] = _pose(source="manual")
    doc.frames[ids[1]] = _pose({"flagged": True, "chain_departure_deg": 9.0, "fitness": 0.9,
                                "flag_reason": "the final pose is 9.0 deg from both tracking chains"})
    doc.frames[ids[2]] = _pose({"flagged": True, "fitness": 0.2, "chain_departure_deg": 1.0,
                                "flag_reason": "fitness 0.20 < 0.5; only 40% of the points near the box are inside it"})
    doc.frames[ids[3]] = _pose({"flagged": True, "flag_reason": "between flagged frames 0000002 and 0000003: its pose leans on theirs"})
    return doc


def test_flagged_frames_are_listed_worst_first_with_a_plain_reason():
    ids = ["0000001", "0000002", "0000003", "0000004"]
    items = review_list(_flagged_document(ids), ids, THRESHOLDS)
    assert [item.index for item in items] == [2, 1, 3]
    assert items[0].severity == pytest.approx(2.5) and items[1].severity == pytest.approx(9 / 8) and items[2].severity == 1.0
    assert items[0].reason == "fitness 0.20 < 0.5 (and 1 more)"
    text = review_markdown(items, current=1, reviewed=0)
    lines = text.split("\n\n")
    assert lines[0].startswith("**3 flagged**, worst first")
    assert lines[1] == "1. frame 3: fitness 0.20 < 0.5 (and 1 more)"  # frames counted from 1
    assert lines[2] == "**2. frame 2: the final pose is 9.0 deg from both tracking chains**"  # the current frame
    # "next flagged" walks the list, wrapping; from a frame not in it, the worst
    order = [item.index for item in items]
    assert [next_in_review(order, k) for k in (0, 2, 1, 3)] == [2, 1, 3, 2]
    assert next_in_review([], 0) is None
    assert severity(_pose({"flagged": True, "error": "no depth"}), THRESHOLDS) == 100.0
    assert severity(_pose({"flagged": True, "points": 0}), THRESHOLDS) == 100.0


def test_a_frame_changed_by_hand_after_its_flag_is_marked_fixed():
    flagged = _pose({"flagged": True, "flag_reason": "x"})
    assert mark_fixed(flagged, {}) == {"reviewed": "fixed"}
    assert mark_fixed(flagged, {"flagged": True, "fitness": 0.1}) == {"flagged": True, "fitness": 0.1}  # a refine that fails again
    assert mark_fixed(_pose(), {}) == {} and mark_fixed(None, {"fitness": 0.9}) == {"fitness": 0.9}


@pytest.fixture(scope="module")
def sequence_root(tmp_path_factory):
    root, poses = make_sequence(tmp_path_factory.mktemp("review") / "box_seq", frames=4)
    return root, poses


@pytest.fixture
def app(sequence_root, tmp_path):
    with served_app(sequence_root[0], tmp_path) as app:
        yield app


def test_the_page_leads_through_the_review(app):
    ids = app.sequence.ids
    document = _flagged_document(ids)
    app.state.edit(lambda doc: doc.frames.update(document.frames))
    assert "**3 flagged**" in app.review.list.content and "1. frame 3:" in app.review.list.content
    app.review.next_flagged.value = True
    assert app.state.frame == 2  # the worst first
    assert "#1 of 3 in the review list" in app.tracking.info.content and "fitness 0.20" in app.tracking.info.content
    assert "fitness 0.9" not in app.tracking.info.content  # no dump of figures
    # the annotator fixes the box: the frame is marked reviewed and leaves the list
    app.moving.move[0].value = "+"
    doc = load_annotation(app.state.path)
    assert doc.frames[ids[2]].source == "manual" and doc.frames[ids[2]].extra == {"reviewed": "fixed"}
    assert app.state.status() == "manual" and "reviewed (fixed)" in app.title.content
    assert "**2 flagged**" in app.review.list.content and "1 reviewed" in app.review.list.content
    app.review.next_flagged.value = True
    assert app.state.frame == 1  # the next worst


def test_after_a_run_the_tracking_panel_shows_its_result_not_its_progress(app, monkeypatch):
    ids = app.sequence.ids
    app.state.set_frame(1)
    app.commit_box([0.0, 0.0, 0.7], [0, 0, 0, 1])  # a box in the range: the run's anchor (kept, with the engine's figures)
    tracked = _flagged_document(ids)
    engine = SimpleNamespace(track_sequence=lambda sequence, document, frames, progress: tracked)
    monkeypatch.setattr(app_tracking, "tracking_engine", lambda: engine)
    app.tracking.range_from.value, app.tracking.range_to.value = 2, 4  # frames counted from 1
    calls = []
    original = app.tracking.start_tracking
    monkeypatch.setattr(app.tracking, "start_tracking", lambda first, last, wait=False: calls.append((first, last)) or original(first, last, wait=True))
    app.tracking.track_range.value = True
    assert calls == [(1, 3)]  # indices of frames 2 to 4
    assert "Tracking" not in app.tracking.info.content
    assert "Tracked 3 frames" in app.message.content and "3 flagged" in app.message.content  # the engine's flag on frame 2 stays
    assert set(load_annotation(app.state.path).frames) == {ids[1], ids[2], ids[3]}


def test_the_guide_lists_the_workflow_and_every_hotkey_and_buttons_carry_their_keys(app):
    guide = app.guide.content
    for step, _ in WORKFLOW:
        assert f"**{step}**" in guide
    assert [step for step, _ in WORKFLOW] == ["Place", "Refine", "Track", "Review", "Preview", "Export"]
    commands = list(app.server.gui._command_handle_from_uuid.values())
    assert len(commands) == len(app.hotkeys) >= 20
    shown = {hotkey.label: hotkey.shown for hotkey in app.hotkeys}
    for command in commands:
        assert f"| {shown[command.label]} | {command.label} |" in guide
    buttons = [h for h in app.server.gui._gui_input_handle_from_uuid.values() if type(h).__name__ == "GuiButtonHandle"]
    with_keys = 0
    for button in buttons:
        base = button.label.split(" (")[0]
        if base in shown or base == "Leave camera view":
            assert button.label.endswith(f"({shown.get(base, 'H')})"), button.label
            with_keys += 1
    assert with_keys >= 9


def test_frames_are_counted_from_1_and_the_view_toggle_says_its_state(app, monkeypatch):
    assert (app.frame_slider.min, app.frame_slider.max, app.frame_slider.value) == (1, 4, 1)
    assert app.tracking.range_from.min == 1 and app.tracking.range_to.value == 4
    assert app.look_button.label == "Look through camera (H)"
    app.look_button.value = True
    assert app.look_through and app.look_button.label == "Leave camera view (H)"
    app._on_camera(SimpleNamespace(position=np.array([0.3, 0.0, 0.0])))  # a report from before: within the settle time
    assert app.look_through
    monkeypatch.setattr("annotate.app.LOOK_SETTLE_S", 0.0)
    app._on_camera(SimpleNamespace(position=np.array([0.001, 0.0, 0.0])))  # still at the sensor
    assert app.look_through
    app._on_camera(SimpleNamespace(position=np.array([0.3, 0.0, 0.0])))  # orbiting away leaves the sensor's view
    assert not app.look_through and app.look_button.label == "Look through camera (H)"


@pytest.mark.skipif(reconstruct_module() is None, reason="needs the reconstruct pipeline")
def test_export_warns_with_the_count_of_flagged_frames_and_files_keep_the_umask(app, sequence_root, tmp_path):
    _, poses = sequence_root
    ids = app.sequence.ids

    def truth(doc):
        doc.extents = TRUE_EXTENTS.copy()
        for k, (frame_id, (p, q)) in enumerate(zip(ids, poses)):
            extra = {"flagged": True, "flag_reason": "test"} if k in (1, 2) else {}
            doc.frames[frame_id] = FramePose(np.asarray(p), np.asarray(q), "tracked" if extra else "manual", extra)

    app.state.edit(truth)
    app.model.out_dir.value = str(tmp_path / "gt")
    assert app.model.start(app.model._export, wait=True)
    assert "Exported" in app.model.info.content and "Warning: 2 frames are still flagged" in app.model.info.content
    mask = os.umask(0o022)
    os.umask(mask)
    for path in (tmp_path / "gt").rglob("*"):
        expected = (0o777 if path.is_dir() else 0o666) & ~mask
        assert stat.S_IMODE(path.stat().st_mode) == expected, path
    app.state.edit(lambda doc: [doc.frames[f].extra.update(reviewed="accepted") for f in ids[1:3]])
    assert app.model.start(app.model._export, wait=True)
    assert "Exported" in app.model.info.content and "Warning" not in app.model.info.content
