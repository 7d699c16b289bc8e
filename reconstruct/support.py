"""The plane an object rests on: a table that stays put in the object frame is measured beside it in every frame.

When the object does not move against its support (it stands on a table while the camera moves, as in YCB-Video or
a scan), the carving cannot tell the table from the object: the space just under the table's measured surface is
"seen just behind a surface" in every frame, and the band of noise above it is never seen free. Both stay solid, a
slab out to the grid's edge joined to the object's base (a can 30 mm too wide at its foot).

The support is found from the frames themselves, in the object frame:

1. the measured points that lie outside the carving's grid (the annotated box and its margin: never the object)
   but within ``SHELL`` of the box's half sides beyond it; every ``PIXEL_STEP``-th pixel of the frames given (the
   pipeline gives every ``FRAME_STEP``-th);
2. the plane most of them lie on (RANSAC, seeded; within ``INLIER_SIGMAS`` depth noise sigmas at their depth),
   refitted to its inliers by least squares;
3. accepted as the support only when it holds ``MIN_SHARE`` of those points, from ``MIN_FRAME_SHARE`` of the frames
   sampled (a static scene: a hand-held object's table and background move in its frame and make no plane there),
   its inliers spread over a plane, not a strip (``MIN_SPREAD``), the cameras look at it from above and the object's
   centre lies above it, and the object rests on it: at most ``MAX_BENEATH`` of the points measured inside the grid
   lie beneath it (a plane of another object's face, cutting through this one, has this one's measurements on both
   sides; with too few of them, MIN_POINTS, nothing says so and no plane is taken).

What the support removes from the object (:func:`beyond_support`): every voxel on the far side of the plane, and the
voxels of the measurement band above it (its inliers' spread) outside the object's footprint (where the voxel
straight above the band is not occupied). A hand-held sequence finds no support and is reconstructed unchanged.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from evaluate.geometry import box_corners
from sequences.camera import Camera
from sequences.sensor_noise import depth_sigma

from .carving import VoxelGrid

#: Points up to this many of the box's half sides beyond the grid are the support's candidates.
SHELL = 1.0
#: Every this many frames and pixels (per axis) give candidates: a plane needs thousands of points, not millions.
FRAME_STEP, PIXEL_STEP = 5, 4
#: RANSAC: hypotheses (three points each), the candidates that vote on them at most (a seeded subset beyond), and
#: the inlier reach in depth noise sigmas.
TRIALS, VOTERS, INLIER_SIGMAS = 256, 20_000, 2.5
#: Points of each kind (candidates; measured inside the grid, for the test that nothing lies beneath the plane) kept
#: per frame at most: memory stays bounded on long sequences.
PER_FRAME = 4000
#: The plane must hold this share of the candidates, at least MIN_POINTS of them ...
MIN_SHARE, MIN_POINTS = 0.5, 200
#: ... measured in this share of the frames sampled (a plane of one frame is a wall passing by) ...
MIN_FRAME_SHARE = 0.8
#: ... and have at most this share of the points measured inside the grid beneath it (beyond their inlier reach) ...
MAX_BENEATH = 0.02
#: ... and be a plane, not a strip: its inliers spread (standard deviation) along both its directions by at least this
#: share of the box's largest half side, and by four times their spread across it.
MIN_SPREAD = 0.25


@dataclass
class SupportPlane:
    """A plane n . p + d = 0 in the object frame (metres), ``normal`` towards the object; ``band``: the height (m)
    above it within which measurements of the plane itself lie (its inliers' spread)."""

    normal: np.ndarray
    offset: float
    band: float
    points: int
    share: float

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (m) of ``points`` (N, 3, object frame) above the plane (positive on the object's side)."""
        return points @ self.normal + self.offset

    def summary(self) -> dict:
        return {"normal": [round(float(x), 4) for x in self.normal], "offset_mm": round(self.offset * 1000, 2),
                "band_mm": round(float(self.band) * 1000, 2), "points": self.points, "share": round(self.share, 3)}


def _candidates(frames: Iterable[tuple[np.ndarray, np.ndarray]], camera: Camera, grid: VoxelGrid,
                extents: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Measured points (N, 3, object frame) outside the grid and within the shell, their depths (N, m), their frame
    numbers; the points inside the grid (M, 3) and their depths (M,); and the camera centres of the frames sampled
    (F, 3, object frame). At most PER_FRAME points of each kind per frame (an evenly thinned subset beyond)."""
    low = np.asarray(grid.origin) - grid.voxel_size / 2
    high = low + grid.voxel_size * np.asarray(grid.shape)
    reach = SHELL * np.asarray(extents, dtype=np.float64) / 2
    points, depths, which, within, within_depths, centres = [], [], [], [], [], []
    shell = box_corners(high - low + 2 * reach) + (high + low) / 2
    for pose, depth in frames:
        centres.append(-pose[:3, :3].T @ pose[:3, 3])
        window = camera.window(shell @ pose[:3, :3].T + pose[:3, 3])  # only the pixels the shell projects to
        measured, _ = camera.backproject(depth, stride=PIXEL_STEP, window=window)
        p = (measured - pose[:3, 3]) @ pose[:3, :3]
        beyond = np.any((p < low) | (p > high), axis=1)
        outside = beyond & np.all((p >= low - reach) & (p <= high + reach), axis=1)
        inside = np.flatnonzero(~beyond)[:: max(1, int(np.count_nonzero(~beyond)) // PER_FRAME)]
        near = np.flatnonzero(outside)[:: max(1, int(np.count_nonzero(outside)) // PER_FRAME)]
        within.append(p[inside])
        within_depths.append(measured[inside, 2])
        points.append(p[near])
        depths.append(measured[near, 2])
        which.append(np.full(near.size, len(centres) - 1))
    if not points:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3))
    return (np.concatenate(points), np.concatenate(depths), np.concatenate(which), np.concatenate(within),
            np.concatenate(within_depths), np.stack(centres))


def find_support(frames: Iterable[tuple[np.ndarray, np.ndarray]], camera: Camera, grid: VoxelGrid, extents: np.ndarray,
                 seed: int = 0) -> SupportPlane | None:
    """The plane the object rests on (see the module notes), or None. ``frames`` yields (pose 4x4 object to camera,
    depth (H, W) metres, 0 = none)."""
    points, depths, which, within, within_depths, cameras = _candidates(frames, camera, grid, extents)
    if len(points) < MIN_POINTS or len(within) < MIN_POINTS:  # nothing to fit, or nothing of the object to test it by
        return None
    reach = INLIER_SIGMAS * depth_sigma(depths)  # noise grows with depth: each point's reach is its own
    rng = np.random.default_rng(seed)
    voters = rng.choice(len(points), VOTERS, replace=False) if len(points) > VOTERS else np.arange(len(points))
    triple = points[rng.integers(0, len(points), (TRIALS, 3))]
    normals = np.cross(triple[:, 1] - triple[:, 0], triple[:, 2] - triple[:, 0])
    length = np.linalg.norm(normals, axis=1)
    good = length > 1e-9
    if not good.any():
        return None
    normals = normals[good] / length[good, None]
    offsets = -np.einsum("ij,ij->i", normals, triple[good, 0])
    votes = (np.abs(points[voters] @ normals.T + offsets) <= reach[voters, None]).sum(axis=0)  # (voters, trials): 5 million at most
    best = int(np.argmax(votes))
    inliers = np.abs(points @ normals[best] + offsets[best]) <= reach
    # least squares on the inliers: the normal is the direction of least spread
    centre = points[inliers].mean(axis=0)
    _, spread, axes = np.linalg.svd(points[inliers] - centre, full_matrices=False)
    spread = spread / np.sqrt(inliers.sum())
    normal = axes[2]
    offset = -float(normal @ centre)
    if np.median(cameras @ normal + offset) < 0:  # a support is seen from above: the cameras on its positive side
        normal, offset = -normal, -offset
    inliers = np.abs(points @ normal + offset) <= reach
    share = float(inliers.mean())
    frames_seen = np.unique(which[inliers]).size / len(cameras)
    beneath = float(np.mean(within @ normal + offset < -INLIER_SIGMAS * depth_sigma(within_depths)))
    # a plane, not a strip: its points spread along both of its directions, over a good part of the box
    flat = spread[1] >= max(MIN_SPREAD * float(np.max(extents)) / 2, 4 * spread[2])
    if (inliers.sum() < MIN_POINTS or share < MIN_SHARE or frames_seen < MIN_FRAME_SHARE or beneath > MAX_BENEATH
            or not flat or offset <= 0):  # offset <= 0: the object's centre is not above it
        return None
    heights = points[inliers] @ normal + offset
    band = float(np.percentile(heights, 97.5) - np.median(heights)) + np.sqrt(3) / 2 * grid.voxel_size
    return SupportPlane(normal, offset, band, int(inliers.sum()), share)


def beyond_support(occupied: np.ndarray, grid: VoxelGrid, plane: SupportPlane) -> np.ndarray:
    """(nx, ny, nz) bool: the voxels of ``occupied`` that are the support, not the object: those below the plane, and
    those in its measurement band outside the object's footprint: whose voxel straight above the band (along the
    plane's normal) is not occupied. A foot that flares out below the band loses its rim there (a voxel for a flare
    of half a voxel per voxel of height); an object that holds no voxel above the band (thinner than the table's
    noise) keeps the band: it cannot be told from the table, and cutting it would leave nothing."""
    vs = grid.voxel_size
    x, y, z = (grid.axis_coordinates(a).astype(np.float32) for a in range(3))
    n = plane.normal.astype(np.float32)
    height = n[0] * x[:, None, None] + n[1] * y[None, :, None] + n[2] * z[None, None, :] + np.float32(plane.offset)
    below = occupied & (height < 0)
    band = occupied & (height >= 0) & (height < plane.band)
    if not band.any() or not (occupied & (height >= plane.band)).any():
        return below
    i, j, k = np.nonzero(band)
    centres = np.stack([x[i], y[j], z[k]], axis=1).astype(np.float64)
    straight_above = centres + np.outer(plane.band + vs - height[i, j, k], plane.normal)
    ijk = np.rint((straight_above - np.asarray(grid.origin)) / vs).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < np.array(grid.shape)), axis=1)
    footprint = np.zeros(len(i), bool)
    footprint[inside] = occupied[tuple(ijk[inside].T)]
    cut = below.copy()
    cut[i[~footprint], j[~footprint], k[~footprint]] = True
    return cut
