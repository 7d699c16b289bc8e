"""A frame's figures and flag, read from the estimate itself: fitness, marginal uncertainty, and the graph's pull.

Figures (document keys): ``fitness`` (share of the frame's points in the box that pair with the model), ``rmse_mm``
(their RMS point-to-plane residual), ``sigma_deg`` and ``sigma_mm`` (the graph's marginal standard deviation along
the frame's weakest rotation and translation; for symmetry y the rotation about y is left out), ``pull_deg`` and
``pull_mm`` (how far the solved pose lies from the frame's own registration), ``weak_turn`` (how much less certain
its registration leaves the weakest rotation than the others). A frame is flagged, with the reason in words, when
one of them passes its limit (:class:`EstimatorConfig`, MAX_WEAK_TURN), or lies in a run of weak turns
(:func:`flag_weak_runs`).
"""

from __future__ import annotations

import numpy as np

from annotate.depth_agreement import agreement_reason
from evaluate.metrics.pose_errors import rotation_error

from .config import EstimatorConfig
from .registration import Registration


#: flag a frame whose weakest rotation is this many times less certain than its median one (:func:`weak_turn`): high
#: enough that a box seen on one face, whose edges still fix the turn, passes; low enough to catch a plain mug's free
#: spin (chosen on the dev split with benchmarks/compare_engines.py)
MAX_WEAK_TURN = 2.2
#: ... and every frame next to such a frame, in a run of frames whose weakest rotation stays this many times less
#: certain: the run's registrations pair with one model, so they share its error in that turn, and the motion that
#: carries it through the run drifts with no frame to stop it (hysteresis, as an edge detector's two thresholds)
WEAK_RUN_TURN = 2.0


def marginal_sigmas(covariance: np.ndarray, symmetric: bool) -> tuple[float, float]:
    """Largest standard deviation of rotation (deg) and translation (m) in a (w, v) covariance (6, 6)."""
    rotation = covariance[:3, :3]
    if symmetric:
        rotation = rotation[np.ix_([0, 2], [0, 2])]
    deg = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(rotation).max(), 0.0))))
    metres = float(np.sqrt(max(np.linalg.eigvalsh(covariance[3:, 3:]).max(), 0.0)))
    return deg, metres


def weak_turn(information: np.ndarray, symmetric: bool) -> float:
    """How much less certain a registration leaves its weakest rotation than its median one (the ratio of their
    standard deviations, translation marginalised; for symmetry y the spin left out): near 1 every turn is fixed by
    the shape seen, large where one turn slides (a plain mug's spin with its handle hidden)."""
    rt = information[:3, :3] - information[:3, 3:] @ np.linalg.solve(information[3:, 3:] + 1e-12 * np.eye(3), information[3:, :3])
    if symmetric:
        rt = rt[np.ix_([0, 2], [0, 2])]
    values = np.clip(np.linalg.eigvalsh(rt), 1e-12, None)
    return float(np.sqrt(np.median(values) / values[0]))


def frame_figures(pose: np.ndarray, registration: Registration | None, covariance: np.ndarray | None, symmetric: bool, config: EstimatorConfig,
                  agreement: dict | None = None) -> dict:
    """The figures of a frame with final ``pose``, and ``flagged``/``flag_reason`` where they pass the limits.
    ``agreement`` (annotate.depth_agreement.agreement_figures), where given, judges the fit instead of the fitness."""
    figures: dict = dict(agreement or {})
    reasons: list[str] = []
    if registration is not None:
        figures["fitness"] = round(float(registration.fitness), 3)
        figures["rmse_mm"] = round(1000 * float(registration.rmse), 2) if np.isfinite(registration.rmse) else None
        if not registration.ok:
            reasons.append("no depth of the object in the box: it is hidden or out of view, and the motion alone places it")
        elif agreement is not None:
            if disagreement := agreement_reason(agreement):
                reasons.append(disagreement)
        elif registration.fitness < config.min_fitness:
            reasons.append(f"only {registration.fitness:.0%} of the points in the box fit the object: a hand or another "
                           "surface covers it, or the box is off it")
        if registration.ok and np.all(np.isfinite(registration.information)) and registration.information[0, 0] > 0:
            ratio = weak_turn(registration.information, symmetric)
            figures["weak_turn"] = round(ratio, 2)
            if ratio > MAX_WEAK_TURN:
                reasons.append(f"the shape seen here leaves one turn nearly free ({ratio:.1f}x less certain than the others): "
                               "the motion carries it")
        if registration.ok:
            pull_deg, pull_m = float(rotation_error(pose[:3, :3], registration.pose[:3, :3], "y" if symmetric else "none")), float(np.linalg.norm(pose[:3, 3] - registration.pose[:3, 3]))
            figures["pull_deg"], figures["pull_mm"] = round(pull_deg, 2), round(1000 * pull_m, 2)
            if pull_deg > config.max_disagreement[0] or pull_m > config.max_disagreement[1]:
                reasons.append(f"its own points and its neighbours disagree by {pull_deg:.1f}° and {1000 * pull_m:.1f} mm")
    if covariance is not None:
        deg, metres = marginal_sigmas(covariance, symmetric)
        figures["sigma_deg"], figures["sigma_mm"] = round(deg, 2), round(1000 * metres, 2)
        if deg > config.max_uncertainty[0]:
            reasons.append(f"the shape seen here does not fix its rotation (±{deg:.1f}°): the motion carries it")
        if metres > config.max_uncertainty[1]:
            reasons.append(f"the shape seen here does not fix its position (±{1000 * metres:.1f} mm): the motion carries it")
    if reasons:
        figures["flagged"] = True
        figures["flag_reason"] = "; ".join(reasons)
    return figures


def weak_runs(turns: np.ndarray) -> list[tuple[int, int]]:
    """The runs [start, end) of consecutive frames whose ``weak_turn`` (NaN: none measured) is at least WEAK_RUN_TURN
    and that hold at least one frame over MAX_WEAK_TURN."""
    weak = np.nan_to_num(turns, nan=0.0) >= WEAK_RUN_TURN
    edges = np.flatnonzero(np.diff(np.concatenate([[0], weak.astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2]) if np.nanmax(turns[a:b]) > MAX_WEAK_TURN]


def flag_weak_runs(figures: list[dict], anchored: np.ndarray) -> None:
    """Flag, in place, the frames of ``figures`` (in frame order) in a run of weak turns (:func:`weak_runs`) that
    their own figures left unflagged, saying which run. A frame with a person's box (``anchored``, (n,) bool) ends a
    run: its box holds the turn."""
    turns = np.array([f.get("weak_turn", np.nan) for f in figures], dtype=np.float64)
    turns[np.asarray(anchored, dtype=bool)] = np.nan
    for start, end in weak_runs(turns):
        weakest = np.max(turns[start:end])
        for k in range(start, end):
            if turns[k] <= MAX_WEAK_TURN:
                reason = (f"one of {end - start} frames in a row whose shape leaves one turn nearly free (from "
                          f"{turns[k]:.1f}x to {weakest:.1f}x less certain than the others): the motion carries it")
                figures[k]["flagged"] = True
                figures[k]["flag_reason"] = "; ".join(filter(None, [figures[k].get("flag_reason"), reason]))
