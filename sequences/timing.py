"""Colour and depth a fraction of a frame apart: poses moved between a frame's colour and depth instants.

A PrimeSense (Redwood's sensor) takes colour and depth on separate clocks; paired by nearest timestamp they lie up
to half a frame apart. The annotation document holds each frame's pose at its colour instant (the box a person
places is on the colour image); a depth image is taken at its own instant, when a moving object stood elsewhere
(at 0.3 frame periods and 30 cm/s, 3 mm away). Whatever carves or fuses depth must pose it at depth time, and a
tracker that registers depth finds depth-time poses, which the document wants at colour time.

:func:`resample_poses` interpolates a pose track at other instants: the rotation along the geodesic between the two
neighbouring poses (their relative rotation's axis and angle), the translation linearly; outside the track the end
interval extends. Where the files carry no timestamps the instants coincide and nothing moves.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .reader import Sequence


def frame_times(sequence: Sequence, ids: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
    """(colour, depth) instants (microseconds, (n,) float) of ``ids``, or None when a frame has no timestamps."""
    frames = {f.id: f for f in sequence.frames}
    colour = [frames[f].color_time_us for f in ids]
    depth = [frames[f].depth_time_us for f in ids]
    if any(t is None for t in colour + depth):
        return None
    return np.asarray(colour, np.float64), np.asarray(depth, np.float64)


def resample_poses(poses: np.ndarray, times: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """``poses`` (n, 4, 4, object to camera) taken at ``times`` (n,), interpolated at ``queries`` (m,) (same unit):
    between the two poses whose times bracket each query (the end interval beyond the track). (m, 4, 4)."""
    poses, times, queries = np.asarray(poses, np.float64), np.asarray(times, np.float64), np.asarray(queries, np.float64)
    if len(poses) < 2:
        return np.repeat(poses[:1], len(queries), axis=0)
    order = np.argsort(times, kind="stable")
    poses, times = poses[order], times[order]
    k = np.clip(np.searchsorted(times, queries, side="right") - 1, 0, len(times) - 2)  # interval [k, k + 1]
    span = times[k + 1] - times[k]
    u = np.divide(queries - times[k], span, out=np.zeros_like(queries), where=span > 0)
    A, B = poses[k], poses[k + 1]
    relative = Rotation.from_matrix(np.einsum("nji,njk->nik", A[:, :3, :3], B[:, :3, :3]))  # A^T B
    out = np.repeat(np.eye(4)[None], len(queries), axis=0)
    out[:, :3, :3] = A[:, :3, :3] @ Rotation.from_rotvec(relative.as_rotvec() * u[:, None]).as_matrix()
    out[:, :3, 3] = A[:, :3, 3] + u[:, None] * (B[:, :3, 3] - A[:, :3, 3])
    return out


def _retimed(sequence: Sequence, poses: dict[str, np.ndarray], to_depth: bool) -> dict[str, np.ndarray]:
    """``poses`` (frame id -> 4x4) taken at one of each frame's instants, resampled at the other (the depth instants
    when ``to_depth``); unchanged where the files carry no timestamps."""
    ids = list(poses)
    times = frame_times(sequence, ids)
    if times is None or len(ids) < 2:
        return dict(poses)
    colour, depth = times
    moved = resample_poses(np.stack([poses[f] for f in ids]), *((colour, depth) if to_depth else (depth, colour)))
    return dict(zip(ids, moved))


def at_depth_time(sequence: Sequence, poses: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The document's colour-time ``poses`` (frame id -> 4x4) moved to each frame's depth instant, read from the track
    they make; unchanged where the files carry no timestamps."""
    return _retimed(sequence, poses, to_depth=True)


def at_colour_time(sequence: Sequence, poses: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Depth-time ``poses`` (a tracker's registrations of depth) moved to each frame's colour instant."""
    return _retimed(sequence, poses, to_depth=False)
