"""Refine that explains itself (issue 49 item 3): a refine that cannot fit the box leaves it as it was and says why in
words, for both tracking engines; one that can moves it onto the object."""

from __future__ import annotations


import numpy as np
import pytest
from test_app_fixtures import served_app, TRUE_EXTENTS, make_sequence

from annotate.app_refine import judge_refine
from annotate.app_tracking import tracking_engine
from sequences.annotation import FramePose, load_annotation

ENGINES = ("chains", "graph")


@pytest.fixture(scope="module")
def sequence_root(tmp_path_factory):
    return make_sequence(tmp_path_factory.mktemp("refine") / "box_seq", frames=4)


@pytest.fixture(params=ENGINES)
def app(request, sequence_root, tmp_path, monkeypatch):
    monkeypatch.setenv("REDWOOD_GT_ENGINE", request.param)
    if tracking_engine() is None:
        pytest.skip(f"tracking engine {request.param} not importable")
    with served_app(sequence_root[0], tmp_path) as app:
        app.state.set_extents(TRUE_EXTENTS)
        yield app


def _truth_elsewhere(app, poses) -> None:
    """The true boxes in frames 2-4: the model a refine of frame 1 fits to."""
    ids = app.sequence.ids

    def change(doc):
        for frame_id, (p, q) in zip(ids[1:], poses[1:]):
            doc.frames[frame_id] = FramePose(np.asarray(p), np.asarray(q), "manual")

    app.state.edit(change)


def test_a_failed_refine_leaves_the_box_and_says_why(app, sequence_root):
    _, poses = sequence_root
    position, orientation = poses[0]
    _truth_elsewhere(app, poses)
    off = position + np.array([0.12, 0.0, 0.0])  # beside the object, on the wall
    app.commit_box(off, orientation)
    saves = app.state.saves
    app.tracking.refine.value = True
    pose = load_annotation(app.state.path).frames["0000001"]
    np.testing.assert_array_equal(pose.position, off)  # as it was
    assert pose.source == "manual" and app.state.saves == saves
    message = app.message.content
    assert message.startswith("Refine left the box of frame 1 as it was:"), message
    assert ("% of the box's points" in message or "points of the frame lie in the box" in message or "of the points in the box fit" in message), message
    assert "move the box onto the object" in message and "fitness" not in message
    assert message in app.tracking.info.content


def test_a_refine_near_the_truth_moves_the_box_onto_it(app, sequence_root):
    _, poses = sequence_root
    position, orientation = poses[0]
    _truth_elsewhere(app, poses)
    start = position + np.array([0.006, -0.004, 0.004])
    app.commit_box(start, orientation)
    app.tracking.refine.value = True
    refined = load_annotation(app.state.path).frames["0000001"]
    assert refined.source == "refined", app.message.content
    assert np.linalg.norm(refined.position - position) < 0.5 * np.linalg.norm(start - position)
    assert app.message.content.startswith("Refined frame 1")


def test_a_refine_with_no_other_box_says_it_needs_one(app, sequence_root):
    _, poses = sequence_root
    app.commit_box(*poses[0])
    saves = app.state.saves
    app.tracking.refine_current()
    assert app.state.saves == saves and "the only one" in app.message.content


def test_the_verdict_in_words():
    low = FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined", {"fitness": 0.12, "flagged": True, "flag_reason": "fitness 0.12 < 0.5"})
    verdict = judge_refine(low)
    assert not verdict.ok and verdict.reason.startswith("only 12% of the box's points lie on the object")
    few = FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined", {"points": 40, "fitness": 0.9})
    assert not judge_refine(few).ok and "only 40 points" in judge_refine(few).reason
    rough = FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined", {"fitness": 0.8, "flagged": True, "flag_reason": "inlier RMSE 4.0 mm > 3.0 mm"})
    assert judge_refine(rough).ok and "RMSE" in judge_refine(rough).reason  # it fits: taken, and flagged
    good = judge_refine(FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined", {"fitness": 0.9}))
    assert good.ok and good.reason == ""
