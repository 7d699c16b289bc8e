"""The tight box: the object-frame axis-aligned box of the mesh, the mesh re-centred on it, poses updated.

A pose maps object to camera, p_cam = R p_obj + t. Moving the object origin to the box centre
``c`` (old object frame) gives p_obj' = p_obj - c, so the same camera points need t' = t + R c.
"""

from __future__ import annotations

import numpy as np
import trimesh


def tight_box(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), full extents (3,)) of the axis-aligned box of (N, 3) points, metres."""
    vertices = np.asarray(vertices, dtype=np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return (lo + hi) / 2, hi - lo


def recentre_pose(pose: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The 4x4 pose of the object frame moved to ``centre`` (old object frame): t' = t + R c."""
    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, 3] = out[:3, 3] + out[:3, :3] @ np.asarray(centre, dtype=np.float64)
    return out


def fit_tight_box(mesh: trimesh.Trimesh, poses: dict[str, np.ndarray]) -> tuple[trimesh.Trimesh, dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Re-centre ``mesh`` on its tight box and update every pose to match.

    Returns (centred mesh (copy), updated poses, centre in the old object frame, full extents).
    """
    centre, extents = tight_box(mesh.vertices)
    centred = mesh.copy()
    centred.apply_translation(-centre)
    return centred, {key: recentre_pose(T, centre) for key, T in poses.items()}, centre, extents
