"""Reconciling the chains between two manual frames, and the anchors' common object frame.

Between manual frames a and b, the forward chain (from a) drifts with distance from a and the
backward chain (from b) with distance from b. Blending them with weights that fall linearly
with that distance is the closed-form solution of the pose graph a-...-b whose two chains have
drift growing with length: the error left over at the far anchor is spread along the chain
instead of piling up at one end. Their disagreement is kept as a quality figure.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from .propagate import predict
from .quality import pose_difference
from annotate.symmetry_axis import closest_about_y
from .tracker import FrameResult


def interpolate(Ta: np.ndarray, Tb: np.ndarray, w: float) -> np.ndarray:
    """Pose (4x4) a fraction ``w`` (0 = Ta, 1 = Tb) of the way along the geodesic from Ta to Tb."""
    out = np.eye(4)
    delta = Rotation.from_matrix(Ta[:3, :3].T @ Tb[:3, :3]).as_rotvec()
    out[:3, :3] = Ta[:3, :3] @ Rotation.from_rotvec(w * delta).as_matrix()
    out[:3, 3] = (1 - w) * Ta[:3, 3] + w * Tb[:3, 3]
    return out


def blend_chains(
    frame_ids: list[str],
    forward: dict[str, FrameResult],
    backward: dict[str, FrameResult],
    symmetric: bool,
    max_deg: float = np.inf,
    max_m: float = np.inf,
    ramp: int = 2,
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, FrameResult]:
    """Blend the forward chain (from ``frame_ids[0]``) and the backward chain (from ``frame_ids[-1]``).

    Frames strictly between the two anchors get the blended pose, the better of the two chains'
    figures and the chains' disagreement (``chain_disagreement_deg``, ``chain_disagreement_m``).
    A frame that failed in one chain takes the other's pose.

    Where the chains' rotation gap jumps by more than ``max_deg`` from one frame to the next, one of
    them lost the object and the linear blend would put the frames between both stories. If they meet again
    (a frame where they agree within twice the thresholds: the seam), the frames take the forward chain
    before the seam and the backward chain after it (blended over up to ``ramp`` frames on each side
    where they still meet): one path joining both anchors, each part carried by the chain that was still
    on the object. Those frames get ``chain_switch: true`` and keep the raw disagreement as
    ``chain_disagreement_raw_deg`` / ``_m``; the ones a jump separates from the seam (the lost
    chain's stretch) get the seam's disagreement as ``chain_disagreement_deg`` / ``_m`` (the path's
    own inconsistency), or the worst departure from constant-velocity motion of the chain that carries
    them between them and its anchor where that is larger (a chain that jumped on the way can carry its
    frames far off while the seam's gap stays small), the others keep the raw one (both chains meant to be
    on the object). A typical case: the backward chain jumps where the object turns a new side to the
    camera, the forward one drifts off later, and the two meet in between.

    If no frame has the two within twice the thresholds, the path switches at once where it moves most
    smoothly (:func:`best_switch`, the path's steps into the anchors counted with ``anchors``: the two
    anchor poses), and a frame a jump separates from the switch gets, as its disagreement, the worst
    departure between it and the anchor its part of the path comes from. The linear blend would mix the
    lost chain into those frames.
    """
    n = len(frame_ids) - 1
    inner = frame_ids[1:-1]
    aligned: dict[str, np.ndarray] = {}
    gaps: dict[str, tuple[float, float]] = {}
    for frame_id in inner:
        f, b = forward[frame_id], backward[frame_id]
        Tb = b.pose.copy()
        if symmetric:
            Tb[:3, :3] = closest_about_y(Tb[:3, :3], f.pose[:3, :3])
        aligned[frame_id] = Tb
        if f.ok and b.ok:
            gaps[frame_id] = pose_difference(f.pose, Tb, symmetric)
    seam = None
    # a chain that lost the object jumps: the gap changes by more than the threshold from one frame to
    # the next (by several degrees at once); two chains drifting apart (a shallow bowl's slow 3 deg
    # per frame) are what the linear blend is for. A centre offset alone is the anchors' own (a dropped link).
    # A one-frame excursion (a bowl's chain 15 deg off for one frame, back the next) is no loss: the gaps'
    # running median of 3 sees through it (except at an end frame, see below).
    gapped = [frame_ids.index(f) for f in inner if f in gaps]
    g = np.array([gaps[frame_ids[k]][0] for k in gapped])
    steps = np.zeros(0)
    if len(g) >= 3:
        # the end frames repeated, so that a chain lost between the first two inner frames (or the last two) shows
        # too; an excursion of an end frame alone then shows as well, and the frame's own doubt covers it (best_switch)
        padded = np.pad(g, 1, mode="edge")
        steps = np.abs(np.diff(np.median(np.stack([padded[:-2], padded[1:-1], padded[2:]]), axis=0)))
    # step j lies between gapped frames j and j + 1 (the running median's centres)
    jumps = [gapped[j] for j in np.flatnonzero(steps > max_deg)]
    own_gap: dict[int, tuple[float, float]] | None = None  # set where the path switches at once
    # both chains' departures from constant-velocity motion: the switch and the both-chains-jumped flag read them
    departures = _departure_maxima(frame_ids, forward, backward, aligned, symmetric, max_deg, max_m, anchors)
    if jumps:
        # the frame where the two chains come closest, in units of the thresholds
        k_best = min(gaps, key=lambda g: max(gaps[g][0] / max_deg, gaps[g][1] / max_m))
        # the seam also holds the two anchors' own placement errors (a link chain_frame_offsets
        # dropped leaves them): twice the thresholds
        meet = {frame_ids.index(g) for g, (d, m) in gaps.items() if d <= 2 * max_deg and m <= 2 * max_m}
        if frame_ids.index(k_best) in meet:
            seam = frame_ids.index(k_best)
            _, _, own_meet = best_switch(frame_ids, forward, backward, aligned, symmetric, max_deg, max_m, anchors, at=seam, departures=departures)
            # the hand-over ramps over the frames around the seam where the chains still meet (at most ``ramp``
            # each side): a ramp reaching a frame where one chain is lost would mix the lost pose in
            lo, hi = seam, seam
            while lo - 1 in meet and seam - (lo - 1) <= ramp:
                lo -= 1
            while hi + 1 in meet and (hi + 1) - seam <= ramp:
                hi += 1
        else:
            # no frame has both chains on the object: the seam is where the path (forward chain before it,
            # backward chain from it) moves most smoothly, switched at once
            seam, _, own_gap = best_switch(frame_ids, forward, backward, aligned, symmetric, max_deg, max_m, anchors, departures=departures)
            lo, hi = seam, seam - 1
    jumped = both_chains_jumped(departures)
    out: dict[str, FrameResult] = {}
    for k, frame_id in enumerate(inner, start=1):
        f, b = forward[frame_id], backward[frame_id]
        if f.ok and not b.ok:
            out[frame_id] = FrameResult(f.pose, True, dict(f.figures))
            continue
        if b.ok and not f.ok:
            out[frame_id] = FrameResult(b.pose, True, dict(b.figures))
            continue
        Tb = aligned[frame_id]
        figures = dict(f.figures if f.figures.get("fitness", 0) >= b.figures.get("fitness", 0) else b.figures)
        deg, metres = gaps.get(frame_id) or pose_difference(f.pose, Tb, symmetric)
        if seam is None:
            pose = interpolate(f.pose, Tb, k / n)
        else:
            w = float(np.clip((k - lo + 1) / (hi - lo + 2), 0.0, 1.0))
            pose = interpolate(f.pose, Tb, w)
            figures["chain_switch"] = True
            figures["chain_disagreement_raw_deg"], figures["chain_disagreement_raw_m"] = deg, metres
            # the loss explains the gap only of the frames it separates from the seam; between the seam and
            # a loss-free stretch the two chains are both meant to be on the object, and their gap stands
            if own_gap is None and any(min(k, seam) <= j < max(k, seam) for j in jumps):
                # ... and the chain that carries it there must not have jumped on its way from its anchor
                deg, metres = (max(a, b) for a, b in zip(gaps[frame_ids[seam]], own_meet[k]))
            elif own_gap is not None and any(min(k, seam - 1) <= j < max(k, seam) for j in jumps):
                # a path switched at once (between seam - 1 and seam); jump j lies between frames j and j + 1
                deg, metres = own_gap[k]
            if (k == 1 and k < seam and 1 in jumps) or (k == n - 1 and k >= seam and n - 2 in jumps):
                # a jump right next to an end frame on its own side of the seam: the repeated end frames let an excursion
                # of that frame alone count as a loss, and its chain has no departure of its own to show (that needs
                # two frames before it), so its chains' raw gap stands
                deg, metres = max(deg, figures["chain_disagreement_raw_deg"]), max(metres, figures["chain_disagreement_raw_m"])
        figures["chain_disagreement_deg"] = deg
        figures["chain_disagreement_m"] = metres
        if k in jumped and (jumped[k][0] > max_deg or jumped[k][1] > max_m):
            # neither chain vouches for the frame: a flag only (quality.pose_reasons), the poses are as before
            figures["chains_jumped_deg"], figures["chains_jumped_m"] = jumped[k]
        out[frame_id] = FrameResult(pose, f.ok or b.ok, figures)
    return out


def best_switch(
    frame_ids: list[str],
    forward: dict[str, FrameResult],
    backward: dict[str, FrameResult],
    aligned: dict[str, np.ndarray],
    symmetric: bool,
    max_deg: float,
    max_m: float,
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
    at: int | None = None,
    departures: Departures | None = None,
) -> tuple[int, tuple[float, float], dict[int, tuple[float, float]]]:
    """The index s (1..n) where the path of the forward chain's poses before s and the backward chain's
    from s on (``aligned``: the backward chain's poses aligned to the forward chain) moves most smoothly,
    the (deg, m) of that path's worst departure, and per inner index the (deg, m) of the worst departure
    between that frame and the anchor its part of the path starts from (a frame that a loss separates from
    the switch gets that as its chains' disagreement: its pose comes from that anchor through that chain alone).

    A chain that loses the object jumps: its pose departs from the constant-velocity prediction by a
    loss's size (several to tens of degrees) instead of the hand's noise (about 1 deg). Each candidate path
    is scored by its worst departure in units of the thresholds, inside the forward part, inside the
    backward part and across the switch (each side's prediction of the other). With ``anchors`` (the
    poses of frame_ids[0] and [-1], where the chains start), the path's steps into them count too, so a
    chain that drifts smoothly away from the far anchor does not win. A departure involving a frame that
    failed in its chain is not scored (that frame keeps a prediction, and takes the other chain's pose).
    ``departures``: the same arguments' :func:`_departure_maxima`, when the caller has it.
    """
    n = len(frame_ids) - 1
    if departures is None:
        departures = _departure_maxima(frame_ids, forward, backward, aligned, symmetric, max_deg, max_m, anchors)
    F, B, ok_f, ok_b, before, after = departures
    cost = partial(_cost, symmetric=symmetric, max_deg=max_deg, max_m=max_m)
    best, best_score = n, (np.inf, 0.0, 0.0)
    for s in ([at] if at is not None else range(1, n + 1)):
        # across the switch (between s - 1 and s): each side's prediction of the other's pose
        sides = []
        if _has(F, ok_f, s - 1, s - 2) and _has(B, ok_b, s):
            sides.append(cost(predict(F[s - 1], F[s - 2]), B[s]))
        if _has(B, ok_b, s, s + 1) and _has(F, ok_f, s - 1):
            sides.append(cost(predict(B[s], B[s + 1]), F[s - 1]))
        if not sides and 1 < s < n and _has(F, ok_f, s - 1) and _has(B, ok_b, s):
            sides.append(cost(F[s - 1], B[s]))
        score = max([before[s], after[s]] + sides)
        if score[0] < best_score[0]:
            best, best_score = s, score
    # each frame's own doubt: the worst departure between it and the anchor its part of the path starts from
    own = {k: before[k + 1][1:] if k < best else after[k][1:] for k in range(1, n)}
    return best, (best_score[1], best_score[2]), own


def _cost(P: np.ndarray, Q: np.ndarray, symmetric: bool, max_deg: float, max_m: float) -> tuple[float, float, float]:
    """The difference of two poses as (the larger of deg / max_deg and m / max_m, deg, m)."""
    deg, metres = pose_difference(P, Q, symmetric)
    return max(deg / max_deg, metres / max_m), deg, metres


def _has(chain: dict, ok: dict, *ks: int) -> bool:
    """Whether ``chain`` holds a registered pose at every index of ``ks``."""
    return all(k in chain and ok[k] for k in ks)


class Departures(NamedTuple):
    """Both chains of one stretch by inner index, and their running maxima of departures (:func:`_departure_maxima`)."""

    F: dict[int, np.ndarray]
    B: dict[int, np.ndarray]
    ok_f: dict[int, bool]
    ok_b: dict[int, bool]
    before: list[tuple[float, float, float]]
    after: list[tuple[float, float, float]]


def _departure_maxima(frame_ids, forward, backward, aligned, symmetric, max_deg, max_m, anchors) -> Departures:
    """Both chains' poses by inner index (forward F, backward B aligned to it; with ``anchors``, F[0] and B[n] are
    the anchors' poses), whether each registered, and the running maxima of their departures from constant-velocity
    motion, as (score in units of the thresholds, deg, m): ``before[k]`` the forward chain's worst over frames 1..k-1,
    ``after[k]`` the backward chain's over frames k..n-1 (see :func:`best_switch`)."""
    n = len(frame_ids) - 1
    F = {k: forward[frame_ids[k]].pose for k in range(1, n)}
    B = {k: aligned[frame_ids[k]] for k in range(1, n)}
    ok_f = {k: forward[frame_ids[k]].ok for k in range(1, n)}
    ok_b = {k: backward[frame_ids[k]].ok for k in range(1, n)}
    if anchors is not None:
        F[0], B[n] = anchors
        ok_f[0] = ok_b[n] = True
    cost = partial(_cost, symmetric=symmetric, max_deg=max_deg, max_m=max_m)
    # departures inside each chain: the forward one predicted from the two frames before, the backward one from the two after
    inside_f = {k: cost(predict(F[k - 1], F[k - 2]), F[k]) for k in range(2, n) if _has(F, ok_f, k, k - 1, k - 2)}
    inside_b = {k: cost(predict(B[k + 1], B[k + 2]), B[k]) for k in range(1, n - 1) if _has(B, ok_b, k, k + 1, k + 2)}
    none = (0.0, 0.0, 0.0)
    before = [none] * (n + 1)
    for k in range(1, n + 1):
        before[k] = max(before[k - 1], inside_f.get(k - 1, none))
    after = [none] * (n + 1)
    for k in range(n - 1, 0, -1):
        after[k] = max(after[k + 1], inside_b.get(k, none))
    return Departures(F, B, ok_f, ok_b, before, after)


def both_chains_jumped(departures: Departures) -> dict[int, tuple[float, float]]:
    """Per inner index whose two chains both registered (``departures``: one stretch's :func:`_departure_maxima`):
    the (deg, m) of the smaller of the two chains' worst jumps on their way from their anchors to the frame (the
    forward chain's between the first anchor and the frame, the backward chain's between the frame and the last
    anchor), as departures from constant-velocity motion. Where both exceed the thresholds, neither chain
    vouches for the frame, whatever their gap says: two chains that each jumped on their way can agree within
    the thresholds on frames that both carry far off.
    """
    n = len(departures.before) - 1
    before, after = departures.before, departures.after
    return {k: min(before[k + 1], after[k])[1:] for k in range(1, n) if departures.ok_f[k] and departures.ok_b[k]}


def common_correction(tracked: dict[str, np.ndarray], placed: dict[str, np.ndarray], symmetric: bool, free_spin: set[str] = frozenset()) -> np.ndarray:
    """The object-frame correction C (4x4) that best fits the placed boxes: tracked[m] @ C ~ placed[m].

    ``tracked`` poses are mutually consistent but share an arbitrary object frame; each manual
    frame m says the frame should be ``inv(tracked[m]) @ placed[m]``. Averaging those (mean
    rotation, mean translation) averages out the independent errors of hand placement.
    For symmetric objects each one's free rotation about y is first made consistent with the first; so is, for an
    object without symmetry, that of each manual frame in ``free_spin`` (its shape leaves the spin free: a mug with
    its handle hidden) with the mean of the others: such a frame's tracked spin comes from its neighbours, and one
    spin a few degrees off would turn every frame by its share of the mean.

    Not used: taking the translation from the tight box of the tracked model instead (the points' 0-2 % and
    98-100 % quantiles per axis): the tracked poses' common offset is a few mm at most, while the model's box can
    be off by more (a hand left in the model, a side never seen), and the centres came out further off.
    """
    corrections = [np.linalg.inv(tracked[m]) @ placed[m] for m in placed]
    rotations = [c[:3, :3] for c in corrections]
    if symmetric:
        rotations = [closest_about_y(R, rotations[0]) for R in rotations]
    elif free_spin and any(m not in free_spin for m in placed):
        # a manual frame whose shape leaves the spin free (a mug's handle hidden) has a tracked spin from its
        # neighbours, not from its own points: its spin says nothing about the object frame's
        reference = Rotation.from_matrix(np.stack([R for m, R in zip(placed, rotations) if m not in free_spin])).mean().as_matrix()
        rotations = [closest_about_y(R, reference) if m in free_spin else R for m, R in zip(placed, rotations)]
    # the median-nearest corrections only: one badly placed (or badly tracked) anchor must not drag the rest
    if len(corrections) >= 3:
        centre = np.median(np.stack([c[:3, 3] for c in corrections]), axis=0)
        spread = [np.linalg.norm(c[:3, 3] - centre) + 0.002 * np.degrees(np.arccos(np.clip((np.trace(R.T @ Rotation.from_matrix(np.stack(rotations)).mean().as_matrix()) - 1) / 2, -1, 1))) for c, R in zip(corrections, rotations)]
        keep = np.asarray(spread) <= 3 * np.median(spread) + 1e-9
        corrections = [c for c, k in zip(corrections, keep) if k]
        rotations = [R for R, k in zip(rotations, keep) if k]
    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(np.stack(rotations)).mean().as_matrix()
    out[:3, 3] = np.mean([c[:3, 3] for c in corrections], axis=0)
    return out


def chain_frame_offsets(
    anchors: list[str],
    placed: dict[str, np.ndarray],
    forwards: list[dict[str, FrameResult]],
    backwards: list[dict[str, FrameResult]],
    symmetric: bool,
    placement_sigma: tuple[float, float] = (1.0, 0.002),
    max_link_deg: float = 8.0,
    max_link_m: float = 0.015,
) -> list[np.ndarray]:
    """Per anchor k, the object-frame change D_k (4x4) that brings poses in anchor k's frame into anchor 0's.

    Each placed box has its own small error E_k (placed = true @ E_k), so chains started from
    different anchors live in slightly different object frames and would leave a seam where they
    meet. The chain from anchor k that reaches anchor k+1 measures the link X = E_(k+1)^-1 E_k as
    ``inv(placed[k+1]) @ forward[k+1]``; the backward chain measures it too, from the other end.
    Both carry the drift their chain gathered, and the placed boxes are themselves a measurement:
    each E_k is near the identity, within ``placement_sigma`` (deg, m per axis: the annotator's
    placement error). The E_k are the weighted least-squares solution of both (a pose graph over
    the anchors, linearised: the errors are a few degrees), each link weighted by its measured
    uncertainty (:func:`_anchor_links`), and D_k = E_k^-1 E_0. A sigma of 0 or less means the
    placements carry no information (the links are taken as they are). Anchors that no measured link
    joins form groups, each centred on its own placed boxes.

    Why both: against the truth, the anchors' frames from the links as they are and from the placed boxes as they
    are lie about equally far off (about 1 deg / 2.5 mm for boxes placed up to 3 deg / 5 mm off, whose per-axis
    error is about 1 deg / 2.2 mm: the default ``placement_sigma``): two measurements of the same size. Weighted
    together they put the anchors' frames closer than the links taken as they are.
    """
    links = _anchor_links(anchors, placed, forwards, backwards, symmetric, max_link_deg, max_link_m)
    count = len(anchors)
    # no placement sigma: a vanishing pull to the placed boxes, which still fixes the anchors no link reaches
    prior = [np.radians(placement_sigma[0]), placement_sigma[1]]
    prior = np.repeat([p if p > 0 else 1e3 for p in prior], 3)
    # normal equations over e = (e_0, ..., e_(K-1)), each (rotation vector (rad), translation (m)) of E_k:
    # e_k ~ 0 with the placement sigma, and each link estimate v ~ A e_k - e_(k+1) with its own variance
    H = np.diag(np.tile(1.0 / prior**2, count))
    g = np.zeros(6 * count)
    for k, value, variances, spin in links:
        J = np.zeros((6, 6 * count))
        J[:3, 6 * k : 6 * k + 3] = J[3:, 6 * k + 3 : 6 * k + 6] = spin
        J[:, 6 * k + 6 : 6 * k + 12] = -np.eye(6)
        w = np.repeat(1.0 / np.asarray(variances), 3)
        H += J.T @ (w[:, None] * J)
        g += J.T @ (w * value)
    errors = np.linalg.solve(H, g).reshape(count, 6)
    E = [pose_exp(e) for e in errors]
    return [np.linalg.inv(E_k) @ E[0] for E_k in E]


#: the uncertainty (deg, m per axis) of an anchor link measured by one chain alone (the other lost the object):
#: a placement's own (with twice that, the link counts too little against the placements, and frames on mugs
#: came out far off)
SINGLE_LINK_SIGMA = (1.0, 0.002)
#: ... and of one measured where the two chains meet (:func:`_meeting_link`): both drifted on the way there
MEETING_LINK_SIGMA = (2.0, 0.004)
#: two chains agreeing closer than this (deg, m per axis) still drifted alike as much
LINK_FLOOR_SIGMA = (0.5, 0.001)


def _anchor_links(anchors, placed, forwards, backwards, symmetric, max_link_deg, max_link_m) -> list[tuple[int, np.ndarray, tuple[float, float], np.ndarray]]:
    """The link estimates between consecutive anchors, one per chain: (k, linearised value of
    X = E_(k+1)^-1 E_k as rotation vector and translation (6,), variance per axis of its rotation (rad^2)
    and translation (m^2), and the spin S (3x3) under which it sees anchor k: value ~ S e_k - e_(k+1),
    S the identity but for symmetric objects).

    A link estimate beyond ``max_link_deg`` / ``max_link_m`` means its chain lost the object and is dropped;
    a link left with one estimate only keeps it within 3/4 of those bounds; two estimates must agree
    within them, and their difference gives their variance. A link with no estimate left is taken where
    the chains meet between the anchors (:func:`_meeting_link`), or is not measured.
    """
    links = []
    for k in range(len(anchors) - 1):
        a, b = anchors[k], anchors[k + 1]
        estimates = []
        f, r = forwards[k].get(b), backwards[k].get(a)
        if f is not None and f.ok:
            estimates.append(np.linalg.inv(placed[b]) @ f.pose)
        if r is not None and r.ok:
            estimates.append(np.linalg.inv(np.linalg.inv(placed[a]) @ r.pose))
        estimates = [e for e in estimates if _small(e, symmetric, max_link_deg, max_link_m)]
        if len(estimates) == 1 and not _small(estimates[0], symmetric, 0.75 * max_link_deg, 0.75 * max_link_m):
            # the other chain lost the object: this one may have drifted too, so only a link two hand
            # placements could explain is taken (a drifted chain's link alone can turn a third of a sequence
            # several degrees off the rest; a right single link can be as large as 6 deg, 3/4 of the default bound)
            estimates = []
        if len(estimates) == 2 and not _small(np.linalg.inv(estimates[0]) @ estimates[1], symmetric, max_link_deg, max_link_m):
            estimates = []  # the two chains tell different stories: neither is trusted
        sigma = SINGLE_LINK_SIGMA
        if not estimates:
            estimates, sigma = _meeting_link(forwards[k], backwards[k], symmetric, 0.75 * max_link_deg, 0.75 * max_link_m), MEETING_LINK_SIGMA
        if not estimates:
            continue
        spins = [np.eye(3)] * len(estimates)
        if symmetric:
            # the spin about the axis is free: a chain may arrive spun by phi about it, X = E_(k+1)^-1 S E_k
            # (S = Ry(phi), often tens of degrees on bottles, bowls and cans). Taken out on the right,
            # X Ry(-phi) = E_(k+1)^-1 (S E_k S^-1): anchor k's error is seen turned by S, tilt and offset alike
            spun = [closest_about_y(e[:3, :3], np.eye(3)) for e in estimates]  # e Ry(theta), theta ~ -phi
            spins = [R.T @ e[:3, :3] for e, R in zip(estimates, spun)]  # Ry(-theta) = S
            for e, R in zip(estimates, spun):
                e[:3, :3] = R
        values = [pose_log(e) for e in estimates]
        variances = (np.radians(sigma[0]) ** 2, sigma[1] ** 2)
        if len(values) == 2:
            # the two chains' difference, per axis, is twice one chain's variance (for symmetric objects it also
            # holds the anchor's error turned by both spins: an overestimate, on the safe side)
            gap = values[0] - values[1]
            variances = (max(np.sum(gap[:3] ** 2) / 6, np.radians(LINK_FLOOR_SIGMA[0]) ** 2),
                         max(np.sum(gap[3:] ** 2) / 6, LINK_FLOOR_SIGMA[1] ** 2))
        links.extend((k, v, variances, S) for v, S in zip(values, spins))
    return links


def pose_log(T: np.ndarray) -> np.ndarray:
    """A small pose (4x4) as (rotation vector (rad), translation (m))."""
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def pose_exp(v: np.ndarray) -> np.ndarray:
    """The inverse of :func:`pose_log`."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(v[:3]).as_matrix()
    T[:3, 3] = v[3:]
    return T


def _meeting_link(forward: dict[str, FrameResult], backward: dict[str, FrameResult], symmetric: bool, max_deg: float, max_m: float) -> list[np.ndarray]:
    """The link (4x4, as in :func:`chain_frame_offsets`) measured where the two chains of one stretch meet,
    as a one-element list, or an empty one when they never come within ``max_deg`` / ``max_m`` of each other.

    Between the anchors, both chains on the object differ by X = E_b^-1 E_a (``inv(backward) @ forward``)
    plus the drift each gathered on the way, which stays smaller where they meet than at the far anchor
    a lost or drifted chain never reached. That drift is as large as the hand placements' own differences
    (1-3 deg): the link's weight says so (``MEETING_LINK_SIGMA``). Without it, a stretch whose one chain is lost
    early and whose other arrives far off at the far anchor has no link at all.
    """
    inner = list(forward)[1:-1]  # at the anchors the chains' links were judged already
    both = [f for f in inner if f in backward and forward[f].ok and backward[f].ok]
    if not both:
        return []
    links = {f: np.linalg.inv(backward[f].pose) @ forward[f].pose for f in both}
    sizes = {f: pose_difference(np.eye(4), X, symmetric) for f, X in links.items()}
    closest = min(both, key=lambda f: max(sizes[f][0] / max_deg, sizes[f][1] / max_m))
    if not _small(links[closest], symmetric, max_deg, max_m):
        return []
    return [links[closest]]


def _small(T: np.ndarray, symmetric: bool, max_deg: float, max_m: float) -> bool:
    deg, metres = pose_difference(np.eye(4), T, symmetric)
    return deg <= max_deg and metres <= max_m
