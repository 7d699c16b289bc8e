"""Input checks shared by the metric functions: shapes, finiteness, rigid transforms."""

from __future__ import annotations

import numpy as np

#: Tolerance on |R^T R - I| and |det R - 1| for a matrix to count as a rotation.
ROTATION_TOLERANCE = 1e-6


def finite_array(value, name: str, shape_tail: tuple[int, ...]) -> np.ndarray:
    """``value`` as float64 with trailing shape ``shape_tail``; ValueError if malformed or not finite."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name}: not a numeric array ({error})") from None
    if array.ndim < len(shape_tail) or array.shape[array.ndim - len(shape_tail):] != shape_tail:
        raise ValueError(f"{name}: expected shape (..., {', '.join(map(str, shape_tail))}), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: contains NaN or inf")
    return array


def rotations(value, name: str) -> np.ndarray:
    """(..., 3, 3) rotation matrices; ValueError unless finite, orthonormal and proper."""
    R = finite_array(value, name, (3, 3))
    gram = np.matmul(np.swapaxes(R, -1, -2), R) - np.eye(3)
    # det R by cofactors along the first row (np.linalg.det's LU costs more for a stack of 3x3)
    r = [[R[..., i, j] for j in range(3)] for i in range(3)]
    det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
           + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
    if np.any(np.abs(gram) > ROTATION_TOLERANCE) or np.any(np.abs(det - 1.0) > ROTATION_TOLERANCE):
        raise ValueError(f"{name}: not a rotation matrix (not orthonormal with determinant +1)")
    return R


def rigid_transforms(value, name: str) -> np.ndarray:
    """(..., 4, 4) rigid transforms [R t; 0 0 0 1]; ValueError otherwise."""
    T = finite_array(value, name, (4, 4))
    if np.any(np.abs(T[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])) > ROTATION_TOLERANCE):
        raise ValueError(f"{name}: last row of a rigid transform must be [0, 0, 0, 1]")
    rotations(T[..., :3, :3], name)
    return T


def extents(value, name: str) -> np.ndarray:
    """(..., 3) box side lengths, finite and >= 0 (metres)."""
    e = finite_array(value, name, (3,))
    if np.any(e < 0):
        raise ValueError(f"{name}: negative box extent")
    return e


def symmetry(value) -> str:
    """Normalise a symmetry label: None / "none" -> "none", "y" -> "y"."""
    if value is None or value == "none":
        return "none"
    if value == "y":
        return "y"
    raise ValueError(f"symmetry must be 'none' or 'y', got {value!r}")
