"""The scene around the object in one depth image: its planes (a table, a wall), and whether it changed.

Both serve the crops (observations.py). A plane that goes on well beyond the object's box is the scene's; where the
object moves, its points in the box are the scene's too, and would hold the object's pose to where it stood. Where
the depth around the box did not change from one frame to the next (beyond the sensor's noise), nothing there moved.
"""

from __future__ import annotations

import numpy as np

from sequences.sensor_noise import depth_sigma

#: the scene's planes (a table, a wall) are found on every this many-th pixel of the subsampled depth ...
PLANE_PIXEL_STEP = 4
#: ... as at most this many planes, each holding at least this share of those points ...
MAX_SCENE_PLANES, MIN_PLANE_SHARE = 4, 0.02
#: ... within this distance (m); RANSAC draws this many planes per search (seeded by the frame's id), each through
#: a pixel and two others at most PLANE_REACH pixels (of the searched grid) away in each direction
PLANE_DISTANCE, PLANE_TRIALS, PLANE_REACH = 0.008, 512, 6
#: the trials are scored on this many of the points, and the best PLANE_FINALISTS counted on all of them
PLANE_SAMPLE, PLANE_FINALISTS = 600, 8
#: a plane keeps at most about this many of its inliers (evenly thinned): enough to tell where it lies, small to pass
#: between processes
KEPT_INLIERS = 512
#: least-squares refits of a drawn plane to its inliers
REFITS = 3
#: points this many distances from a plane found are not searched again
SPREAD = 4
#: a plane is the scene's, not the object's, where most of its points lie beyond the box grown by BEYOND (m) (an
#: object's face, extended, also crosses the table in a strip)
BEYOND_SHARE, BEYOND = 0.75, 0.03
#: a crop drops its points within this many depth noise sigmas of a scene's plane (sequences.sensor_noise) ...
DROP_SIGMAS = 2.5
#: ... unless they are this share of the crop or more: the object's own face lies on the plane (a thin object lying
#: on the table cannot be told from it)
MAX_CROP_SHARE = 0.2


def scene_planes(grid: np.ndarray, rng: np.random.Generator) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Up to MAX_SCENE_PLANES planes (unit normal, offset d with n.x + d = 0, about KEPT_INLIERS of their inlier
    points) of an image's points ``grid`` (h, w, 3, m; z = 0 where none), largest first: RANSAC on triples of nearby
    pixels (a plane that fills a twentieth of the image is then drawn as often as a twentieth of the triples), each
    plane refit to its inliers by least squares."""
    h, w = grid.shape[:2]
    valid = grid[..., 2] > 0
    points = grid[valid]
    planes, remaining, total = [], np.ones(len(points), dtype=bool), len(points)
    index = np.full((h, w), -1)
    index[valid] = np.arange(total)
    for _ in range(MAX_SCENE_PLANES):
        if remaining.sum() < MIN_PLANE_SHARE * total:
            break
        rows, cols = np.nonzero(valid & remaining[np.maximum(index, 0)])
        first = rng.integers(0, len(rows), PLANE_TRIALS)
        steps = rng.integers(-PLANE_REACH, PLANE_REACH + 1, (2, PLANE_TRIALS, 2))  # the two other pixels of each triple
        near_rows = np.clip(rows[first] + steps[..., 0], 0, h - 1)
        near_cols = np.clip(cols[first] + steps[..., 1], 0, w - 1)
        ia, ib, ic = index[rows[first], cols[first]], index[near_rows[0], near_cols[0]], index[near_rows[1], near_cols[1]]
        ok = (ib >= 0) & (ic >= 0)
        a, b, c = points[ia[ok]], points[ib[ok]], points[ic[ok]]
        normal = np.cross(b - a, c - a)
        length = np.linalg.norm(normal, axis=1)
        fine = length > 1e-9
        normal, a = normal[fine] / length[fine, None], a[fine]
        left = points[remaining]
        offsets = np.einsum("ij,ij->i", normal, a)
        # scored on a sample first, counted on every point for the best few: the count is the time
        sample = left[rng.choice(len(left), min(len(left), PLANE_SAMPLE), replace=False)].astype(np.float32)
        scores = sample @ np.ascontiguousarray(normal.T, dtype=np.float32) - offsets.astype(np.float32)
        scores = np.count_nonzero(np.abs(scores, out=scores) < PLANE_DISTANCE, axis=0)
        few = np.argsort(-scores, kind="stable")[:PLANE_FINALISTS]
        counts = (np.abs(left @ normal[few].T - offsets[few]) < PLANE_DISTANCE).sum(axis=0)
        if not len(counts) or counts.max() < MIN_PLANE_SHARE * total:
            break
        best = int(few[np.argmax(counts)])
        centre, n = a[best], normal[best]
        for _ in range(REFITS):  # the drawn plane's inliers, then the refit's: a noisy wall's are cut off askew at first
            inliers = left[np.abs((left - centre) @ n) < PLANE_DISTANCE]
            centre = inliers.mean(axis=0)
            n = np.linalg.svd(inliers - centre, full_matrices=False)[2][-1]
        distance = np.abs((points - centre) @ n)
        on = points[remaining & (distance < PLANE_DISTANCE)]
        planes.append((n, float(-n @ centre), on[:: max(1, len(on) // KEPT_INLIERS)]))
        # a far wall's noise spreads it wider than the distance: what is left of it is no new plane
        remaining &= distance >= SPREAD * PLANE_DISTANCE
    return planes


#: a pixel has changed where two readings differ by more than this many standard deviations of their difference ...
CHANGE_SIGMAS = 3.0
#: ... and the object has moved between two frames where this share of the pixels around its box changed (the
#: sensor's noise alone changes 1-3 %, a 2 mm step 7 % and more)
STILL_SHARE = 0.04
#: a plane stands still from one frame to the next where it turns by at most this (deg) and moves by at most this (m)
#: along its normal: a fit to hundreds of points varies by a tenth of that; a hand-held camera moves more
STILL_TURN, STILL_SHIFT = 0.2, 0.001


def changed_share(a: np.ndarray, b: np.ndarray, z_near: float, z_far: float) -> float:
    """The share of the pixels of two depth images of one window (m, 0 = none) that both measure, one of them between
    ``z_near`` and ``z_far`` (m: the object's box), and whose readings differ beyond the sensor's noise; 1 where there
    is no such pixel."""
    # pixels that see the box's depth range in either image: the wall far behind would only dilute the share
    near = ((a >= z_near) & (a <= z_far)) | ((b >= z_near) & (b <= z_far))
    both = (a > 0) & (b > 0) & near
    if not both.any():
        return 1.0
    za, zb = a[both], b[both]
    return float(np.mean(np.abs(za - zb) > CHANGE_SIGMAS * np.sqrt(2.0) * depth_sigma(za)))
