"""The seen surface from fused depth: a truncated signed distance field on the carving's grid, joined with the carved hull.

The carving (:mod:`reconstruct.carving`) keeps a voxel unless frames see it free beyond a noise tolerance, so a surface
seen head-on ends up to that tolerance outside the measured one. Averaging the depth of every frame that measured a
surface places it at the mean of the measurements instead: here Open3D's TSDF fusion (``t.geometry.VoxelBlockGrid``,
KinectFusion's running average of the projective distance ``depth - z``, truncated at ``TRUNCATION_VOXELS``).

Steps, in the object frame on the carving's grid (same voxel centres, so the two fields meet without resampling):

1. per frame, the depth masked to the object: pixels whose measured point lies within ``HULL_REACH`` voxels of the
   carved solid (a hand or the table elsewhere is not fused; one pressed against the object is, and the carving
   removes what the others see free);
2. Open3D integrates the masked depth at the frame's pose into the blocks within the truncation of its points;
3. one signed field (positive outside, in [-1, 1]): where at least ``MIN_WEIGHT`` frames measured a voxel,
   the larger of the TSDF and the carving's field (the object lies inside both: the TSDF can only take away from the
   hull, never add to it: a corner's shadow that the TSDF fills behind an edge was seen free by the carving); elsewhere
   the carving's field alone, the blurred occupancy that :func:`reconstruct.meshing.occupancy_mesh` meshes (the unseen
   part keeps the hull, the symmetry prior's fill and the box prior).

The field's zero level, meshed by :func:`reconstruct.meshing.field_mesh`, is one closed surface: the fused surface where
frames measured it, the hull elsewhere.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from sequences.camera import Camera

from .carving import VoxelGrid

#: Truncation distance in voxels (6 mm at the default 2 mm): it must exceed the depth noise (sigma 1.3 mm at 0.6 m,
#: 2 mm at 1 m, plus 1-3 mm disparity steps) for the average to see both signs around the surface, and it bounds how
#: far the measurement of one side of a thin wall reaches through to the other. Measured on six sequences of the
#: benchmark's dev split from the true poses (laptop, square bowl, REDWOOD75 bowl, patterned mug, camera, wood block):
#: the largest error of a measured box face summed 13.4 / 12.2 / 13.8 mm with 2 / 3 / 4 voxels.
TRUNCATION_VOXELS = 3.0
#: A measured point belongs to the object when it lies within this many voxels of the carved solid: the carved solid
#: holds the surface (it is the space no frame saw free), the depth noise puts points up to ~2 sigma outside it.
HULL_REACH = 2
#: Voxels measured by fewer frames keep the carving's verdict (3 frames: 14.0 mm summed on the six sequences above).
MIN_WEIGHT = 1.0
#: Open3D's block side in voxels.
BLOCK_RESOLUTION = 8
#: Blur (voxels) of the carved occupancy before it becomes a signed field (as reconstruct.meshing.occupancy_mesh).
BLUR_SIGMA = 0.7


@dataclass
class FusedDepth:
    """A TSDF on a carving grid. ``tsdf`` (nx, ny, nz) float32: projective signed distance over the truncation, in
    [-1, 1], positive in front of the measured surface; ``weight`` (nx, ny, nz) float32: frames that measured the voxel
    (0: none; ``tsdf`` is 0 there)."""

    tsdf: np.ndarray
    weight: np.ndarray
    truncation: float  # metres
    frames: int


def object_depth(depth: np.ndarray, pose: np.ndarray, camera: Camera, near_solid: np.ndarray, grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray]:
    """``depth`` (H, W) float32 metres with every pixel but the object's set to 0: those whose measured point (at
    ``pose``, object to camera) falls in a voxel of ``near_solid`` ((nx, ny, nz) bool on ``grid``); and those voxels'
    indices ((N, 3) int64).

    Only the rectangle the grid projects to is back-projected (the whole image when part of the grid lies behind the
    camera), in float32: a voxel index is z (R^T r) / s - (R^T t + origin) / s for the pixel's ray r = ((u - cx) / fx,
    (v - cy) / fy, 1), depth z and voxel size s."""
    depth = np.asarray(depth, dtype=np.float32)
    pose = np.asarray(pose, dtype=np.float64)
    R, t = pose[:3, :3], pose[:3, 3]
    shape = np.array(grid.shape)
    rows, cols = camera.window(grid.corners() @ R.T + t)
    out = np.zeros_like(depth)
    crop = depth[rows, cols]
    vv, uu = np.nonzero(crop > 0)
    if not vv.size:
        return out, np.zeros((0, 3), np.int64)
    z = crop[vv, uu]
    x = ((np.arange(cols.start, cols.stop) - camera.cx) / camera.fx).astype(np.float32)[uu]
    y = ((np.arange(rows.start, rows.stop) - camera.cy) / camera.fy).astype(np.float32)[vv]
    M = (R.T / grid.voxel_size).astype(np.float32)
    c = ((R.T @ t + np.asarray(grid.origin)) / grid.voxel_size).astype(np.float32)
    index = []
    inside = np.ones(z.size, dtype=bool)
    for a in range(3):
        g = z * (M[a, 0] * x + M[a, 1] * y + M[a, 2]) - c[a]
        g += np.float32(0.5)  # nearest voxel: floor(g + 0.5), within the grid when 0 <= g + 0.5 < n
        inside &= (g >= 0) & (g < shape[a])
        index.append(g)
    index = np.stack([np.floor(g[inside]).astype(np.int64) for g in index], axis=1)
    near = near_solid[tuple(index.T)]
    keep = np.flatnonzero(inside)[near]
    out[vv[keep] + rows.start, uu[keep] + cols.start] = z[keep]
    return out, index[near]


def touched_blocks(index: np.ndarray, reach: int, shape: tuple[int, int, int]) -> np.ndarray:
    """(M, 3) int32 coordinates of the blocks (BLOCK_RESOLUTION voxels a side, grid indices) that hold a voxel within
    ``reach`` voxels (per axis) of a voxel of ``index`` ((N, 3) within the grid), on a grid of ``shape``: a block is
    wider than 2 ``reach``, so the blocks of a cube's 8 corners are all the blocks it touches."""
    B = BLOCK_RESOLUTION
    nb = np.array([-(-s // B) for s in shape])
    padded = nb + 2  # corners reach one block past either end of the grid
    touched = np.zeros(int(np.prod(padded)), dtype=bool)
    index = index.astype(np.int32) + np.int32(reach + B)  # + one block: every corner's block is counted from 0
    for corner in np.stack(np.unravel_index(np.arange(8), (2, 2, 2)), axis=1):
        block = [(index[:, a] - np.int32(2 * reach * (1 - corner[a]))) // np.int32(B) for a in range(3)]
        touched[(block[0] * padded[1] + block[1]) * padded[2] + block[2]] = True
    return (np.argwhere(touched.reshape(padded)[1:-1, 1:-1, 1:-1])).astype(np.int32)


def fuse(grid: VoxelGrid, frames: Iterable[tuple[str, np.ndarray, np.ndarray]], camera: Camera, solid: np.ndarray,
         truncation_voxels: float = TRUNCATION_VOXELS, hull_reach: int = HULL_REACH) -> FusedDepth:
    """Fuse the object's depth of ``frames`` ((frame id, depth (H, W) float32 metres with 0 = none, pose 4x4 object to
    camera) each) into a TSDF on ``grid``, with Open3D's ``VoxelBlockGrid`` on the CPU.

    The object's pixels are those near ``solid`` ((nx, ny, nz) bool, the carved object; :func:`object_depth`). Open3D
    puts voxel (i, j, k) of its blocks at (i, j, k) voxel sizes from its world origin, so the grid's first voxel centre
    is made that origin (the extrinsic is the pose composed with that shift). Open3D reads the pixel ``int(u)`` for a
    projection ``u``; pixel centres lie at integer coordinates, so the principal point is passed half a pixel further on
    (``int(u + 0.5)``: the nearest pixel, as the carving reads it). Each frame integrates the blocks within the
    truncation of its object points (Open3D's own allocation from a depth image reads every fourth pixel only): every
    voxel of them that projects to a fused pixel, ``depth - z`` above minus the truncation, is updated; voxels of no
    frame's blocks keep weight 0.
    """
    import open3d as o3d
    import open3d.core as o3c

    vs = grid.voxel_size
    truncation = float(truncation_voxels) * vs
    reach = int(np.ceil(truncation_voxels))
    near_solid = ndimage.binary_dilation(solid, ndimage.generate_binary_structure(3, 1), iterations=hull_reach) if hull_reach > 0 else solid
    capacity = int(np.prod([-(-s // BLOCK_RESOLUTION) for s in grid.shape]))  # every block of the grid: the hash map never grows
    volume = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), ((1), (1)), vs, BLOCK_RESOLUTION, capacity)
    K = camera.K.astype(np.float64).copy()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    intrinsic = o3c.Tensor(K)
    shift = np.eye(4)
    shift[:3, 3] = grid.origin  # Open3D's world (voxel index times size) -> object frame
    count = 0
    for _, depth, pose in frames:
        masked, index = object_depth(depth, pose, camera, near_solid, grid)
        if not len(index):
            continue
        count += 1
        keys = o3c.Tensor(touched_blocks(index, reach, grid.shape))
        volume.integrate(keys, o3d.t.geometry.Image(o3c.Tensor(masked)), intrinsic, o3c.Tensor(np.asarray(pose, np.float64) @ shift),
                         1.0, float(masked.max()) + 1.0, float(truncation_voxels))
    tsdf = np.zeros(grid.shape, dtype=np.float32)
    weight = np.zeros(grid.shape, dtype=np.float32)
    if count:
        coordinates, indices = volume.voxel_coordinates_and_flattened_indices()
        index = np.rint(coordinates.numpy() / vs).astype(np.int64)
        flat = indices.numpy().reshape(-1)
        inside = np.all((index >= 0) & (index < np.array(grid.shape)), axis=1)
        at = tuple(index[inside].T)
        tsdf[at] = volume.attribute("tsdf").reshape((-1,)).numpy()[flat[inside]]
        weight[at] = volume.attribute("weight").reshape((-1,)).numpy()[flat[inside]]
    return FusedDepth(tsdf, weight, truncation, count)


def carved_field(solid: np.ndarray, blur_sigma: float = BLUR_SIGMA) -> np.ndarray:
    """(nx, ny, nz) float32 signed field of a solid, positive outside, in [-1, 1]: the blurred occupancy ``f`` as
    ``2 (0.5 - f)``, whose zero level is the surface :func:`reconstruct.meshing.occupancy_mesh` meshes."""
    field = solid.astype(np.float32)
    if blur_sigma > 0:
        field = ndimage.gaussian_filter(field, blur_sigma, mode="constant")
    return 2.0 * (0.5 - field)


def joined_field(solid: np.ndarray, fused: FusedDepth, min_weight: float = MIN_WEIGHT, blur_sigma: float = BLUR_SIGMA) -> np.ndarray:
    """(nx, ny, nz) float32 signed field, positive outside: the larger of the TSDF and the carving's field where at
    least ``min_weight`` frames measured a voxel, the carving's field elsewhere."""
    carved = carved_field(solid, blur_sigma)
    measured = fused.weight >= min_weight
    return np.where(measured, np.maximum(fused.tsdf, carved), carved).astype(np.float32)
