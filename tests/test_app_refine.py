"""Refine that explains itself (issue 49 item 3): a refine that cannot fit the box leaves it as it was and says why in
words, for both tracking engines; one that can moves it onto the object."""

from __future__ import annotations


import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation
from test_app_fixtures import served_app, TRUE_EXTENTS, make_sequence, render

from annotate.app_refine import engine_config, judge_refine
from annotate.app_tracking import tracking_engine
from annotate.depth_agreement import MIN_AGREEMENT, agreement_figures, agreement_reason
from sequences.annotation import Annotation, FramePose, load_annotation
from sequences.camera import Camera
from sequences.reader import open_sequence

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


def test_the_depth_agreement_judges_the_fit_where_the_engine_measured_it():
    """The share of the model the frame's depth confirms decides, not the share of the box's points on the model."""
    assert agreement_figures(450, 50) == {"depth_votes": 500, "depth_agreement": 0.9}
    assert agreement_figures(0, 0) == {"depth_votes": 0}
    assert agreement_reason({"fitness": 0.2}) is None  # not measured: nothing to say
    unseen_sides = FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined", {"fitness": 0.2, **agreement_figures(950, 50)})
    assert judge_refine(unseen_sides).ok and judge_refine(unseen_sides).reason == ""
    seen_through = FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined", {"fitness": 0.9, **agreement_figures(300, 700)})
    verdict = judge_refine(seen_through)
    assert not verdict.ok and verdict.reason.startswith("only 30% of the object the other posed frames show lies where this frame measures it")
    hidden = FramePose(np.zeros(3), np.array([0, 0, 0, 1.0]), "refined", {"fitness": 0.9, **agreement_figures(30, 10)})
    assert not judge_refine(hidden).ok and "measures only 40 points" in judge_refine(hidden).reason


@pytest.mark.parametrize("engine_name", ENGINES)
def test_a_refine_in_a_frame_showing_a_side_no_posed_frame_saw_is_taken(engine_name, tmp_path, monkeypatch):
    """Frames 2-4 see the box turned 30-40 deg (its front and one side), frame 1 turned -65 deg (mostly the other side):
    under half of frame 1's points pair with the model, but the depth confirms all of the model the true box puts in
    view, so the refine from the true box is taken and stays on it."""
    monkeypatch.setenv("REDWOOD_GT_ENGINE", engine_name)
    engine = tracking_engine()
    if engine is None:
        pytest.skip(f"tracking engine {engine_name} not importable")
    root = tmp_path / "turned"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    camera, poses = Camera(), []
    for k, turn in enumerate([-65.0, 30.0, 35.0, 40.0]):
        orientation = (Rotation.from_euler("x", 180, degrees=True) * Rotation.from_euler("y", turn, degrees=True)).as_quat()
        position = np.array([0.0, 0.0, 0.7])
        color, depth = render(camera, position, orientation)
        Image.fromarray(color).save(root / "rgb" / f"{k + 1:07d}-{33_333 * k:012d}.jpg", quality=92)
        Image.fromarray(np.round(depth * 1000).astype(np.uint16)).save(root / "depth" / f"{k + 1:07d}-{33_333 * k:012d}.png")
        poses.append((position, orientation))
    sequence = open_sequence(root)
    document = Annotation("turned", "other", "none", TRUE_EXTENTS.copy())
    for frame_id, (position, orientation) in zip(sequence.ids, poses):
        document.frames[frame_id] = FramePose(position, orientation, "manual")
    config = engine_config(engine)
    result = engine.refine_frame(sequence, document, sequence.ids[0], config)
    assert result.extra["fitness"] < 0.5  # the fitness alone would have declined it
    assert result.extra["depth_agreement"] >= 0.95 > MIN_AGREEMENT
    assert judge_refine(result, config).ok
    assert np.linalg.norm(result.position - poses[0][0]) < 0.004
