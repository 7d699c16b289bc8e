"""A box-like object's frame from its faces: the rotation that turns the model's face normals onto the box axes.

A camera's body is a box whose faces are the object frame's planes, so its model's normals cluster around
the six directions +-x, +-y, +-z. Each placed box carries its own tilt error (up to 3 deg) and the common
object frame takes their mean (1-1.5 deg off); the faces themselves pin the rotation down to the normals'
noise over thousands of points. :func:`face_rotation` finds the small rotation Rf that brings the normals
within a cone of the axes onto them (least squares, linearised and repeated); poses are then corrected by
``pose @ Rf^T`` (engine._snap_faces).

Not for every shape:
- where a part is tilted against the frame (a laptop's lid), it falls into a cone and drags the fit: a
  laptop's side faces are too thin to show up (:func:`box_like`: each axis needs a share of the normals);
- a round body (a mug) has normals spread around its axis: its side fills the cones about x and z by as much
  as the gaps between them, and nothing there fixes a spin (:func:`box_like`: the faces must hold most normals).
  Symmetric objects are left to the axis snap, except where it is refused (a shallow bowl):
  :func:`tilt_onto_axis` then turns the normals near +-y (its foot, its inner bottom) onto y.
- a laptop has a frame in its faces all the same (:func:`hinge_rotation`): its base's top and bottom face along y,
  and its lid, hinged along x, faces somewhere in the y-z plane whatever its angle. Without it, its box keeps the
  placed boxes' mean tilt, a degree or so off. The plane is narrow (``TrackingConfig.hinge_plane_deg``, 3 deg):
  within a wider one the normals along the lid's side edges, which lean out of the plane on the side seen more,
  turn the spin off. The base's cone alone, the spin left as it is, does less well.

The bowls' flat faces (engine, ``TrackingConfig.flat_snap``): where a bowl's axis fit is refused,
:func:`tilt_onto_axis` turns its box by a degree or less, which lowers the rotation errors a little overall and
changes no flag. Its cone (``TrackingConfig.flat_cone_deg``) is 5 deg: 3 and 7 deg do no better. It is not used
on cans and bottles in place of their axis snap: there it makes the rotations worse.

On a camera the face snap (:func:`face_rotation`) lowers the rotation error; on a laptop it does harm (its lid
falls into the z cone), and :func:`box_like` keeps it out. The shares of a model's normals in the cones tell them
apart (``TrackingConfig.min_face_share`` / ``min_faces_total``): a camera's six cones hold about two thirds to
three quarters of its normals, 7-14 % about x; a laptop holds under 1 % about x; a mug's six cones a fifth to a
third.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: the six face directions of a box, object frame
AXES = np.vstack([np.eye(3), -np.eye(3)])


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (N, 3, 3) of vectors (N, 3): skew(v) @ w = v x w."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _unit_rows(normals: np.ndarray) -> np.ndarray:
    """The finite rows of ``normals`` (N, 3), each scaled to unit length (estimated normals come unnormalised)."""
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    normals = normals[np.all(np.isfinite(normals), axis=1)]
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def face_rotation(normals: np.ndarray, cone_deg: float = 10.0, min_points: int = 30, iterations: int = 4) -> tuple[np.ndarray | None, np.ndarray]:
    """The rotation Rf (3x3) with ``Rf @ n`` on the nearest box axis for the normals ``n`` (N, 3; unit, object
    frame, either sign) that lie within ``cone_deg`` of one, and the count of such normals per axis (6,: +x, +y,
    +z, -x, -y, -z, after the rotation). None where fewer than ``min_points`` normals lie in the cones.

    Axes holding fewer than ``min_points`` normals are left out of the fit (a stray patch is not a face).
    """
    normals = _unit_rows(normals)
    rotation, cos_cone = np.eye(3), np.cos(np.radians(cone_deg))
    counts = np.zeros(6, dtype=int)
    for _ in range(iterations):
        turned = normals @ rotation.T
        dots = turned @ AXES.T
        nearest = np.argmax(dots, axis=1)
        inside = dots[np.arange(len(turned)), nearest] > cos_cone
        counts = np.bincount(nearest[inside], minlength=6)
        used = inside & np.isin(nearest, np.flatnonzero(counts >= min_points))
        if used.sum() < min_points:
            return None, counts
        rotation = _turn_onto(turned[used], AXES[nearest[used]], (0, 1, 2)) @ rotation
    return rotation, counts


def _alignment_rows(m: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The linearised least-squares rows (3N, 3) and right-hand side (3N,) for a small rotation w turning unit
    vectors ``m`` (N, 3) onto ``a`` (N, 3): (I + [w]x) m ~ a, i.e. w x m = -(m x w) = a - m."""
    return -_skew(m).reshape(-1, 3), (a - m).reshape(-1)


def _turn_onto(m: np.ndarray, a: np.ndarray, about: tuple[int, ...]) -> np.ndarray:
    """The small rotation (3x3) about the object axes ``about`` that best turns unit vectors ``m`` (N, 3) onto
    ``a`` (N, 3) (:func:`_alignment_rows`)."""
    return _small_rotation(*_alignment_rows(m, a), about)


def _small_rotation(rows: np.ndarray, rhs: np.ndarray, about) -> np.ndarray:
    """The rotation (3x3) of the rotation vector w, zero but about the object axes ``about``, that solves the
    linearised rows (K, 3) ``rows`` w ~ ``rhs`` (K,) in the least-squares sense."""
    columns = list(about)
    w = np.zeros(3)
    w[columns], *_ = np.linalg.lstsq(rows[:, columns], rhs, rcond=None)
    return Rotation.from_rotvec(w).as_matrix()


def _near_y(turned: np.ndarray, cos_cone: float) -> tuple[np.ndarray, np.ndarray]:
    """Which of the unit normals ``turned`` (N, 3) lie within the cone (cosine ``cos_cone``) of +-y (N,), and the
    axis each of those faces along (+y or -y; (K, 3))."""
    near = np.abs(turned[:, 1]) > cos_cone
    targets = np.zeros((int(near.sum()), 3))
    targets[:, 1] = np.sign(turned[near, 1])
    return near, targets


def tilt_onto_axis(normals: np.ndarray, cone_deg: float = 5.0, min_points: int = 30, iterations: int = 6) -> tuple[np.ndarray | None, int]:
    """The rotation Rt (3x3, about x and z only) with ``Rt @ n`` on +-y for the normals ``n`` (N, 3; unit, object
    frame) within ``cone_deg`` of +-y, and how many normals lay there at the last step (before its own turn);
    None where fewer than ``min_points`` do.

    A symmetric object's flat faces across its axis (a bowl's foot and inner bottom) face along it exactly; the
    curved parts near them are spread evenly about it, so the cone's mean is the axis too. The spin about y is
    left alone (it is free for symmetry y).
    """
    normals = _unit_rows(normals)
    rotation, cos_cone, count = np.eye(3), np.cos(np.radians(cone_deg)), 0
    for _ in range(iterations):
        turned = normals @ rotation.T
        near, a = _near_y(turned, cos_cone)
        count = int(near.sum())
        if count < min_points:
            return None, count
        rotation = _turn_onto(turned[near], a, (0, 2)) @ rotation
    return rotation, count


def hinge_rotation(normals: np.ndarray, cone_deg: float = 5.0, plane_deg: float = 3.0, min_points: int = 30, iterations: int = 6,
                   min_spin_share: float = 0.05) -> tuple[np.ndarray | None, np.ndarray]:
    """The rotation Rh (3x3) that turns the normals ``n`` (N, 3; unit, object frame) within ``cone_deg`` of +-y onto
    +-y and those within ``plane_deg`` of the y-z plane into it, and the shares of the normals in the cone and in
    the plane at the last step (2,). None where fewer than ``min_points`` normals lie in either. The spin about y
    is turned only where the plane's normals hold a z component of at least ``min_spin_share`` of all the normals
    (the sum of their squared z components): a lid; a flat slab alone leaves its spin as it is.

    A laptop's faces: its base's top and bottom face along y; its lid, hinged along x, faces somewhere in the y-z
    plane, as do the base's front and back edges. The cone fixes the tilt about x and z; the plane fixes the spin
    about y (a spin gives the lid's normals an x component) and z again. The box's x faces are too thin to count
    (:func:`box_like`), and the lid's own angle is free: only its hinge's direction is used.
    """
    normals = _unit_rows(normals)
    rotation = np.eye(3)
    cos_cone, sin_plane = np.cos(np.radians(cone_deg)), np.sin(np.radians(plane_deg))
    shares = np.zeros(2)
    for _ in range(iterations):
        turned = normals @ rotation.T
        near, a = _near_y(turned, cos_cone)
        flat = np.abs(turned[:, 0]) < sin_plane if plane_deg > 0 else np.zeros(len(turned), dtype=bool)
        shares = np.array([near.mean(), flat.mean()]) if len(turned) else shares
        if near.sum() < min_points or (plane_deg > 0 and flat.sum() < min_points):
            return None, shares
        # (I + [w]x) m ~ a for the cone; the x row of (I + [w]x) p = 0 for the plane: w_y p_z - w_z p_y = -p_x
        cone_rows, cone_rhs = _alignment_rows(turned[near], a)
        p = turned[flat]
        rows = np.vstack([cone_rows, np.column_stack([np.zeros(len(p)), p[:, 2], -p[:, 1]])])
        rhs = np.concatenate([cone_rhs, -p[:, 0]])
        # the spin is seen only by normals with a z component (the lid, the base's front and back): where they are
        # too few, the normals' noise alone would set it, and it is left as it is
        about = [0, 1, 2] if len(p) and np.sum(p[:, 2] ** 2) >= min_spin_share * len(normals) else [0, 2]
        rotation = _small_rotation(rows, rhs, about) @ rotation
    return rotation, shares


def box_like(counts: np.ndarray, total: int, min_share: float, min_total: float) -> bool:
    """Whether each of the three axes holds at least ``min_share`` of the ``total`` normals in its two cones and
    all six cones together at least ``min_total`` (``counts`` from :func:`face_rotation`): a box seen on all its
    sides; not a laptop (thin sides) or a plate, nor a round body whose side faces every way (a mug)."""
    counts = np.asarray(counts)
    per_axis = counts.reshape(2, 3).sum(axis=0)
    return total > 0 and bool(np.all(per_axis >= min_share * total)) and bool(counts.sum() >= min_total * total)
