"""Chains that lost the object: the seam between the two chains, the anchors' links, and the checks
of the final poses against the chains and against the motion (reconcile.py, consistency.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from annotate.tracking.config import TrackingConfig
from annotate.tracking.consistency import chain_departures, flagged_gaps, flags_grown, free_spin_runs, rotation_jumps
from annotate.tracking.quality import flag_reasons
from annotate.tracking.quality import pose_difference
from annotate.tracking.reconcile import best_switch, blend_chains, chain_frame_offsets
from annotate.tracking.tracker import FrameResult

STEP_DEG = 6.0  # the object's turn per frame (a hand turning it briskly)


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


def test_a_chain_lost_between_the_first_two_inner_frames_is_seen():
    # the forward chain right at frame 1 only, 25 deg off from frame 2 on; the backward one right throughout.
    # The gaps' running median starts at frame 2 unless the end frames are repeated: the loss between frames
    # 1 and 2 went unseen and the linear blend put frame 28 about 23 deg off
    truth = _truth(31)
    ids, forward, backward = _chains(truth, lost_after=1, found_from=0)
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    errors = [pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)]
    assert max(errors) < 1e-4
    assert all(out[f].figures["chain_switch"] for f in ids[1:-1])
    # the same loss one step later was always seen
    ids, forward, backward = _chains(truth, lost_after=2, found_from=0)
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    assert max(pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)) < 1e-4


def test_an_end_frame_off_in_one_chain_alone_is_flagged_or_right():
    # the forward chain 15 deg off at the first inner frame only (back on the object from the second): with the end
    # frames repeated in the gaps' running median this shows as a loss, the seam lands after it, and frame 1 takes
    # the forward chain's pose; its doubt must say so (its disagreement alone is 0)
    truth = _truth(20)
    ids = [f"{k:07d}" for k in range(len(truth))]
    off = _block(Rotation.from_euler("x", 15, degrees=True))
    forward = {f: FrameResult(T @ off if k == 1 else T, True, {"fitness": 0.9}) for k, (f, T) in enumerate(zip(ids, truth))}
    backward = {f: FrameResult(T, True, {"fitness": 0.9}) for f, T in zip(ids, truth)}
    for fw, bw, end in ((forward, backward, ids[1]), ({f: backward[f] for f in ids}, {f: FrameResult(truth[k] @ off if k == 18 else truth[k], True, {"fitness": 0.9}) for k, f in enumerate(ids)}, ids[18])):
        out = blend_chains(ids, fw, bw, symmetric=False, max_deg=5.0, max_m=0.01, anchors=(truth[0], truth[-1]))
        k = ids.index(end)
        error = pose_difference(out[end].pose, truth[k])[0]
        assert error < 1.0 or flag_reasons(out[end].figures, TrackingConfig()), (end, error, out[end].figures)


def test_manual_frames_side_by_side_or_a_chain_failed_throughout_do_not_crash():
    truth = _truth(2)
    ids, forward, backward = _chains(truth, lost_after=5, found_from=0)
    assert blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01, anchors=(truth[0], truth[-1])) == {}
    truth = _truth(8)
    ids, forward, backward = _chains(truth, lost_after=8, found_from=0)
    failed = {f: FrameResult(r.pose, False, {"error": "registration failed"}) for f, r in backward.items()}
    out = blend_chains(ids, forward, failed, symmetric=False, max_deg=5.0, max_m=0.01, anchors=(truth[0], truth[-1]))
    assert all(pose_difference(out[f].pose, truth[k])[0] < 1e-3 for k, f in enumerate(ids[1:-1], start=1))


def test_frames_both_chains_jumped_on_their_way_to_are_flagged_and_keep_their_pose():
    # both chains turn 10 deg the same way: the forward one from frame 5 on, the backward one (going back) from
    # frame 20 down. Their gap stays small where both are off (frames 5-19), so no loss shows in it; yet each
    # chain jumped between its anchor and those frames, which a gap alone would leave unflagged
    truth = _truth(26)
    ids = [f"{k:07d}" for k in range(len(truth))]
    off = _block(Rotation.from_euler("y", 10, degrees=True))
    forward = {f: FrameResult(T @ off if k >= 5 else T, True, {"fitness": 0.9}) for k, (f, T) in enumerate(zip(ids, truth))}
    backward = {f: FrameResult(T @ off if k < 20 else T, True, {"fitness": 0.9}) for k, (f, T) in enumerate(zip(ids, truth))}
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01, anchors=(truth[0], truth[-1]))
    config = TrackingConfig()
    for k, f in enumerate(ids[1:-1], start=1):
        figures = out[f].figures
        if 5 <= k < 20:
            assert figures["chains_jumped_deg"] == pytest.approx(10.0, abs=0.5) and flag_reasons(figures, config), k
        else:
            assert "chains_jumped_deg" not in figures, k
    # a flag, not a new pose: where both chains agree the frame keeps their (wrong) pose for a person to review
    assert all(pose_difference(out[ids[k]].pose, truth[k] @ off)[0] < 1e-3 for k in range(5, 20))


def _off_x(deg: float) -> np.ndarray:
    return _block(Rotation.from_euler("x", deg, degrees=True))


def test_chains_that_never_meet_switch_where_the_path_is_smooth():
    # the forward chain right up to frame 10 then 25 deg off, the backward one 12 deg off the other way up
    # to frame 10 then right: no frame has both on the object, yet one path (forward to 10, backward from 11) is right
    truth = _truth(21)
    ids = [f"{k:07d}" for k in range(21)]
    forward = {f: FrameResult(truth[k] if k <= 10 else truth[k] @ _off_x(25), True, {}) for k, f in enumerate(ids)}
    backward = {f: FrameResult(truth[k] if k >= 11 else truth[k] @ _off_x(-12), True, {}) for k, f in enumerate(ids)}
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    errors = [pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)]
    assert max(errors) < 1e-4
    assert all(out[f].figures["chain_switch"] for f in ids[1:-1])
    # the path is smooth (the truth throughout, up to the constant-velocity prediction's 0.2 mm): no disagreement left
    assert all(out[f].figures["chain_disagreement_deg"] < 1e-4 for f in ids[1:-1])
    assert best_switch(ids, forward, backward, {f: backward[f].pose for f in ids}, False, 5.0, 0.01)[0] == 11
    # a frame that failed in one chain keeps a prediction there, not scored (it takes the other chain's pose)
    backward[ids[15]] = FrameResult(backward[ids[14]].pose, False, {"error": "no depth"})
    assert best_switch(ids, forward, backward, {f: backward[f].pose for f in ids}, False, 5.0, 0.01, (truth[0], truth[-1]))[0] == 11
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01, anchors=(truth[0], truth[-1]))
    assert max(pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1) if k != 15) < 1e-4
    # the linear blend of the same chains (no thresholds) puts frames 12-18 deg off
    blended = blend_chains(ids, forward, backward, symmetric=False)
    assert max(pose_difference(blended[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)) > 10.0


def test_chains_lost_together_keep_a_flag_whatever_the_path():
    truth = _truth(21)
    ids, forward, backward = _chains(truth, lost_after=5, found_from=15)  # both lost in frames 6-14
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01)
    errors = {k: pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)}
    # every path holds a loss (a 20-25 deg jump, or a switch between two lost chains): the frames it
    # carries wrong say so, through the path's worst departure or the chains' raw gap
    assert all(out[ids[k]].figures["chain_disagreement_deg"] > 5.0 for k in errors if errors[k] > 5.0)
    assert sum(e > 5.0 for e in errors.values()) >= 9
    assert all(flag_reasons(out[ids[k]].figures, TrackingConfig()) for k in errors if errors[k] > 5.0)


def _link_weight(placement_deg: float, link_deg: float) -> float:
    """Two anchors, rotation about one axis: the share of a measured link (sigma ``link_deg``) the least-squares
    estimate takes, against two placed boxes each off by sigma ``placement_deg`` (their difference: twice the variance)."""
    return 2 * placement_deg**2 / (2 * placement_deg**2 + link_deg**2)


def test_the_switch_follows_the_chain_that_moves_smoothly():
    # the backward chain jumps 12 deg between frames 6 and 7 (lost before 7); the forward chain jumps
    # 15 deg between 12 and 13: the smoothest path switches in 7..12, and its worst step is the hand's motion
    truth = _truth(21)
    ids = [f"{k:07d}" for k in range(21)]
    forward = {f: FrameResult(truth[k] if k <= 12 else truth[k] @ _off_x(15), True, {}) for k, f in enumerate(ids)}
    backward = {f: truth[k] if k >= 7 else truth[k] @ _off_x(-12) for k, f in enumerate(ids)}
    found = {f: FrameResult(T, True, {}) for f, T in backward.items()}
    s, (deg, metres), _ = best_switch(ids, forward, found, backward, False, 5.0, 0.01, (truth[0], truth[-1]))
    assert 7 <= s <= 13
    assert deg < 1e-4 and metres < 5e-4  # the hand's motion: a turning object's velocity turns too (0.2 mm)
    # a path through a loss scores that loss: with a backward chain that jumps with the forward one, 15 deg
    same = {f: forward[f].pose for f in ids}
    assert abs(best_switch(ids, forward, forward, same, False, 5.0, 0.01)[1][0] - 15.0) < 1e-6


def test_a_chain_drifting_smoothly_away_from_the_far_anchor_is_not_the_smoothest_path():
    # the forward chain drifts 2.2 deg per frame (no jump: 44 deg off at the far anchor), the backward one is
    # 12 deg off up to frame 5 and right from 6; no frame has the two within twice the thresholds from 6 on
    truth = _truth(21)
    ids = [f"{k:07d}" for k in range(21)]
    forward = {f: FrameResult(truth[k] @ _off_x(2.2 * k), True, {}) for k, f in enumerate(ids)}
    backward = {f: FrameResult(truth[k] if k >= 6 else truth[k] @ _off_x(-12), True, {}) for k, f in enumerate(ids)}
    aligned = {f: r.pose for f, r in backward.items()}
    # without the anchors the all-forward path looks smooth; with them its step into the far anchor counts
    assert best_switch(ids, forward, backward, aligned, False, 5.0, 0.01)[0] == 20
    s, (deg, _), _ = best_switch(ids, forward, backward, aligned, False, 5.0, 0.01, (truth[0], truth[-1]))
    assert s < 20 and deg >= 5.0
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01, anchors=(truth[0], truth[-1]))
    errors = {k: pose_difference(out[f].pose, truth[k])[0] for k, f in enumerate(ids[1:-1], start=1)}
    assert max(errors.values()) < 13.0  # the all-forward path: up to 42 deg
    assert all(flag_reasons(out[ids[k]].figures, TrackingConfig()) for k in errors if errors[k] > 5.0)


def test_a_link_from_one_chain_alone_is_not_trusted():
    from annotate.tracking.reconcile import SINGLE_LINK_SIGMA

    truth = _truth(11)
    placed = {"a": truth[0], "b": truth[10] @ _block(Rotation.from_euler("z", 2, degrees=True))}
    drifted = {"b": FrameResult(truth[10] @ _block(Rotation.from_euler("x", 7, degrees=True)), True, {})}
    lost = {"a": FrameResult(truth[0] @ _block(Rotation.from_euler("x", 20, degrees=True)), True, {})}
    offsets = chain_frame_offsets(["a", "b"], placed, [drifted], [lost], symmetric=False)
    assert np.allclose(offsets[1], np.eye(4))  # the 7 deg drift of the forward chain alone is not taken as the link
    small = {"b": FrameResult(placed["b"] @ _block(Rotation.from_euler("x", 3, degrees=True)), True, {})}
    # a small one is, as it is when the placed boxes are said to carry no information ...
    offsets = chain_frame_offsets(["a", "b"], placed, [small], [lost], symmetric=False, placement_sigma=(0.0, 0.0))
    assert abs(pose_difference(np.eye(4), offsets[1])[0] - 3.0) < 1e-4
    # ... and weighed against the placed boxes otherwise (1 deg each, against a lone chain's sigma)
    offsets = chain_frame_offsets(["a", "b"], placed, [small], [lost], symmetric=False, placement_sigma=(1.0, 0.002))
    expected = 3.0 * _link_weight(1.0, SINGLE_LINK_SIGMA[0])
    assert 0.5 < expected < 3.0 and abs(pose_difference(np.eye(4), offsets[1])[0] - expected) < 1e-6


def test_two_agreeing_chains_set_the_link_by_their_agreement():
    from annotate.tracking.reconcile import LINK_FLOOR_SIGMA

    truth = _truth(11)
    placed = {"a": truth[0], "b": truth[10]}
    x = lambda deg: _block(Rotation.from_euler("x", deg, degrees=True))  # noqa: E731
    # both chains arrive 3 deg (about x) off the placed box: the same link twice
    offsets = chain_frame_offsets(["a", "b"], placed, [{"b": FrameResult(placed["b"] @ x(3), True, {})}],
                                  [{"a": FrameResult(placed["a"] @ x(-3), True, {})}], symmetric=False)
    # their mean has half the floor's variance
    expected = 3.0 * _link_weight(1.0, LINK_FLOOR_SIGMA[0] / np.sqrt(2))
    assert abs(pose_difference(np.eye(4), offsets[1])[0] - expected) < 1e-6
    # arriving 2 and 6 deg off (4 apart, about one axis): each chain's variance per axis is 4^2 / 6,
    # their mean's 4^2 / 12 (the gap spread over 3 axes, halved for the mean)
    offsets = chain_frame_offsets(["a", "b"], placed, [{"b": FrameResult(placed["b"] @ x(2), True, {})}],
                                  [{"a": FrameResult(placed["a"] @ x(-6), True, {})}], symmetric=False)
    expected = 4.0 * _link_weight(1.0, 4.0 / np.sqrt(12))
    assert abs(pose_difference(np.eye(4), offsets[1])[0] - expected) < 1e-6


def test_anchor_frames_are_the_least_squares_pose_graph_solution():
    # four anchors, placed boxes off about x by known angles, both chains exact: every link is measured
    # with the floor's variance; the solution is checked against a dense weighted least squares over
    # the angles (a second implementation: rotations about one axis add)
    from annotate.tracking.reconcile import LINK_FLOOR_SIGMA

    truth = _truth(31)
    ids = ["0", "10", "20", "30"]
    off = np.array([1.5, -2.0, 0.5, 2.5])  # deg: E_k = rot_x(off[k])
    placed = {f: truth[int(f)] @ _block(Rotation.from_euler("x", d, degrees=True)) for f, d in zip(ids, off)}
    # a chain from anchor k lives in anchor k's object frame: truth @ E_k
    forwards = [{ids[k + 1]: FrameResult(truth[int(ids[k + 1])] @ _block(Rotation.from_euler("x", off[k], degrees=True)), True, {})} for k in range(3)]
    backwards = [{ids[k]: FrameResult(truth[int(ids[k])] @ _block(Rotation.from_euler("x", off[k + 1], degrees=True)), True, {})} for k in range(3)]
    offsets = chain_frame_offsets(ids, placed, forwards, backwards, symmetric=False, placement_sigma=(1.0, 0.002))
    link_sigma = LINK_FLOOR_SIGMA[0] / np.sqrt(2)
    rows, rhs = [], []
    for k in range(4):  # e_k ~ 0, sigma 1 deg
        rows.append(np.eye(4)[k] / 1.0)
        rhs.append(0.0)
    for k in range(3):  # e_k - e_(k+1) ~ off_k - off_(k+1)
        rows.append((np.eye(4)[k] - np.eye(4)[k + 1]) / link_sigma)
        rhs.append((off[k] - off[k + 1]) / link_sigma)
    estimate = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    for k in range(4):
        # D_k = E_k^-1 E_0: a turn about x by estimate_0 - estimate_k
        expected = _block(Rotation.from_euler("x", estimate[0] - estimate[k], degrees=True))
        assert pose_difference(offsets[k], expected)[0] < 1e-5  # arccos resolution
    # the anchors' frames brought together: the placed boxes differ by up to 4.5 deg, the estimate from the
    # truth's relative offsets by at most 0.3 (exact links, but a floor on their sigma: some pull to the boxes stays)
    assert np.max(np.abs((estimate - estimate[0]) - (off - off[0]))) < 0.3


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
    true_link = np.linalg.inv(E_b)  # E_b^-1 E_a: brings anchor b's chains into anchor a's object frame
    # the link where the chains meet (frame 4: 1 deg drift), taken as it is without a placement sigma ...
    offsets = chain_frame_offsets(["0", "10"], placed, [forward], [backward], symmetric=False, placement_sigma=(0.0, 0.0))
    assert pose_difference(offsets[1], true_link)[0] < 1.01 and pose_difference(np.eye(4), true_link)[0] > 2.99
    measured = offsets[1]
    # ... and weighed against the placed boxes with its meeting sigma
    from annotate.tracking.reconcile import MEETING_LINK_SIGMA

    offsets = chain_frame_offsets(["0", "10"], placed, [forward], [backward], symmetric=False, placement_sigma=(1.0, 0.002))
    share = _link_weight(1.0, MEETING_LINK_SIGMA[0])
    expected = Rotation.from_matrix(measured[:3, :3]).as_rotvec() * share
    assert np.allclose(Rotation.from_matrix(offsets[1][:3, :3]).as_rotvec(), expected, atol=1e-9)


def test_a_frame_the_recheck_clears_needs_a_trusted_neighbour():
    from annotate.tracking.refine import _vouched

    order = [str(k) for k in range(8)]
    before = {f: FrameResult(np.eye(4), True, {"chain_disagreement_deg": 20.0 if f in "2345" else 0.0}) for f in order}
    never_suspect = {"0", "1", "6", "7"}

    def cleared(frames):
        return {f: FrameResult(np.eye(4), True, {"chain_disagreement_deg": 0.5}) if f in frames else r for f, r in before.items()}

    def kept(out):
        return {f for f in order if out[f] is not before[f]}

    # frame 3 alone cleared, between frames 2 and 4 whose disagreement stands: it keeps its own
    assert kept(_vouched(cleared({"3"}), before, order, never_suspect)) == set()
    # runs joined to a frame never suspect, from the left (1 -> 2 -> 3) and from the right (6 -> 5 -> 4)
    assert kept(_vouched(cleared({"2", "3"}), before, order, never_suspect)) == {"2", "3"}
    assert kept(_vouched(cleared({"3", "4", "5"}), before, order, never_suspect)) == {"3", "4", "5"}
    # a failed neighbour vouches for nothing: with frame 6 failed, 5 and 4 stand alone
    assert kept(_vouched(cleared({"4", "5"}), before, order, never_suspect - {"6"})) == set()


def test_a_symmetric_objects_links_arrive_spun_about_its_axis():
    # a can: the chains may arrive turned by any angle about the axis (y); anchor a's box is 3 mm off along x,
    # b's is exact. The forward chain arrives at b spun by 90 deg, the backward one at a by -30 deg: each sees
    # a's offset turned by its spin (0, 0, -3 mm and 2.6, 0, 1.5 mm), not as it is
    truth = _truth(11)
    E_a = np.eye(4)
    E_a[:3, 3] = [0.003, 0.0, 0.0]
    placed = {"a": truth[0] @ E_a, "b": truth[10]}
    spin = lambda deg: _block(Rotation.from_euler("y", deg, degrees=True))  # noqa: E731
    forward = {"b": FrameResult(truth[10] @ spin(90) @ E_a, True, {})}  # chain from a: a's object frame, spun
    backward = {"a": FrameResult(truth[0] @ spin(-30), True, {})}  # chain from b: b's object frame, spun
    offsets = chain_frame_offsets(["a", "b"], placed, [forward], [backward], symmetric=True, placement_sigma=(0.0, 0.0))
    # D_b = E_b^-1 E_a: the chains from b brought into a's frame, 3 mm along x (the spin about y is free)
    assert np.linalg.norm(offsets[1][:3, 3] - E_a[:3, 3]) < 1e-6
    assert pose_difference(offsets[1], E_a, symmetric=True)[0] < 1e-4


def test_a_second_chain_that_fits_clearly_worse_does_not_flag_the_end_frames():
    from types import SimpleNamespace

    from annotate.tracking import TrackingConfig
    from annotate.tracking.refine import recheck_single_chains

    truth = _truth(8)
    ids = [str(k) for k in range(8)]

    class Tracker:
        """Registration stand-in: a start within 5 deg of the truth lands on it (fitness 0.9); one further off
        stays where it is, at fitness ``lost`` (a worse minimum, or with ``lost`` 0.9 a rival as good)."""

        def __init__(self, lost):
            self.config, self.symmetric, self.lost = TrackingConfig(), False, lost

        def register(self, frame_id, init, model, hits):
            T = truth[int(frame_id)]
            if pose_difference(init, T)[0] < 5.0:
                return FrameResult(T, True, {"fitness": 0.9})
            return FrameResult(init, True, {"fitness": self.lost})

    results = {f: FrameResult(T, True, {"fitness": 0.9}) for f, T in zip(ids, truth)}
    # the second chain runs outward from the manual frame 2 (after its inner neighbour 3); frame 2's pose is
    # 30 deg off, so the constant-velocity starts of frames 1 and 0 are far off too
    results["2"] = FrameResult(truth[2] @ _block(Rotation.from_euler("x", 30, degrees=True)), True, {"fitness": 0.9})
    model = SimpleNamespace(frames=10)
    worse = recheck_single_chains(Tracker(lost=0.6), results, [["3", "2", "1", "0"]], model=model)
    rival = recheck_single_chains(Tracker(lost=0.9), results, [["3", "2", "1", "0"]], model=model)
    for f in ("1", "0"):
        # a clearly worse fit: no rival, the disagreement is the final pose's own re-registration (0)
        assert worse[f].figures["chain_disagreement_deg"] < 1e-4 and worse[f].figures["second_chain_fitness"] == 0.6
        # a fit as good: the disagreement stands
        assert rival[f].figures["chain_disagreement_deg"] > 20.0 and "second_chain_fitness" not in rival[f].figures


def test_runs_of_free_spin_frames_are_measured_and_long_or_one_sided_ones_flagged():
    ids = [f"{k:07d}" for k in range(20)]
    # free: 0-2 (before the first fixing frame), 5-6 (short, inside), 8-15 with the manual frame 11
    # splitting it into 8-10 and 12-15, 17-19 (after the last fixing frame)
    free = {ids[k] for k in [0, 1, 2, 5, 6, 8, 9, 10, 11, 12, 13, 14, 15, 17, 18, 19]}
    runs = free_spin_runs(ids, free, {ids[11]})
    assert set(runs) == free - {ids[11]}
    assert [runs[ids[k]] for k in (0, 2, 5, 6, 8, 10, 12, 15, 17, 19)] == [
        (3, True), (3, True), (2, False), (2, False), (3, False), (3, False), (4, False), (4, False), (3, True), (3, True)]
    assert free_spin_runs(ids, set(ids), set()) == {f: (20, True) for f in ids}
    assert free_spin_runs(ids, set(), {ids[3]}) == {}
    config = TrackingConfig(max_free_spin_run=3)
    assert flag_reasons({"free_spin_run": 3, "free_spin_end": False}, config) == []
    assert flag_reasons({"free_spin_run": 4, "free_spin_end": False}, config) == ["its shape leaves the spin about the axis free for 4 frames in a row"]
    assert len(flag_reasons({"free_spin_run": 1, "free_spin_end": True}, config)) == 1
    assert flag_reasons({"free_spin_run": 9, "free_spin_end": True}, TrackingConfig(max_free_spin_run=0)) == []


def test_a_weak_second_chain_and_a_far_rejected_refinement_are_flagged():
    config = TrackingConfig()  # min fitness 0.5, refinement steps 10 deg / 20 mm
    assert not flag_reasons({"fitness": 0.52, "second_chain_fitness": 0.55}, config)
    assert any("second tracking chain" in r for r in flag_reasons({"fitness": 0.52, "second_chain_fitness": 0.43}, config))
    # a rejected step within the limits was a small correction turned down; beyond them a rival pose
    assert not flag_reasons({"refine_rejected_deg": 9.0, "refine_rejected_m": 0.019}, config)
    assert any("10.4 deg and 29 mm" in r for r in flag_reasons({"refine_rejected_deg": 10.37, "refine_rejected_m": 0.029}, config))
    assert flag_reasons({"refine_rejected_deg": 2.0, "refine_rejected_m": 0.021}, config)


def test_frames_beyond_the_seam_are_only_as_good_as_their_chain_back_to_its_anchor():
    # both chains right in frames 12-18 (the seam); the forward chain lost after 18, the backward chain
    # 8 deg off in frames 21-26 (a jump at 27 -> 26 and back at 21 -> 20): the chains' gap at the seam says
    # nothing about those frames, the backward chain's own jump on its way from frame 30 does
    truth = _truth(31)
    ids, forward, backward = _chains(truth, lost_after=18, found_from=12)
    for k in range(21, 27):
        backward[ids[k]] = FrameResult(truth[k] @ _off_x(8), True, {})
    out = blend_chains(ids, forward, backward, symmetric=False, max_deg=5.0, max_m=0.01, anchors=(truth[0], truth[-1]))
    errors = {k: pose_difference(out[ids[k]].pose, truth[k])[0] for k in range(1, 30)}
    figures = {k: out[ids[k]].figures for k in range(1, 30)}
    assert all(abs(errors[k] - 8.0) < 1e-4 for k in range(21, 27)) and all(errors[k] < 1e-4 for k in range(27, 30))
    assert all(figures[k]["chain_disagreement_deg"] > 5.0 for k in range(21, 27))  # the seam's own gap: 0
    assert all(figures[k]["chain_disagreement_deg"] < 1.0 for k in range(27, 30))  # no jump between them and frame 30


def test_a_frame_with_one_chain_is_judged_against_that_chain_alone():
    # before the first manual frame one chain ran: a one-pose witness tuple, the distance to it
    truth = _truth(3)
    final = {"0": truth[0] @ _block(Rotation.from_euler("y", 12, degrees=True))}
    departures = chain_departures(final, {"0": (truth[0],)}, symmetric=False)
    assert abs(departures["0"][0] - 12.0) < 1e-4 and departures["0"][1] < 1e-9


def test_short_unflagged_runs_between_flagged_frames_are_found():
    ids = [f"{k:02d}" for k in range(16)]
    flagged = {ids[k] for k in (2, 3, 5, 8, 12)}  # gaps: 4 (1 frame), 6-7 (2), 9-11 (3), none before 2 / after 12
    tracked = set(ids) - {ids[7]}  # 7 is a manual frame: never flagged for its neighbours
    gaps = flagged_gaps(ids, flagged, set(ids), max_gap=2)
    assert gaps == {ids[4]: (ids[3], ids[5]), ids[6]: (ids[5], ids[8]), ids[7]: (ids[5], ids[8])}
    assert flagged_gaps(ids, flagged, tracked, max_gap=2) == {ids[4]: (ids[3], ids[5])}
    assert set(flagged_gaps(ids, flagged, set(ids), max_gap=3)) == {ids[k] for k in (4, 6, 7, 9, 10, 11)}
    assert flagged_gaps(ids, flagged, set(ids), max_gap=0) == {}
    assert flagged_gaps(ids, set(), set(ids), max_gap=2) == {}


def test_a_long_constant_velocity_prediction_stays_rigid():
    """propagate.predict made rigid: a chain predicting from its own predictions (each registration only turns
    them, by a rotation) drifted off the rotations 2.4 times further each frame; 0.7 after 40 frames on a bowl."""
    from annotate.tracking.propagate import predict

    step = np.eye(4)
    step[:3, :3], step[:3, 3] = Rotation.from_rotvec([0.01, 0.03, -0.02]).as_matrix(), [0.001, 0.0, -0.002]
    start = np.eye(4)
    start[:3, 3] = [0.0, 0.0, 0.6]
    before, previous = start, step @ start
    previous[:3, :3] *= 1.0 + 1e-9  # a rounding-sized drift off the rotations
    for _ in range(100):
        previous, before = predict(previous, before), previous
    R = previous[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12  # without the fix: 1e-9 * 2.4^100, far beyond 1
    # and it still moves by the step each frame: 101 steps from the start
    np.testing.assert_allclose(previous, np.linalg.matrix_power(step, 101) @ start, atol=1e-6)


def _spin_deg(R: np.ndarray) -> float:
    return float(Rotation.from_matrix(R).as_rotvec(degrees=True)[1])


def test_a_manual_frame_whose_spin_is_free_does_not_set_the_object_frames_spin():
    """reconcile.common_correction: a mug with 3 manual frames, one with its handle hidden: its tracked spin is
    +4.1 deg against -1.0 and -0.9 for the others, and counted, it would hold every frame's spin 1.6 deg off."""
    from annotate.tracking.reconcile import common_correction

    def pose(spin_deg: float, tilt_deg: float = 0.0, t=(0.0, 0.0, 0.6)) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = Rotation.from_rotvec(np.radians([tilt_deg, spin_deg, 0.0])).as_matrix()
        out[:3, 3] = t
        return out

    # the truth is the identity in each frame's object frame; tracked poses share an object frame spun by +1 deg
    # from it, except the free frame "a", whose spin came out 5 deg further; the placed boxes are off by 0.3-0.5 deg
    tracked = {"a": pose(6.0), "b": pose(1.0), "c": pose(1.0, 0.5)}
    placed = {"a": pose(0.3), "b": pose(-0.4), "c": pose(0.5, 0.5)}
    dragged = common_correction(tracked, placed, symmetric=False)
    free = common_correction(tracked, placed, symmetric=False, free_spin={"a"})
    # each manual frame asks for a spin of placed - tracked: -5.7, -1.4 and -0.5 deg. The frames end 1 deg + the
    # correction off: with "a", 1 - 2.53 = -1.53 deg; without it, 1 - 0.95 = 0.05 deg
    np.testing.assert_allclose(_spin_deg(dragged[:3, :3]), -2.53, atol=0.03)
    np.testing.assert_allclose(_spin_deg(free[:3, :3]), -0.95, atol=0.03)
    # the tilt and the translation are still taken from all three
    np.testing.assert_allclose(free[:3, 3], dragged[:3, 3], atol=1e-12)
    # every manual frame free, or none: as before
    np.testing.assert_allclose(common_correction(tracked, placed, False, {"a", "b", "c"}), dragged, atol=1e-12)


def test_flags_grow_from_a_flagged_frame_over_neighbours_whose_chain_figures_are_already_high():
    order = [f"{k:07d}" for k in range(9)]
    limits = {"chain_disagreement_deg": 5.0, "chain_disagreement_m": 0.01, "chain_departure_deg": 8.0}
    degrees = [0.5, 0.9, 1.4, 3.1, 6.0, 2.8, 4.4, 1.0, 3.5]  # frame 4 crosses the limit; 3, 5, 6 are half-way there
    figures = {f: {"chain_disagreement_deg": d, "chain_disagreement_m": 0.002} for f, d in zip(order, degrees)}
    figures[order[2]]["chain_departure_deg"] = 3.0  # 37 % of its limit: stays
    figures[order[8]]["chain_disagreement_m"] = 0.009  # high, but no flagged frame beside it
    eligible = set(order) - {order[6]}  # frame 6 is an anchor: never flagged by its neighbours
    grown = flags_grown(order, {order[4]}, eligible, figures, limits, 0.5, 2)
    assert sorted(grown) == [order[3], order[5]]
    assert grown[order[3]] == (order[4], "chain_disagreement_deg", 3.1, 5.0)
    # an anchor in between stops the growth; without it, the flags run on to frame 6 and stop at 7 (1.0 deg)
    grown = flags_grown(order, {order[4]}, set(order), figures, limits, 0.5, 2)
    assert sorted(grown) == [order[3], order[5], order[6]] and grown[order[6]][0] == order[5]
    # at most ``reach`` frames out: one step reaches frames 3 and 5 only
    assert sorted(flags_grown(order, {order[4]}, set(order), figures, limits, 0.5, 1)) == [order[3], order[5]]
    assert flags_grown(order, set(), set(order), figures, limits, 0.5, 2) == {}
