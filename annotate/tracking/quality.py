"""Per-frame quality figures and the review flags derived from them.

Figures (stored as extra keys on each tracked frame of the document):
- ``fitness``: share of the frame's cropped points within the inlier distance of the model;
- ``inlier_rmse``: RMS distance of those inliers, metres;
- ``depth_agreement`` / ``depth_votes`` (a refined frame): whether the frame's depth confirms the model of the other
  posed frames where the result puts it (annotate.depth_agreement); where present it judges the fit, not the fitness;
- ``in_box``: share of the points near the box (crop with margin) that lie inside the box;
- ``chain_disagreement_deg`` / ``chain_disagreement_m``: how far apart the forward and the
  backward chain put the frame between two manual frames; outside their span, how far a second
  chain on the model of all frames lands from the final pose (refine.recheck_single_chains);
- ``chain_departure_deg`` / ``chain_departure_m``: how far the final pose is from the nearest pose a chain gave
  the frame: of its two chains between two manual frames, else of the one chain that reached it (outside the
  manual frames' span, or where one chain failed; consistency.chain_departures); only the degrees are flagged
  (``max_chain_departure_deg``);
- ``free_spin_run`` / ``free_spin_end``: objects without symmetry, frames whose geometry leaves the spin
  about the axis free (a mug with its handle hidden; free_spin.py): how many such
  frames in a row hold it, and whether no frame beyond that run fixes the spin (before the first or after
  the last frame that does); flagged beyond ``max_free_spin_run``, and at either end
  (consistency.free_spin_runs);
- ``rotation_jump_deg``: the larger rotation to the previous and the next frame's final pose
  (an anchor that kept its placed box at that box; consistency.rotation_jumps);
- for anchors, ``manual_correction_deg`` / ``manual_correction_m``: how far the placed box
  is from the pose the rest of the sequence agrees on (the anchor takes that pose within the thresholds).
"""

from __future__ import annotations

import numpy as np

from annotate.depth_agreement import agreement_reason
from evaluate.geometry import untransform


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray, symmetric: bool = False) -> float:
    """Angle between two rotations (3x3), degrees; with ``symmetric`` the angle between their y axes."""
    if symmetric:
        cos = float(np.clip(Ra[:, 1] @ Rb[:, 1], -1.0, 1.0))
    else:
        cos = float(np.clip((np.trace(Ra.T @ Rb) - 1.0) / 2.0, -1.0, 1.0))
    return float(np.degrees(np.arccos(cos)))


def pose_difference(Ta: np.ndarray, Tb: np.ndarray, symmetric: bool = False) -> tuple[float, float]:
    """(rotation difference in degrees, distance between the box centres in metres) of two 4x4 poses."""
    return rotation_angle_deg(Ta[:3, :3], Tb[:3, :3], symmetric), float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))


def in_box_share(points_cam: np.ndarray, pose: np.ndarray, extents: np.ndarray) -> float:
    """Share of camera-frame points (N, 3) inside the box at ``pose`` with full sides ``extents``; 0 when empty."""
    if len(points_cam) == 0:
        return 0.0
    local = untransform(pose, points_cam)
    return float(np.mean(np.all(np.abs(local) <= np.asarray(extents) / 2, axis=1)))


def flag_reasons(figures: dict, config) -> list[str]:
    """Reasons a frame needs review, from its figures and the thresholds of a TrackingConfig."""
    return pose_reasons(figures, config) + spin_reasons(figures, config)


#: The chains' figures in words: a frame's own flag reasons and those of the frames flagged beside it (engine.py) say
#: them alike.
CHAIN_WORDS = {
    "chain_disagreement_deg": lambda v: f"two tracking chains disagree by {v:.1f} deg",
    "chain_disagreement_m": lambda v: f"two tracking chains disagree by {1000 * v:.0f} mm",
    "chain_departure_deg": lambda v: f"the final pose is {v:.1f} deg from both tracking chains",
}


def pose_reasons(figures: dict, config) -> list[str]:
    """The reasons of :func:`flag_reasons` that doubt more than the spin a frame's shape leaves free."""
    reasons = []
    if figures.get("error"):
        reasons.append(str(figures["error"]))
    if figures.get("points", config.min_points) < config.min_points:
        reasons.append(f"only {figures['points']} points in the box")
    disagreement = agreement_reason(figures)  # where asked, the depth's agreement judges the fit, not the fitness
    if disagreement:
        reasons.append(disagreement)
    elif "depth_votes" not in figures and "fitness" in figures and figures["fitness"] < config.min_fitness:
        reasons.append(f"fitness {figures['fitness']:.2f} < {config.min_fitness}")
    if "inlier_rmse" in figures and not figures["inlier_rmse"] <= config.max_inlier_rmse:
        reasons.append(f"inlier RMSE {figures['inlier_rmse'] * 1000:.1f} mm > {config.max_inlier_rmse * 1000:.1f} mm")
    if "second_chain_fitness" in figures and figures["second_chain_fitness"] < config.min_fitness:
        reasons.append(f"the second tracking chain fits only {figures['second_chain_fitness']:.2f} < {config.min_fitness}")
    if large_rejected_step(figures, config):
        reasons.append(f"the joint refinement found a pose {figures['refine_rejected_deg']:.1f} deg and "
                       f"{figures['refine_rejected_m'] * 1000:.0f} mm away that fits nearly as well")
    if "flip_repaired_deg" in figures:
        reasons.append(f"the joint refinement left it turned over, {figures['flip_repaired_deg']:.0f} deg from the frame before: "
                       "registered again from that frame's pose")
    if "slide_rejected_m" in figures:
        reasons.append(f"the fitness rises {figures['slide_rejected_m'] * 1000:.0f} mm along the direction its registration leaves free, "
                       "off its neighbours' path: slid or not, the pose is unsure")
    if "in_box" in figures and figures["in_box"] < config.min_in_box:
        reasons.append(f"only {figures['in_box']:.0%} of the points near the box are inside it")
    if figures.get("chain_disagreement_deg", 0.0) > config.max_chain_disagreement_deg:
        reasons.append(CHAIN_WORDS["chain_disagreement_deg"](figures["chain_disagreement_deg"]))
    if figures.get("chain_disagreement_m", 0.0) > config.max_chain_disagreement_m:
        reasons.append(CHAIN_WORDS["chain_disagreement_m"](figures["chain_disagreement_m"]))
    if figures.get("chains_jumped_deg", 0.0) > config.max_chain_disagreement_deg or figures.get("chains_jumped_m", 0.0) > config.max_chain_disagreement_m:
        reasons.append(f"both tracking chains jumped on their way to this frame (by at least {figures.get('chains_jumped_deg', 0.0):.1f} deg / "
                       f"{figures.get('chains_jumped_m', 0.0) * 1000:.0f} mm)")
    if figures.get("chain_departure_deg", 0.0) > config.max_chain_departure_deg:
        reasons.append(CHAIN_WORDS["chain_departure_deg"](figures["chain_departure_deg"]))
    if figures.get("rotation_jump_deg", 0.0) > config.max_frame_rotation_deg:
        reasons.append(f"the box turns {figures['rotation_jump_deg']:.1f} deg from a neighbouring frame")
    if figures.get("manual_correction_deg", 0.0) > config.max_manual_correction_deg:
        reasons.append(f"the placed box is {figures['manual_correction_deg']:.1f} deg off the tracked pose: it was kept (check it, or clear it)")
    if figures.get("manual_correction_m", 0.0) > config.max_manual_correction_m:
        reasons.append(f"the placed box is {figures['manual_correction_m'] * 1000:.0f} mm off the tracked pose: it was kept (check it, or clear it)")
    return reasons


def spin_reasons(figures: dict, config) -> list[str]:
    """The reasons that doubt only the spin about the axis, in frames whose shape leaves it free (a mug's
    handle hidden): the rest of the pose, and so the free space the frame sees, is as good as any other's."""
    reasons = []
    if config.max_free_spin_run > 0 and figures.get("free_spin_run", 0) > 0:
        if figures.get("free_spin_end"):
            reasons.append("its shape leaves the spin about the axis free, and no frame beyond it fixes that spin")
        elif figures["free_spin_run"] > config.max_free_spin_run:
            reasons.append(f"its shape leaves the spin about the axis free for {figures['free_spin_run']} frames in a row")
    return reasons


def large_rejected_step(figures: dict, config) -> bool:
    """Whether the joint refinement turned down a move beyond its step limits (refine.large_step): a rival
    pose that far fits the model nearly as well, so the model does not settle the frame, and nothing else may flag
    it."""
    deg, metres = figures.get("refine_rejected_deg", 0.0), figures.get("refine_rejected_m", 0.0)
    return (config.max_refine_step_deg > 0 and deg > config.max_refine_step_deg) or (config.max_refine_step_m > 0 and metres > config.max_refine_step_m)


def document_figures(figures: dict, config) -> dict:
    """Figures as written to the document: rounded, the raw error message dropped, and
    ``flagged: true`` with ``flag_reason`` where :func:`flag_reasons` finds any."""
    pose, spin = pose_reasons(figures, config), spin_reasons(figures, config)
    out = rounded(figures)
    out.pop("error", None)
    if pose or spin:
        out["flagged"] = True
        out["flag_reason"] = "; ".join(pose + spin)
        if not pose:
            # only the spin is in doubt: reconstruction still carves with the frame (reconstruct.pipeline.carving_frames)
            out["flag_spin_only"] = True
    return out


def rounded(figures: dict) -> dict:
    """Figures rounded for the document (4 significant decimals for shares, 0.1 mm, 0.01 deg)."""
    out = {}
    for key, value in figures.items():
        if isinstance(value, float):
            if key.endswith("_m") or key == "inlier_rmse":
                value = round(value, 5) if np.isfinite(value) else None
            elif key.endswith("_deg"):
                value = round(value, 2)
            else:
                value = round(value, 4)
        out[key] = value
    return out
