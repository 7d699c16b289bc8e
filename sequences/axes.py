"""Object axis conventions and the rotations between them and ShapeNet's (y up), the toolkit's object frame.

Each convention is a proper rotation ``SHAPENET_FROM[name]`` with ``p_shapenet = SHAPENET_FROM[name] @ p_name``:

- ``shapenet``: y up (a mug's handle along -z), the toolkit's own object frame;
- ``redwood75``: REDWOOD75's raw axes (raw x = ShapeNet z, raw y = -ShapeNet y, raw z = ShapeNet x), as
  cpas_toolbox's ``redwood75.yaml`` remaps them (``remap_y_axis: -y, remap_x_axis: z``);
- ``nocs``: NOCS REAL275's model axes (ShapeNet x = NOCS z, y = y, z = -NOCS x), as ``real275.yaml``
  remaps them (``remap_y_axis: y, remap_x_axis: -z``);
- ``ycb``: YCB models (z up): ShapeNet x = YCB x, y = YCB z, z = -YCB y.

The data layer owns these conventions; ``evaluate.geometry`` re-exports the REDWOOD75 ones.
"""

from __future__ import annotations

import numpy as np

#: REDWOOD75 raw object axes in terms of ShapeNet axes.  ``p_raw = RAW_FROM_SHAPENET @ p_shapenet``.
RAW_FROM_SHAPENET = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
SHAPENET_FROM_RAW = RAW_FROM_SHAPENET.T
#: ShapeNet coordinates from NOCS coordinates (cpas_toolbox's rotation for y -> y, x -> -z).
SHAPENET_FROM_NOCS = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
#: ShapeNet coordinates from YCB model coordinates (z up).
SHAPENET_FROM_YCB = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

SHAPENET_FROM = {
    "shapenet": np.eye(3),
    "redwood75": SHAPENET_FROM_RAW,
    "nocs": SHAPENET_FROM_NOCS,
    "ycb": SHAPENET_FROM_YCB,
}
#: The axis conventions a mesh file may use.
MESH_AXES = tuple(SHAPENET_FROM)


def to_shapenet_points(points, axes: str) -> np.ndarray:
    """(N, 3) points in ``axes`` coordinates to ShapeNet coordinates (same units and origin)."""
    return np.asarray(points, dtype=np.float64) @ SHAPENET_FROM[axes].T


def shapenet_to_raw_points(points) -> np.ndarray:
    return np.asarray(points, dtype=np.float64) @ RAW_FROM_SHAPENET.T


def raw_to_shapenet_points(points) -> np.ndarray:
    return to_shapenet_points(points, "redwood75")


def raw_to_shapenet_rotation(R_raw) -> np.ndarray:
    """Object-to-camera rotation(s) (..., 3, 3) of an object in raw REDWOOD75 axes to those of the same object in
    ShapeNet axes: ``R_shapenet = R_raw @ RAW_FROM_SHAPENET`` (ShapeNet coordinates -> raw -> camera)."""
    return np.asarray(R_raw, dtype=np.float64) @ RAW_FROM_SHAPENET
