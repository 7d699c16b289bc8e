"""The spin of frames whose own evidence leaves it free, taken from a window of their neighbours.

A mug with its handle hidden gives the registration nothing about its spin about the body's axis. Where the two
chains disagreed (suspect frames), or the frame's shape leaves the spin free (free_spin.py), each frame's pose
comes from its own registration, one frame at a time, so consecutive frames jitter about the spin. A hand turns a
mug smoothly, so the mean spin over a symmetric window of frames is closer to the truth than any one of them; a
symmetric window keeps a constant turn where it is. Only the chosen frames are averaged: averaging every frame bends
the good ones.

Only the spin about the body's axis is averaged, about that axis (the box centre is off it, by the handle): the
tilt of the axis is fixed by the body's shape in every frame.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .free_spin import spin_matrix


def windowed_spins(poses: list[np.ndarray], selected: list[bool], half_window: int, axis: np.ndarray, point: np.ndarray,
                   usable: list[bool] | None = None) -> list[np.ndarray]:
    """``poses`` (4x4 object -> camera, in frame order) with each ``selected`` and ``usable`` frame spun about the
    line ``axis`` (unit) through ``point`` (object frame, m: the body's axis) by the mean spin about it of the usable
    frames within +-``half_window`` of it, relative to it (the window is cut to be symmetric at the ends of the
    range; a frame at an end keeps its pose). A frame not ``usable`` (its registration failed: its pose is only a
    start) neither moves nor counts in its neighbours' windows, nor does the frame opposite it in their windows;
    all are usable by default. Other frames are
    returned unchanged."""
    stack = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    n = len(stack)
    usable = np.ones(n, dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    out = [np.array(p, dtype=np.float64) for p in stack]
    for i in np.flatnonzero(np.asarray(selected, dtype=bool) & usable):
        k = min(half_window, i, n - 1 - i)
        if k <= 0:
            continue
        # a frame left out takes its mirror image with it: a lopsided window would move a constant turn off the frame
        both = usable[i - k : i + k + 1] & usable[i - k : i + k + 1][::-1]
        near = np.arange(i - k, i + k + 1)[both]
        relative = np.einsum("ji,njk->nik", stack[i, :3, :3], stack[near, :3, :3])  # R_i^T R_j
        spin = float(np.mean(Rotation.from_matrix(relative).as_rotvec() @ axis))
        out[i] = stack[i] @ spin_matrix(axis, point, np.degrees(spin))
    return out
