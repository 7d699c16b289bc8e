"""Suspect frames (their chains disagreed) registered once more to the model of the trusted frames
(refine.reregister_suspects), against rendered frames whose true poses are known."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_tracking_render import render_sequence

from annotate.tracking import TrackingConfig
from annotate.tracking.config import scaled_to
from annotate.tracking.frames import FrameStore
from annotate.tracking.quality import pose_difference
from annotate.tracking.refine import build_model, reregister_suspects
from annotate.tracking.tracker import FrameResult, Tracker
from sequences.reader import open_sequence

SUSPECT = {"fitness": 0.9, "chain_disagreement_deg": 20.0, "chain_disagreement_m": 0.002}  # beyond the 5 deg threshold
TRUSTED = {"fitness": 0.95, "chain_disagreement_deg": 0.5, "chain_disagreement_m": 0.001}


def camera_mesh() -> trimesh.Trimesh:
    """A camera-like body: a 12 x 8 x 6 cm box with a 4 cm lens on its front, off-centre (no symmetry)."""
    body = trimesh.creation.box(extents=[0.12, 0.08, 0.06])
    lens = trimesh.creation.cylinder(radius=0.02, height=0.04, sections=24)
    lens.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    lens.apply_translation([0.025, 0.0, 0.05])
    mesh = trimesh.util.concatenate([body, lens])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def off(pose: np.ndarray, degrees: float, metres: float, axis=(0.3, 1.0, 0.2)) -> np.ndarray:
    """``pose`` turned by ``degrees`` about an object-frame axis and moved by ``metres`` along object x."""
    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis) / np.linalg.norm(axis)).as_matrix()
    step[:3, 3] = [metres, 0.0, 0.0]
    return pose @ step


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("suspects") / "camera_0001"
    mesh = camera_mesh()
    truth = render_sequence(root, mesh, frames=10, seed=3, hand=False)
    config = scaled_to(TrackingConfig(), mesh.extents)
    tracker = Tracker(FrameStore(open_sequence(root), config.stride, colors=False), mesh.extents, False, config)
    ids = sorted(truth)
    suspects = ids[3:5]
    model = build_model(tracker, {f: truth[f] for f in ids if f not in suspects}, config.max_global_frames)
    return tracker, truth, ids, suspects, model


def test_suspect_frames_come_back_to_the_trusted_model(scene):
    tracker, truth, ids, suspects, model = scene
    results = {f: FrameResult(truth[f], True, dict(TRUSTED)) for f in ids}
    for f in suspects:
        results[f] = FrameResult(off(truth[f], 6.0, 0.004), True, dict(SUSPECT))
    calm = ids[7]  # off too, but its chains agreed: not this step's business
    results[calm] = FrameResult(off(truth[calm], 6.0, 0.004), True, dict(TRUSTED))
    out = reregister_suspects(tracker, results, model)
    for f in suspects:
        deg, metres = pose_difference(out[f].pose, truth[f], False)
        assert deg < 0.5 and metres < 0.001, (f, deg, metres)
        assert out[f].figures == SUSPECT  # poses only: the chains' figures (and so the flag) stay
    np.testing.assert_array_equal(out[calm].pose, results[calm].pose)
    for f in set(ids) - set(suspects) - {calm}:
        np.testing.assert_array_equal(out[f].pose, truth[f])


def test_a_move_beyond_the_step_limit_and_manual_frames_are_kept(scene):
    tracker, truth, ids, suspects, model = scene
    results = {f: FrameResult(truth[f], True, dict(TRUSTED)) for f in ids}
    for f in suspects:
        results[f] = FrameResult(off(truth[f], 6.0, 0.0), True, dict(SUSPECT))
    strict = Tracker(tracker.store, tracker.extents, False, replace(tracker.config, max_suspect_step_deg=3.0))
    out = reregister_suspects(strict, results, model)
    for f in suspects:  # the registration would turn them 6 deg: more than 3 allowed
        np.testing.assert_array_equal(out[f].pose, results[f].pose)
    out = reregister_suspects(tracker, results, model, skip={suspects[0]})
    np.testing.assert_array_equal(out[suspects[0]].pose, results[suspects[0]].pose)
    assert pose_difference(out[suspects[1]].pose, truth[suspects[1]], False)[0] < 0.5


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="worker processes are forked, on Linux only")
def test_the_suspect_steps_give_the_same_poses_on_worker_processes(scene):
    """The recheck, the re-registration and a refinement round's restarts of suspect frames, on one process and on two."""
    import os

    from annotate.tracking.refine import recheck_disagreements, refine_all
    from annotate.tracking.registration import open3d_threads

    tracker, truth, ids, suspects, model = scene
    results = {f: FrameResult(truth[f], True, dict(TRUSTED)) for f in ids}
    for f in suspects:
        results[f] = FrameResult(off(truth[f], 6.0, 0.004), True, dict(SUSPECT))
    chains = {f: (off(truth[f], 6.0, 0.004), off(truth[f], -4.0, -0.003)) for f in suspects}
    out = {}
    for count in (1, 2):
        counted = Tracker(tracker.store, tracker.extents, False, replace(tracker.config, workers=count))
        before = os.times()
        with open3d_threads(1):  # as the engine runs them: Open3D's reductions on several threads sum in a varying order
            out[count] = (reregister_suspects(counted, results, model), recheck_disagreements(counted, results, chains), refine_all(counted, results, 1))
        after = os.times()
        ran_elsewhere = after.children_user + after.children_system > before.children_user + before.children_system
        assert ran_elsewhere == (count > 1)
    for k, (one, two) in enumerate(zip(out[1], out[2])):
        for f in ids:
            assert np.array_equal(one[f].pose, two[f].pose), (k, f)
            assert one[f].figures == two[f].figures
    assert any(not np.array_equal(out[1][2][f].pose, results[f].pose) for f in suspects)  # the round moved them


def test_a_frame_left_turned_over_is_registered_again_from_the_frame_before(scene):
    from annotate.tracking.config import TrackingConfig as Config
    from annotate.tracking.quality import document_figures
    from annotate.tracking.refine import repair_flips

    tracker, truth, ids, _, _ = scene
    over = np.eye(4)
    over[:3, :3] = Rotation.from_euler("x", 180, degrees=True).as_matrix()  # upside down about the box centre
    results = {f: FrameResult(truth[f], True, dict(TRUSTED)) for f in ids}
    for f in (ids[4], ids[6]):  # two frames turned over, the frame between them right: each is judged by the one before
        results[f] = FrameResult(truth[f] @ over, True, dict(SUSPECT))
    results[ids[9]] = FrameResult(truth[ids[9]] @ over, True, dict(TRUSTED))  # a manual frame is left as placed
    out = repair_flips(tracker, results, anchors=[ids[9]])
    for f in (ids[4], ids[6]):
        assert pose_difference(out[f].pose, truth[f], False)[0] < 1.0, f
        assert out[f].figures["flip_repaired_deg"] > 170.0
        assert "turned over" in document_figures(dict(out[f].figures), Config())["flag_reason"]
    np.testing.assert_array_equal(out[ids[9]].pose, results[ids[9]].pose)
    for f in set(ids) - {ids[4], ids[6], ids[9]}:
        np.testing.assert_array_equal(out[f].pose, truth[f])
    calm = {f: FrameResult(truth[f], True, dict(TRUSTED)) for f in ids}
    assert repair_flips(tracker, calm) is calm  # nothing turned over: nothing built, nothing changed


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="worker processes are forked, on Linux only")
def test_a_rounds_suspect_stretches_run_apart_and_give_the_loops_poses(scene):
    """The first round's restarts of suspect frames from the refined poses before them: cut into stretches that need
    nothing of each other, run on two processes, they give what one loop over all the frames in order gives."""
    from annotate.tracking.refine import _Settler, min_hits_for
    from annotate.tracking.registration import open3d_threads

    tracker, truth, ids, _, model = scene
    results = {f: FrameResult(truth[f], True, dict(TRUSTED)) for f in ids}
    lost = [ids[1], ids[5], ids[6]]  # two stretches: frames 2-4 are kept between them
    for f in lost:
        results[f] = FrameResult(off(truth[f], 6.0, 0.004), True, dict(SUSPECT))
    counted = Tracker(tracker.store, tracker.extents, False, replace(tracker.config, workers=2))
    hits = min_hits_for(model, counted.config)
    with open3d_threads(1):
        own = {f: counted.register(f, results[f].pose, model, hits) for f in ids}
        settler = _Settler(counted, results, own, {f: r.pose for f, r in results.items()}, model, hits, retry=True)
        stretches = settler._stretches(ids)
        assert [(a, b, retried) for a, b, retried, _ in stretches] == [(0, 5, True), (5, 10, True)]
        np.testing.assert_array_equal(stretches[1][3][-1], settler._plain[ids[4]][1])  # frame 5 restarts from frame 4
        apart = settler.all(2)
        in_order = dict(settler._run((0, len(ids), True, [])))
    assert list(apart) == ids
    for f in ids:
        assert np.array_equal(apart[f].pose, in_order[f].pose), f
        assert apart[f].figures == in_order[f].figures
    for f in lost:  # restarted from the frames before them, they come back
        assert pose_difference(apart[f].pose, truth[f], False)[0] < 1.0
