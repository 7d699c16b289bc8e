"""Colour and depth a fraction of a frame apart: the graph's poses are at depth time, the document's at colour time.

A PrimeSense (Redwood's sensor) takes colour and depth on separate clocks; paired by nearest timestamp they lie up
to half a frame apart. Registration measures depth, so each node of the graph is the pose at its depth frame's
time; the box a person sees and places is on the colour image, so the document holds the pose at the colour time.
Between them the object moves by its velocity times the offset: T_c = T_d Exp(xi s), with xi the central
difference of the neighbouring poses (object frame, per frame period) and s the offset (t_colour - t_depth) in
frame periods. Where the files carry no timestamps, s = 0.
"""

from __future__ import annotations

import numpy as np

from sequences.reader import Sequence

from .registration import offset, retract


def colour_offsets(sequence: Sequence, ids: list[str]) -> np.ndarray:
    """(t_colour - t_depth) / frame period per frame of ``ids`` (n,), 0 where a time is missing."""
    frames = {f.id: f for f in sequence.frames}
    colour = np.array([frames[f].color_time_us if frames[f].color_time_us is not None else np.nan for f in ids], dtype=np.float64)
    depth = np.array([frames[f].depth_time_us if frames[f].depth_time_us is not None else np.nan for f in ids], dtype=np.float64)
    steps = np.diff(depth)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    if len(steps) == 0:
        return np.zeros(len(ids))
    return np.nan_to_num((colour - depth) / np.median(steps))


def velocities(poses: np.ndarray) -> np.ndarray:
    """Per frame (n, 6): the motion per frame period, (w, v) in the frame's object frame, by central differences
    (one-sided at the ends; zero for a single frame)."""
    n = len(poses)
    if n < 2:
        return np.zeros((n, 6))
    forward = np.stack([offset(poses[k], poses[k + 1]) for k in range(n - 1)])
    out = np.empty((n, 6))
    out[0], out[-1] = forward[0], forward[-1]
    out[1:-1] = 0.5 * (forward[:-1] + forward[1:])
    return out


def shifted(poses: np.ndarray, offsets: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """``poses`` (n, 4, 4) moved along the motion by ``offsets`` (n,) frame periods; the motion is read from
    ``reference`` (default ``poses``)."""
    if not np.any(offsets):
        return poses.copy()
    xi = velocities(poses if reference is None else reference)
    return np.stack([retract(pose, v * s) for pose, v, s in zip(poses, xi, offsets)])
