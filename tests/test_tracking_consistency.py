"""Chains that lost the object: the seam between the two chains, the anchors' links, and the checks
of the final poses against the chains and against the motion (reconcile.py, consistency.py)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from annotate.tracking.consistency import chain_departures, rotation_jumps
from annotate.tracking.quality import pose_difference
from annotate.tracking.reconcile import blend_chains, chain_frame_offsets
from annotate.tracking.tracker import FrameResult

STEP_DEG = 6.0  # the object's turn per frame (a v5 synthetic sequence: 5.6-6.4 deg median)


def _pose(deg_z: float, extra: Rotation | None = None, x: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    R = Rotation.from_euler("z", deg_z, degrees=True)
    T[:3, :3] = (R * extra).as_matrix() if extra is not None else R.as_matrix()
    T[:3, 3] = [x, 0.0, 0.5]
    return T


def _truth(n: int) -> list[np.ndarray]:
    return [_pose(STEP_DEG * k, x=0.002 * k) for k in range(n)]


def _chains(truth: list[np.ndarray], lost_after: int, found_from: int):
    """The forward chain right up to ``lost_after`` then 25 deg off about x; the backward chain 20 deg off
    about y before ``found_from`` then right (both right in between: where they meet)."""
    ids = [f"{k:07d}" for k in range(len(truth))]
    off_f, off_b = Rotation.from_euler("x", 25, degrees=True), Rotation.from_euler("y", -20, degrees=True)
    forward = {f: FrameResult(T if k <= lost_after else T @ _block(off_f), True, {"fitness": 0.9}) for k, (f, T) in enumerate(zip(ids, truth))}
    backward = {f: FrameResult(T if k >= found_from else T @ _block(off_b), True, {"fitness": 0.8}) for k, (f, T) in enumerate(zip(ids, truth))}
    return ids, forward, backward


def _block(R: Rotation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R.as_matrix()
    return T


def test_chains_that_lost_the_object_are_joined_at_their_seam_not_blended():
    truth = _truth(31)
    ids, forward, backward = _chains(truth, lost_after=18, found_from=12)
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    errors = [pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)]
    assert max(errors) < 1e-4  # forward before the seam, backward after it, both right around it
    inner = [out[f].figures for f in ids[1:-1]]
    assert all(x["chain_switch"] and x["chain_disagreement_deg"] < 1e-4 for x in inner)
    assert abs(inner[0]["chain_disagreement_raw_deg"] - 20.0) < 1e-4 and abs(inner[-1]["chain_disagreement_raw_deg"] - 25.0) < 1e-4
    # the linear blend of the same chains (no thresholds: the old reconciliation) puts frames 9 deg off
    blended = blend_chains(ids, forward, backward, symmetric=False)
    worst = max(pose_difference(blended[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1))
    assert 8.0 < worst < 25.0
    assert not any("chain_switch" in blended[f].figures for f in ids[1:-1])


def test_chains_that_never_meet_are_blended_and_keep_their_disagreement():
    truth = _truth(21)
    ids, forward, backward = _chains(truth, lost_after=5, found_from=15)  # no frame where both are right
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    assert not any("chain_switch" in out[f].figures for f in ids[1:-1])
    assert all(out[f].figures["chain_disagreement_deg"] > 5.0 for f in ids[6:15])


def test_a_link_from_one_chain_alone_is_not_trusted():
    truth = _truth(11)
    placed = {"a": truth[0], "b": truth[10] @ _block(Rotation.from_euler("z", 2, degrees=True))}
    drifted = {"b": FrameResult(truth[10] @ _block(Rotation.from_euler("x", 7, degrees=True)), True, {})}
    lost = {"a": FrameResult(truth[0] @ _block(Rotation.from_euler("x", 20, degrees=True)), True, {})}
    offsets = chain_frame_offsets(["a", "b"], placed, [drifted], [lost], symmetric=False)
    assert np.allclose(offsets[1], np.eye(4))  # the 7 deg drift of the forward chain alone is not taken as the link
    small = {"b": FrameResult(placed["b"] @ _block(Rotation.from_euler("x", 3, degrees=True)), True, {})}
    offsets = chain_frame_offsets(["a", "b"], placed, [small], [lost], symmetric=False)
    assert abs(pose_difference(np.eye(4), offsets[1])[0] - 3.0) < 1e-4  # a small one is
    # both chains arriving within a few degrees and agreeing: the link is their mean
    good_f = {"b": FrameResult(placed["b"] @ _block(Rotation.from_euler("x", 3, degrees=True)), True, {})}
    good_b = {"a": FrameResult(placed["a"] @ _block(Rotation.from_euler("x", -3, degrees=True)), True, {})}
    offsets = chain_frame_offsets(["a", "b"], placed, [good_f], [good_b], symmetric=False)
    assert abs(pose_difference(np.eye(4), offsets[1])[0] - 3.0) < 1e-6


def test_final_poses_far_from_both_chains_and_jumps_are_measured():
    truth = _truth(10)
    final = {f"{k}": T for k, T in enumerate(truth)}
    final["4"] = _pose(STEP_DEG * 4 + 50.0, x=0.008)  # slid 50 deg about the spin axis
    chains = {f"{k}": (truth[k] @ _block(Rotation.from_euler("x", 3, degrees=True)), truth[k] @ _block(Rotation.from_euler("x", -8, degrees=True))) for k in range(1, 9)}
    departures = chain_departures(final, chains, symmetric=False)
    assert abs(departures["3"][0] - 3.0) < 1e-4 and departures["3"][1] < 1e-9
    expected = pose_difference(final["4"], chains["4"][0])[0]
    assert abs(departures["4"][0] - expected) < 1e-9 and expected > 45.0
    jumps = rotation_jumps([final[f"{k}"] for k in range(10)], symmetric=False)
    assert np.allclose(jumps[[0, 1, 2, 6, 7, 8, 9]], STEP_DEG)
    assert np.allclose(jumps[[3, 4, 5]], [STEP_DEG + 50.0, STEP_DEG + 50.0, 50.0 - STEP_DEG])
    # symmetric: a spin about y is no motion
    spun = [T @ _block(Rotation.from_euler("y", 40 * k, degrees=True)) for k, T in enumerate(truth)]
    assert np.allclose(rotation_jumps(spun, symmetric=True), rotation_jumps(truth, symmetric=True))


def test_a_frame_both_chains_lost_is_blended_and_not_ok():
    truth = _truth(31)
    ids, forward, backward = _chains(truth, lost_after=18, found_from=12)
    forward[ids[15]] = FrameResult(truth[15], False, {"error": "no depth"})
    backward[ids[15]] = FrameResult(truth[15], False, {"error": "no depth"})
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    assert not out[ids[15]].ok
    assert max(pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)) < 1e-4


def test_a_gap_no_loss_explains_keeps_its_disagreement():
    truth = _truth(31)
    ids, forward, backward = _chains(truth, lost_after=40, found_from=12)  # the backward chain lost before 12
    for k in range(19, 30):  # ... and the forward chain drifts 1.5 deg per frame after 18 (no jump)
        forward[ids[k]] = FrameResult(truth[k] @ _block(Rotation.from_euler("x", 1.5 * (k - 18), degrees=True)), True, {})
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    figures = {k: out[ids[k]].figures for k in range(1, 30)}
    assert all(figures[k]["chain_switch"] for k in figures)
    assert all(figures[k]["chain_disagreement_deg"] < 1e-4 for k in range(1, 19))  # the lost chain's stretch
    assert all(abs(figures[k]["chain_disagreement_deg"] - 1.5 * (k - 18)) < 1e-4 for k in range(19, 30))


def test_the_model_of_a_badly_tracked_sequence_uses_the_frames_whose_chains_agree_best():
    from annotate.tracking import TrackingConfig
    from annotate.tracking.refine import best_agreeing

    config = TrackingConfig()  # thresholds 5 deg, 10 mm
    truth = _truth(8)
    # chains' disagreement per frame (deg, m): frame 3 is close in both, frame 5 slid 60 mm along a plane
    gaps = [(0.0, 0.0), (6.0, 0.002), (1.0, 0.030), (1.0, 0.003), (2.0, 0.004), (0.5, 0.060), (4.0, 0.001), (0.0, 0.0)]
    results = {f"{k}": FrameResult(T, True, {"chain_disagreement_deg": d, "chain_disagreement_m": m}) for k, (T, (d, m)) in enumerate(zip(truth, gaps))}
    results["0"] = FrameResult(truth[0], False, {})  # failed: never in the model
    picked = best_agreeing(results, 4, config)
    # scores (the larger of deg / 5 and m / 0.01): 7 -> 0, 3 -> 0.3, 4 -> 0.4, 6 -> 0.8, 1 -> 1.2, 2 -> 3, 5 -> 6
    assert list(picked) == ["3", "4", "6", "7"]  # in frame order
    assert all(np.array_equal(picked[f], results[f].pose) for f in picked)


def test_a_link_both_chains_missed_at_the_anchors_is_taken_where_they_meet():
    # placed boxes 3 deg apart in their own object frames: chains from anchor b live 3 deg off those from a
    truth = _truth(11)
    E_b = _block(Rotation.from_euler("x", 3, degrees=True))
    placed = {"0": truth[0], "10": truth[10] @ E_b}
    ids = [str(k) for k in range(11)]
    # the forward chain drifts 1 deg a frame after frame 5 (7 deg at b: too far for a link alone); the
    # backward chain is lost before frame 4; between them, at frames 4-5, both are on the object
    forward = {f: FrameResult(truth[k] @ _block(Rotation.from_euler("y", max(0, k - 3), degrees=True)), True, {}) for k, f in enumerate(ids)}
    backward = {f: FrameResult(truth[k] @ E_b @ (_block(Rotation.from_euler("z", 20, degrees=True)) if k < 4 else np.eye(4)), True, {}) for k, f in enumerate(ids)}
    offsets = chain_frame_offsets(["0", "10"], placed, [forward], [backward], symmetric=False)
    true_link = np.linalg.inv(E_b)  # E_b^-1 E_a: brings anchor b's chains into anchor a's object frame
    # halfway between the placed boxes' identity and the link where the chains meet (frame 4: 1 deg drift)
    assert pose_difference(offsets[1], true_link)[0] < 2.0 < pose_difference(np.eye(4), true_link)[0]
