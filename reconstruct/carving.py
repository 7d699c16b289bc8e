"""Space carving in the object frame: a voxel grid over the annotated box plus a margin.

Frames: voxel centres live in the object frame (ShapeNet axes, metres); a pose maps object to
camera, p_cam = R p_obj + t (OpenCV camera). In each frame a voxel is *seen free* where the
valid depth pixel its centre projects to lies behind it by more than a tolerance
``tol_sigmas * sigma(z) + half the voxel diagonal`` (sigma(z) is the structured-light noise model,
sequences.sensor_noise). Missing depth, pixels outside the image and points behind the camera are unknown, never
free. A voxel is carved when it is seen free in more than ``k`` frames: a few frames whose pose is
off by a degree or two millimetres (or whose depth is noisy) can not eat the object, while a hand
or any occluder that moves relative to the object is seen free in most frames and goes. A veto
keeps a voxel that more frames see just behind the measured surface (inside the object) than
twice those that see it free: frames whose pose is off see the object's rim free, the others
see it inside.

Missing depth that a projector shadow explains is free up to the depth the shadow's geometry
proves (:func:`shadow_free_depth`): the camera sees past the occluder there, only the projector
does not (a hand's place behind the object's own shadow is otherwise never carved).

The thresholds below were chosen with benchmarks/bench_reconstruct.py, from the true poses and from poses all
off by 1 deg and 2 mm (their figures are in the commit history).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from sequences.camera import Camera
from sequences.sensor_noise import depth_sigma

from . import pyramid

#: A voxel is carved when seen free in more than k frames, k = max(DEFAULT_MIN_FREE,
#: floor(DEFAULT_FREE_FRACTION * frames)), and (the veto) in at least DEFAULT_VETO times as many
#: frames as saw it just behind the measured surface. Without the veto a few frames with bad poses
#: eat the object (they see its rim free); the veto counts the frames that see those voxels inside
#: and keeps them. A higher k fills cavities seen from few frames (a mug's inside) but fattens the
#: object under pose errors; a veto of 1.0 keeps remnants of a hand.
DEFAULT_MIN_FREE = 1
#: Fraction of the frames that must see a voxel free before it is carved, on long sequences.
DEFAULT_FREE_FRACTION = 0.01
#: Free votes needed per "just behind the surface" vote (see above).
DEFAULT_VETO = 0.5
#: With the veto, a voxel leaves the active set and is carved for good once seen free in more than
#: this many frames (else a hand held still for many frames would be saved by the veto); fewer lets
#: frames with pose errors eat a bowl's thin rim.
DEFAULT_SETTLE = 6
#: With the veto, a voxel that no frame ever saw just behind the measured surface (no evidence of
#: the object within a tolerance of it) is carved once seen free in more than this many frames
#: (None: no such rule). Pose errors move surfaces by a few millimetres, so the object's own voxels
#: near any surface a frame sees collect "behind" votes; voxels in a cavity seen only through its
#: opening from a few frames (a mug's inside) collect none. Off: it eats a can's rim under pose
#: errors; the evidence hull (reconstruct.evidence) opens a mug's unseen inside instead.
DEFAULT_UNBACKED: int | None = None
#: Noise tolerance in depth standard deviations (plus half a voxel diagonal): 3 sigmas fatten flat
#: faces seen head-on with no gain under pose errors.
DEFAULT_TOL_SIGMAS = 2.0
#: Share of a ring (symmetry y) that must be carved for the whole ring to be carved: less shrinks
#: radii under pose errors, much more keeps noise; 0.3 fills more of the sides never seen than 0.5.
DEFAULT_CARVED_SHARE = 0.3
#: With observation counts (revolve_occupancy's ``observed``, the default in the pipeline): the share
#: of a ring's observed voxels that must be carved, and the least part of the ring counted as observed.
#: Counting observed voxels, not the whole ring, keeps a bowl's thin rim that frames with pose errors
#: see free, and still fills the sides of a can seen from one direction only
#: (tests/test_reconstruct.py::test_symmetry_fills_the_sides_never_seen).
OBSERVED_CARVED_SHARE = 0.6
#: So a ring is carved only where at least OBSERVED_CARVED_SHARE * OBSERVED_FLOOR (15 %) of it was seen free: a
#: pocket off the axis, open on a tenth of its rings, would otherwise carve the rest of them, hidden inside the
#: solid, into a void no camera could see (tests/test_reconstruct_seen.py, the pocket test).
OBSERVED_FLOOR = 0.25
#: Count projector shadows as free up to the depth their geometry proves (shadow_free_depth): a palm
#: behind a mug's own shadow is otherwise never carved and stretches the box by centimetres. ~9 ms a frame.
DEFAULT_SHADOWS = True


#: Voxels per side of the blocks decided whole when a frame sees all their voxels free, or none of them
#: free or just behind the surface (their projections' hull against min / max pyramids of the
#: frame's images); only the other blocks are decided voxel by voxel. Same counts as voxel by voxel.
DEFAULT_BLOCK = 4
#: Blocks decided voxel by voxel at once (memory: 3 x 8 bytes x B^3 per block).
MIXED_CHUNK = 512
#: Top level of the frames' pyramids: blocks whose pixel rectangle is larger than 2^top pixels are decided voxel by voxel.
PYRAMID_TOP = 6
#: Frames between recomputing which blocks have no voxel left to decide.
PRUNE_EVERY = 2


#: The depth sensor's projector: metres along the camera's +x axis (PrimeSense: 7.5 cm to the right),
#: so its shadows are bands of missing depth just left of foreground edges (see shadow_free_depth).
PROJECTOR_BASELINE = 0.075
#: Slack (pixels) on the width a projector shadow may have, and pixels next to the occluder's edge
#: that get only the occluder's depth (its sub-pixel position, an edge pixel lost to dropout): a wider
#: slack lets rim voxels be seen free through the fill (a can loses height).
SHADOW_SLACK_PX = 1.0
SHADOW_EDGE_PX = 3.0


def shadow_free_depth(depth: np.ndarray, fx: float, baseline: float = PROJECTOR_BASELINE, slack_px: float = SHADOW_SLACK_PX, edge_px: float = SHADOW_EDGE_PX) -> np.ndarray:
    """Depth (H, W) float32 metres that each camera ray is known to be free up to: missing pixels that a projector shadow explains filled.

    A projector at ``baseline`` metres along the camera's +x sees a point at depth D, camera column
    x, at its own column x - fx baseline / D. A foreground edge at column r and depth d_near (the
    first valid pixel right of a run of missing ones) hides from the projector every point left
    of it whose projector column falls behind the edge's: pixel x is shadowed only if its surface
    lies deeper than 1 / (1/d_near - (r - x) / (fx baseline)). So the camera ray of a shadowed
    pixel is free at least up to that depth (the occluder blocks the projector's ray, not the
    camera's), and the whole run, as wide as the shadow of d_near on the background d_far left of
    it (``fx * baseline * (1/d_near - 1/d_far)`` pixels, plus ``slack_px``), is explained by it.
    Such runs are filled with that bound, counted from ``edge_px`` pixels nearer the edge than the
    pixel (slack for the edge's sub-pixel position and an edge pixel lost to dropout) and capped at
    d_far, so the pixels next to the edge get d_near: a filled pixel never says free in front of
    the occluder, nor behind the background. Other missing pixels stay 0 (unknown). With ``baseline`` < 0 rows are mirrored.
    """
    depth = np.asarray(depth, dtype=np.float32)
    if baseline < 0:
        return shadow_free_depth(depth[:, ::-1], fx, -baseline, slack_px, edge_px)[:, ::-1].copy()
    h, w = depth.shape
    valid = depth > 0
    columns = np.arange(w, dtype=np.int32)
    left = np.maximum.accumulate(np.where(valid, columns, -1), axis=1)  # nearest valid column at or left of each pixel
    right = np.minimum.accumulate(np.where(valid, columns, w)[:, ::-1], axis=1)[:, ::-1]  # ... at or right of it
    hole = ~valid & (left >= 0) & (right < w)
    rows, cols = np.nonzero(hole)
    d_left = depth[rows, left[hole]]
    d_right = depth[rows, right[hole]]
    width = (right[hole] - left[hole] - 1).astype(np.float32)
    explained = (d_right < d_left) & (width <= fx * baseline * (1.0 / d_right - 1.0 / d_left) + slack_px)
    reach = np.maximum(right[hole] - cols - np.float32(edge_px), 0).astype(np.float32)  # pixels from the edge, less the slack
    inverse = np.maximum(1.0 / d_right - reach / np.float32(fx * baseline), 1.0 / d_left)
    filled = depth.copy()
    filled[hole] = np.where(explained, 1.0 / inverse, 0.0)
    return filled


def choose_k(n_frames: int, min_free: int = DEFAULT_MIN_FREE, fraction: float = DEFAULT_FREE_FRACTION) -> int:
    """Votes threshold: carve a voxel seen free in more than ``k`` of ``n_frames`` frames."""
    return int(max(min_free, np.floor(fraction * n_frames + 1e-9)))


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid in the object frame: voxel (i, j, k) has centre ``origin + voxel_size * (i, j, k)``."""

    origin: np.ndarray  # (3,) centre of voxel (0, 0, 0), object frame, metres
    voxel_size: float  # metres
    shape: tuple[int, int, int]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def centres(self, dtype=np.float32) -> np.ndarray:
        """(N, 3) voxel centres in C order over ``shape`` (object frame, metres)."""
        axes = [self.origin[a] + self.voxel_size * np.arange(self.shape[a]) for a in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        return grid.reshape(-1, 3).astype(dtype)

    def axis_coordinates(self, axis: int) -> np.ndarray:
        return self.origin[axis] + self.voxel_size * np.arange(self.shape[axis])

    def corners(self) -> np.ndarray:
        """(8, 3) centres of the grid's corner voxels (object frame, metres), float64: its projection's hull."""
        bits = np.stack(np.unravel_index(np.arange(8), (2, 2, 2)), axis=1)
        return np.asarray(self.origin, np.float64) + self.voxel_size * (np.array(self.shape) - 1) * bits


def inside_box(grid: "VoxelGrid", extents) -> np.ndarray:
    """(nx, ny, nz) bool: voxels whose centre lies inside the box of full sides ``extents`` centred on the origin."""
    half = np.asarray(extents, dtype=np.float64) / 2
    axes = [np.abs(grid.axis_coordinates(a)) <= half[a] for a in range(3)]
    return axes[0][:, None, None] & axes[1][None, :, None] & axes[2][None, None, :]


def bound_by_box(occupied: np.ndarray, behind: np.ndarray, grid: "VoxelGrid", extents) -> np.ndarray:
    """``occupied`` without the voxels outside the box of full sides ``extents`` (centred on the origin) that no frame saw
    just behind a measured surface (``behind`` == 0). Outside the box only a measurement makes a voxel object: space no
    frame looked at, and space some frames saw free too few times to be carved, are not. (nx, ny, nz) arrays."""
    return occupied & ~((behind == 0) & ~inside_box(grid, extents))


def default_margin(extents: np.ndarray) -> np.ndarray:
    """Margin (metres, per side and axis) around the annotated box: covers box errors of ~15 %."""
    return np.maximum(0.01, 0.15 * np.asarray(extents, dtype=np.float64))


def make_grid(extents, voxel_size: float, margin=None) -> VoxelGrid:
    """Grid covering the box centred on the origin with full sides ``extents`` plus ``margin`` per side."""
    extents = np.asarray(extents, dtype=np.float64)
    if voxel_size <= 0 or not np.isfinite(voxel_size):
        raise ValueError(f"voxel size must be positive, got {voxel_size}")
    margin = default_margin(extents) if margin is None else np.broadcast_to(np.asarray(margin, dtype=np.float64), (3,))
    half = extents / 2 + margin
    n = np.maximum(np.ceil(2 * half / voxel_size).astype(int), 1)
    origin = -(n - 1) * voxel_size / 2  # grid centred on the box centre
    return VoxelGrid(origin, float(voxel_size), (int(n[0]), int(n[1]), int(n[2])))


@dataclass
class CarveResult:
    """Free-space votes on a grid. ``free_count`` saturates at ``k + 1`` (carved voxels stop being tested)."""

    grid: VoxelGrid
    free_count: np.ndarray  # (nx, ny, nz) uint16
    k: int
    frames: list[str]
    projections: int  # voxel projections done (speed figure)
    behind_count: np.ndarray | None = None  # (nx, ny, nz) uint16: frames that saw the voxel just behind the surface
    veto: float | None = None
    settled: int | None = None  # with the veto: voxels seen free more often than this were dropped, carved for good
    unbacked: int | None = None  # with the veto: voxels never seen just behind the surface are carved when seen free in more frames than this

    @property
    def occupied(self) -> np.ndarray:
        """(nx, ny, nz) bool: voxels not carved.

        Carved: seen free in more than ``k`` frames and, with ``veto``, in at least ``veto`` times
        as many frames as saw it just behind the measured surface (inside the object); with
        ``unbacked``, also when no frame saw it behind the surface and more than ``unbacked`` saw it free.
        """
        carved = self.free_count > self.k
        if self.veto is not None and self.behind_count is not None:
            carved &= self.free_count >= self.veto * self.behind_count
            if self.settled is not None:
                carved |= self.free_count > self.settled
            if self.unbacked is not None:
                carved |= (self.behind_count == 0) & (self.free_count > self.unbacked)
        return ~carved


@dataclass
class FrameImages:
    """One frame's per-pixel bounds (metres, (H + 2, W + 2) float32 with a one-pixel border) and their pyramids.

    A voxel at camera depth z projecting to a pixel is seen free where z < threshold, and just behind
    the surface where near <= z <= far. The border and missing depth compare as neither (threshold
    -1, near inf, far -1), so pixels outside the image need no bounds test.
    """

    threshold: np.ndarray
    near: np.ndarray
    far: np.ndarray
    threshold_min: pyramid.Pyramid
    threshold_max: pyramid.Pyramid
    near_min: pyramid.Pyramid | None
    far_max: pyramid.Pyramid | None
    row0: int  # the padded image's row at the images' first row


def _frame_images(depth: np.ndarray, rows: tuple[int, int] | None, fx: float, tol_sigmas: float, half_diagonal: float, silhouette_px: int, shadows: bool,
                  behind: bool) -> FrameImages:
    """The bounds of one depth image (H, W) float32 metres, 0 = none (see :func:`carve` for the options).

    ``rows`` (first, last; image rows): the only rows any voxel projects to (None: all). The images
    cover a band of the padded image from ``row0`` (a multiple of the pyramid's top tile) to one row
    past ``last`` (plus the bottom border row if the band reaches it); rows outside ``rows`` keep the
    border's values. Every step is row by row (the shadow fill) or pixel by pixel, and the
    silhouette's minimum filter reads ``silhouette_px`` rows beyond: the same values as for the whole image.
    """
    depth = np.asarray(depth, dtype=np.float32)
    height, width = depth.shape
    first, last = (0, height - 1) if rows is None else rows
    if first > last:  # the grid projects above or below the image: every voxel lands on a border row
        first, last, row0, row1 = 0, -1, 0, height + 2
    else:
        tile = 2 ** PYRAMID_TOP
        row0, row1 = first // tile * tile, min(last + 3, height + 2)  # padded rows [row0, row1)
    near = np.full((row1 - row0, width + 2), np.inf, dtype=np.float32)  # z >= d: behind the surface
    far = np.full((row1 - row0, width + 2), -1.0, dtype=np.float32)  # z <= d + tol: not deeper than the noise
    threshold = np.full((row1 - row0, width + 2), -1.0, dtype=np.float32)
    if first <= last:
        read = (max(first - silhouette_px, 0), min(last + silhouette_px, height - 1))
        depth = depth[read[0]:read[1] + 1]
        if silhouette_px > 0:
            # a voxel is free only if every pixel within silhouette_px sees past it: silhouettes
            # grow by that much, so a pose off by a pixel or two can not cut into the object
            depth = ndimage.minimum_filter(depth, size=2 * silhouette_px + 1, mode="nearest")
        depth = depth[first - read[0]:last - read[0] + 1]
        inside = (slice(first + 1 - row0, last + 2 - row0), slice(1, -1))
        # free where the voxel's depth z < d - (tol_sigmas sigma(d) + half diagonal)
        tolerance = np.float32(tol_sigmas) * depth_sigma(depth) + np.float32(half_diagonal)
        missing = depth <= 0
        if behind:
            near[inside] = np.where(missing, np.inf, depth)
            far[inside] = np.where(missing, -1.0, depth + tolerance)  # d + tol
        if shadows:
            depth = shadow_free_depth(depth, fx)
            tolerance = np.float32(tol_sigmas) * depth_sigma(depth) + np.float32(half_diagonal)
            missing = depth <= 0
        inner = depth - tolerance
        inner[missing] = -1.0
        threshold[inside] = inner
    # rows no voxel projects to are read only by pyramid tiles that also cover projected rows: the
    # minimum's identity there keeps them from spoiling those tiles (the image's border rows stay -1)
    lowest = threshold.copy()
    lowest[max(1 - row0, 0):first + 1 - row0] = np.inf
    lowest[last + 2 - row0:height + 1 - row0] = np.inf
    return FrameImages(threshold, near, far, pyramid.build(lowest, np.minimum, PYRAMID_TOP), pyramid.build(threshold, np.maximum, PYRAMID_TOP),
                       pyramid.build(near, np.minimum, PYRAMID_TOP) if behind else None, pyramid.build(far, np.maximum, PYRAMID_TOP) if behind else None, row0)


def grid_rows(grid: VoxelGrid, pose: np.ndarray, K: np.ndarray, height: int) -> tuple[int, int] | None:
    """(first, last) image rows the grid's voxel centres project to at ``pose`` (object to camera), or None
    when part of the grid lies behind the camera. The grid's image is the hull of its 8 corners' images."""
    corners = grid.corners().T
    q = K @ (np.asarray(pose, np.float64)[:3, :3] @ corners + np.asarray(pose, np.float64)[:3, 3:4])
    if q[2].min() <= 1e-3:
        return None
    v = q[1] / q[2]
    # row index floor(v + 0.5), one row of slack for rounding (the blocks' corners are projected apart)
    first = int(np.clip(np.floor(v.min() + 0.5) - 1, 0, height - 1))
    last = int(np.clip(np.floor(v.max() + 0.5) + 1, 0, height - 1))
    if v.max() + 0.5 < 0 or v.min() + 0.5 >= height:  # the grid is above or below the image: no row
        return (0, -1)
    return first, last


def _prefetched(frames: Iterable[tuple[str, np.ndarray, np.ndarray]], prepare: Callable[[np.ndarray, np.ndarray], FrameImages],
                ahead: bool = True) -> Iterator[tuple[str, FrameImages, np.ndarray]]:
    """(frame id, prepared images, pose) in order, each frame's images prepared on a worker thread while
    the one before is carved (numpy releases the GIL: the two overlap on two cores); without ``ahead``, in turn
    on this thread."""
    if not ahead:
        for frame_id, depth, pose in frames:
            yield frame_id, prepare(depth, pose), pose
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = None
        for frame_id, depth, pose in frames:
            job = (frame_id, pool.submit(prepare, depth, pose), pose)
            if pending is not None:
                yield pending[0], pending[1].result(), pending[2]
            pending = job
        if pending is not None:
            yield pending[0], pending[1].result(), pending[2]


def carve(
    grid: VoxelGrid,
    frames: Iterable[tuple[str, np.ndarray, np.ndarray]],
    camera: Camera,
    k: int,
    tol_sigmas: float = DEFAULT_TOL_SIGMAS,
    voxel_margin: float = 1.0,
    silhouette_px: int = 0,
    progress: Callable[[int], None] | None = None,
    veto: float | None = DEFAULT_VETO,
    settle: int = DEFAULT_SETTLE,
    shadows: bool = False,
    unbacked: int | None = None,
    block: int = DEFAULT_BLOCK,
    ahead: bool = True,
) -> CarveResult:
    """Count free-space votes per voxel.

    ``frames`` yields (frame id, depth (H, W) float32 metres with 0 = none, pose 4x4 object to
    camera). Voxels are grouped in blocks of ``block`` per side; a frame decides a block whole when the
    hull of its voxels' projections (its 8 corners' pixel rectangle and depth range) lies where the
    frame's min / max image pyramids (:mod:`reconstruct.pyramid`) prove every voxel seen free, or
    none seen free or just behind the surface; the other blocks are decided voxel by voxel (float64).
    The votes are those of every voxel decided alone (tests/test_reconstruct.py checks it). Blocks
    whose voxels are all carved for good leave the active set.

    With ``veto`` (a ratio), frames that see a voxel just behind the measured surface (0 to one
    tolerance deep: evidence it is inside the object) are counted too, and a voxel is carved only
    when its free votes are at least ``veto`` times those; voxels then leave the active set once
    seen free in more than ``max(k, settle)`` frames. With ``unbacked`` (and the veto), voxels no
    frame saw just behind the surface are carved once seen free in more than ``unbacked`` frames.

    With ``shadows``, missing pixels that a projector shadow explains count as free up to the
    occluder's depth (:func:`shadow_free_depth`); they never count as "just behind the surface".

    ``ahead``: prepare the next frame's images on a second thread meanwhile (off: one thread, the same votes).
    """
    drop = k if veto is None else max(k, settle)
    B = max(1, int(block))
    vs = grid.voxel_size
    nb = tuple(-(-s // B) for s in grid.shape)  # blocks per axis (the last ones may stick out of the grid)
    n_blocks = int(np.prod(nb))
    block_ijk = np.stack(np.unravel_index(np.arange(n_blocks), nb), axis=0).astype(np.float64)  # (3, n_blocks)
    block_origin = np.asarray(grid.origin, np.float64)[:, None] + vs * B * block_ijk  # centre of each block's first voxel
    local = np.stack(np.unravel_index(np.arange(B ** 3), (B, B, B)), axis=0).astype(np.float64) * vs  # (3, B^3)
    corners = np.stack(np.unravel_index(np.arange(8), (2, 2, 2)), axis=0).astype(np.float64) * vs * (B - 1)  # (3, 8)
    # free votes of a voxel = lazy[block] (frames that saw the whole block free) + fine[block, voxel]
    lazy = np.zeros(n_blocks, dtype=np.int32)
    fine = np.zeros((n_blocks, B ** 3), dtype=np.int32)
    inside_grid = np.ones(tuple(n * B for n in nb), dtype=bool)
    inside_grid[grid.shape[0]:, :, :] = inside_grid[:, grid.shape[1]:, :] = inside_grid[:, :, grid.shape[2]:] = False
    inside_grid = inside_grid.reshape(nb[0], B, nb[1], B, nb[2], B).transpose(0, 2, 4, 1, 3, 5).reshape(n_blocks, B ** 3)
    fine[~inside_grid] = drop + 1  # voxels past the grid's end: settled from the start, cropped at the end
    fine_min = fine.min(axis=1)
    behind = np.zeros((n_blocks, B ** 3), dtype=np.uint16) if veto is not None else None
    active = np.flatnonzero(lazy + fine_min <= drop)  # blocks with a voxel not carved for good yet
    half_diagonal = np.float32(voxel_margin * np.sqrt(3.0) / 2 * grid.voxel_size)
    K = camera.K
    width, height = camera.width, camera.height
    ids: list[str] = []
    projections = 0
    eps_px, eps_z = 1e-6, 1e-9  # rounding slack (pixels, metres): a block near a decision boundary is refined
    def prepare(depth: np.ndarray, pose: np.ndarray) -> FrameImages:
        return _frame_images(depth, grid_rows(grid, pose, K, height), **options)

    options = dict(fx=float(K[0, 0]), tol_sigmas=tol_sigmas, half_diagonal=half_diagonal, silhouette_px=silhouette_px,
                   shadows=shadows, behind=veto is not None)
    for done, (frame_id, images, pose) in enumerate(_prefetched(frames, prepare, ahead), start=1):
        ids.append(frame_id)
        if progress is not None and not active.size:
            progress(done)
        if not active.size:
            continue
        flat_threshold, flat_near, flat_far = images.threshold.reshape(-1), images.near.reshape(-1), images.far.reshape(-1)
        # [u z, v z, z] = K (R p + t), in float64
        M = K @ np.asarray(pose, dtype=np.float64)[:3, :]
        qb = M[:, :3] @ block_origin[:, active] + M[:, 3:4]  # (3, blocks)
        qc = (M[:, :3] @ corners)[:, :, None] + qb[:, None, :]  # (3, 8 corners, blocks): reductions over the short axis first
        projections += qc[0].size
        zc = qc[2]
        z_lo, z_hi = np.minimum.reduce(zc, axis=0), np.maximum.reduce(zc, axis=0)
        in_front = z_lo > 1e-3  # the box's image is the hull of its corners' images only in front of the camera
        safe = np.where(in_front, zc, 1.0)
        uc, vc = qc[0] / safe, qc[1] / safe
        # padded pixel index floor(u + 1.5), clipped onto the border, of every voxel centre lies in these ranges
        x0 = np.clip(np.floor(np.minimum.reduce(uc, axis=0) + 1.5 - eps_px), 0, width + 1).astype(np.int64)
        x1 = np.clip(np.floor(np.maximum.reduce(uc, axis=0) + 1.5 + eps_px), 0, width + 1).astype(np.int64)
        y0 = np.clip(np.floor(np.minimum.reduce(vc, axis=0) + 1.5 - eps_px), 0, height + 1).astype(np.int64)
        y1 = np.clip(np.floor(np.maximum.reduce(vc, axis=0) + 1.5 + eps_px), 0, height + 1).astype(np.int64)
        level = pyramid.rectangle_level(y1 - y0 + 1, x1 - x0 + 1)
        # rows within the images' band (the grid's voxels project into it; the clip only moves the
        # voxels past the grid's end that fill the last blocks, which are never counted)
        band = images.threshold.shape[0] - 1
        y0 = np.clip(y0 - images.row0, 0, band)
        y1 = np.clip(y1 - images.row0, 0, band)
        all_free = in_front & (pyramid.query(images.threshold_min, y0, y1, x0, x1, level) > z_hi + eps_z)
        need_free = ~(all_free | (in_front & (pyramid.query(images.threshold_max, y0, y1, x0, x1, level) <= z_lo - eps_z)))
        lazy[active[all_free]] += 1
        if veto is not None:  # a block seen all free has no voxel behind the surface
            near_lo = pyramid.query(images.near_min, y0, y1, x0, x1, level)
            far_hi = pyramid.query(images.far_max, y0, y1, x0, x1, level)
            need_behind = ~(all_free | (in_front & ((z_hi + eps_z < near_lo) | (z_lo - eps_z > far_hi))))
        else:
            need_behind = np.zeros_like(need_free)
        dq = M[:, :3] @ local  # (3, B^3)
        rows_band = (images.row0, images.row0 + images.threshold.shape[0] - 1)  # padded rows of the images (as above)
        mixed = 0
        # per-voxel decisions for the blocks that need them, each group with only the tests its blocks need
        for count_free, count_behind in ((True, True), (True, False), (False, True)):
            group = np.flatnonzero((need_free if count_free else ~need_free) & (need_behind if count_behind else ~need_behind))
            mixed += group.size
            for start in range(0, group.size, MIXED_CHUNK):
                part = group[start:start + MIXED_CHUNK]
                blocks = active[part]
                q = qb[:, part, None] + dq[:, None, :]  # (3, blocks, B^3)
                projections += q[0].size
                z = q[2]
                behind_camera = None
                if not in_front[part].all():  # the camera is inside the grid: voxels behind it are unknown
                    behind_camera = z <= 1e-3
                    z = np.where(behind_camera, 1.0, z)
                inverse = np.reciprocal(z)
                u = q[0]
                u *= inverse
                u += 1.5
                np.clip(u, 0.0, width + 1.0, out=u)
                v = q[1]
                v *= inverse
                v += 1.5
                # padded row floor(v + 1.5) clipped onto the border, then onto the band: clipping v onto the band's
                # (integer) rows floors to the same row
                np.clip(v, rows_band[0], rows_band[1], out=v)
                pixel = v.astype(np.intp)
                pixel -= images.row0
                pixel *= width + 2
                pixel += u.astype(np.intp)
                votes = fine[blocks]
                alive = votes <= drop - lazy[blocks, None]  # voxels not carved for good before this frame
                if behind_camera is not None:
                    alive &= ~behind_camera
                if count_free:
                    votes += (flat_threshold[pixel] > z) & alive
                    fine[blocks] = votes
                if count_behind:
                    behind[blocks] += (z >= flat_near[pixel]) & (z <= flat_far[pixel]) & alive
        if progress is not None:
            progress(done)
        if done % PRUNE_EVERY == 0 or not mixed:  # fine votes only grow: a stale minimum keeps settled blocks a little longer, nothing else
            fine_min[active] = np.minimum.reduce(fine[active], axis=1)
        active = active[lazy[active] + fine_min[active] <= drop]
    # free votes saturate at drop + 1 (a voxel carved for good is no longer counted)
    count = np.minimum(lazy[:, None] + fine, drop + 1).astype(np.uint16)

    def to_grid(values: np.ndarray) -> np.ndarray:
        full = values.reshape(nb + (B, B, B)).transpose(0, 3, 1, 4, 2, 5).reshape(tuple(n * B for n in nb))
        return np.ascontiguousarray(full[: grid.shape[0], : grid.shape[1], : grid.shape[2]])

    return CarveResult(grid, to_grid(count), k, ids, projections, None if behind is None else to_grid(behind), veto, drop,
                       None if veto is None else unbacked)


class Rings:
    """The rings of a grid about a vertical axis: the voxels of one height (y index) whose radius about the axis at
    (x, z) = ``centre`` (object frame, m) rounds to the same half voxel. Sums over rings and spreads back, no loops."""

    def __init__(self, grid: VoxelGrid, centre=(0.0, 0.0)) -> None:
        x = grid.axis_coordinates(0) - centre[0]
        z = grid.axis_coordinates(2) - centre[1]
        ring = np.rint(np.sqrt(x[:, None] ** 2 + z[None, :] ** 2) / (grid.voxel_size / 2)).astype(np.int64).reshape(-1)
        n_rings = int(ring.max()) + 1
        self.shape = grid.shape
        self.count = grid.shape[1] * n_rings
        self.index = (np.arange(grid.shape[1])[:, None] * n_rings + ring[None, :]).reshape(-1)  # per voxel, (y, x, z) order

    def _flat(self, voxels: np.ndarray) -> np.ndarray:
        return np.asarray(voxels).transpose(1, 0, 2).reshape(-1)

    def sum(self, voxels: np.ndarray) -> np.ndarray:
        """(count,) float: per ring, the sum of ``voxels`` ((nx, ny, nz) bool or numbers)."""
        return np.bincount(self.index, weights=self._flat(voxels), minlength=self.count)

    def size(self) -> np.ndarray:
        """(count,) int: the voxels of each ring."""
        return np.bincount(self.index, minlength=self.count)

    def spread(self, per_ring: np.ndarray) -> np.ndarray:
        """(nx, ny, nz): each voxel takes its ring's value of ``per_ring`` ((count,))."""
        nx, ny, nz = self.shape
        return per_ring[self.index].reshape(ny, nx, nz).transpose(1, 0, 2)


def revolve_occupancy(occupied: np.ndarray, grid: VoxelGrid, carved_share: float = DEFAULT_CARVED_SHARE, observed: np.ndarray | None = None) -> np.ndarray:
    """Occupancy made symmetric about the object y axis: a ring is carved where ``carved_share`` of it is.

    A ring is the voxels of one height whose radius rounds to the same half voxel. A share below
    one fills the sides never seen (a hand in the way, one side never facing the camera); above
    zero it ignores the odd voxel a noisy frame carved too deep. With ``observed`` (nx, ny, nz) bool
    (voxels some frame saw free or just behind the surface), the share is of the ring's observed
    voxels (at least OBSERVED_FLOOR of the ring): a side never seen does not count against carving,
    so the share can be high enough that frames whose pose errors see a thin rim free do not eat it.
    Returns (nx, ny, nz) bool.
    """
    rings = Rings(grid)
    carved_count = rings.sum(~occupied)
    total = rings.size()
    if observed is not None:
        total = np.maximum(rings.sum(observed), OBSERVED_FLOOR * total)
    return ~rings.spread(carved_count >= carved_share * np.maximum(total, 1))
