"""Reconciling the chains between two manual frames, and the anchors' common object frame.

Between manual frames a and b, the forward chain (from a) drifts with distance from a and the
backward chain (from b) with distance from b. Blending them with weights that fall linearly
with that distance is the closed-form solution of the pose graph a-...-b whose two chains have
drift growing with length: the error left over at the far anchor is spread along the chain
instead of piling up at one end. Their disagreement is kept as a quality figure.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .quality import pose_difference
from .symmetry import closest_about_y
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
) -> dict[str, FrameResult]:
    """Blend the forward chain (from ``frame_ids[0]``) and the backward chain (from ``frame_ids[-1]``).

    Frames strictly between the two anchors get the blended pose, the better of the two chains'
    figures and the chains' disagreement (``chain_disagreement_deg``, ``chain_disagreement_m``).
    A frame that failed in one chain takes the other's pose.
    """
    n = len(frame_ids) - 1
    out: dict[str, FrameResult] = {}
    for k, frame_id in enumerate(frame_ids[1:-1], start=1):
        f, b = forward[frame_id], backward[frame_id]
        if f.ok and not b.ok:
            out[frame_id] = FrameResult(f.pose, True, dict(f.figures))
            continue
        if b.ok and not f.ok:
            out[frame_id] = FrameResult(b.pose, True, dict(b.figures))
            continue
        Tb = b.pose.copy()
        if symmetric:
            Tb[:3, :3] = closest_about_y(Tb[:3, :3], f.pose[:3, :3])
        pose = interpolate(f.pose, Tb, k / n)
        figures = dict(f.figures if f.figures.get("fitness", 0) >= b.figures.get("fitness", 0) else b.figures)
        deg, metres = pose_difference(f.pose, Tb, symmetric)
        figures["chain_disagreement_deg"] = deg
        figures["chain_disagreement_m"] = metres
        out[frame_id] = FrameResult(pose, f.ok or b.ok, figures)
    return out


def common_correction(tracked: dict[str, np.ndarray], placed: dict[str, np.ndarray], symmetric: bool) -> np.ndarray:
    """The object-frame correction C (4x4) that best fits the placed boxes: tracked[m] @ C ~ placed[m].

    ``tracked`` poses are mutually consistent but share an arbitrary object frame; each manual
    frame m says the frame should be ``inv(tracked[m]) @ placed[m]``. Averaging those (mean
    rotation, mean translation) averages out the independent errors of hand placement.
    For symmetric objects each one's free rotation about y is first made consistent with the first.
    """
    corrections = [np.linalg.inv(tracked[m]) @ placed[m] for m in placed]
    rotations = [c[:3, :3] for c in corrections]
    if symmetric:
        rotations = [closest_about_y(R, rotations[0]) for R in rotations]
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
    max_link_deg: float = 8.0,
    max_link_m: float = 0.015,
) -> list[np.ndarray]:
    """Per anchor k, the object-frame change D_k (4x4) that brings poses in anchor k's frame into anchor 0's.

    Each placed box has its own small error E_k (placed = true @ E_k), so chains started from
    different anchors live in slightly different object frames and would leave a seam where they
    meet. The chain from anchor k that reaches anchor k+1 measures X = E_(k+1)^-1 E_k as
    ``inv(placed[k+1]) @ forward[k+1]``; the backward chain measures its inverse. Their mean
    (drift of the two chains averages) links consecutive anchors: D_(k+1) = X D_k, D_0 = I.
    Hand-placed boxes differ by a few degrees and millimetres; a link estimate beyond
    ``max_link_deg`` / ``max_link_m`` means its chain lost the object and is dropped. A link
    with no estimate left is the identity (trust the placed boxes as they are).
    """
    offsets = [np.eye(4)]
    for k in range(len(anchors) - 1):
        a, b = anchors[k], anchors[k + 1]
        estimates = []
        f, r = forwards[k].get(b), backwards[k].get(a)
        if f is not None and f.ok:
            estimates.append(np.linalg.inv(placed[b]) @ f.pose)
        if r is not None and r.ok:
            estimates.append(np.linalg.inv(np.linalg.inv(placed[a]) @ r.pose))
        estimates = [e for e in estimates if _small(e, symmetric, max_link_deg, max_link_m)]
        if len(estimates) == 2 and not _small(np.linalg.inv(estimates[0]) @ estimates[1], symmetric, max_link_deg, max_link_m):
            estimates = []  # the two chains tell different stories: neither is trusted
        if not estimates:
            link = np.eye(4)
        else:
            rotations = [e[:3, :3] for e in estimates]
            if symmetric:
                rotations = [closest_about_y(R, np.eye(3)) for R in rotations]
            link = np.eye(4)
            link[:3, :3] = Rotation.from_matrix(np.stack(rotations)).mean().as_matrix()
            link[:3, 3] = np.mean([e[:3, 3] for e in estimates], axis=0)
        offsets.append(link @ offsets[-1])
    return offsets


def _small(T: np.ndarray, symmetric: bool, max_deg: float, max_m: float) -> bool:
    deg, metres = pose_difference(np.eye(4), T, symmetric)
    return deg <= max_deg and metres <= max_m
