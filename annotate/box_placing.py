"""Placing a box from a click or an outline, as pure functions on a frame's points.

The box is the one of :mod:`annotate.box_edits`: position (3,) m in the camera frame, orientation (4,) x y z w
object to camera, extents (3,) full sides along object x, y, z (m). Points are camera-frame (N, 3) m. A viewer
camera is given as ``(R, t, fov, aspect)``: R (3, 3) and t (3,) map its OpenCV frame (x right, y down, z forward)
to the world (here the sensor's camera frame), fov is vertical (rad), aspect width / height; screen coordinates run
0..1 from the top left, as viser reports them.

The steps of a placement (:func:`place_on_surface`):
1. the clicked point: the point nearest the camera among those within :data:`PICK_DEG` of the click's ray;
2. the surface it lies on (:func:`surface_region`): the pixels connected to it without a jump in depth, up to the
   box's reach. Fingers lying on the object stand proud of it and are cut off at their edges, and so is what lies
   behind (a body, a wall); a hand that only touches the object's side may stay;
3. the box, kept at its orientation and size, fitted to that surface's points (:func:`fit_position`): across the
   view it goes where it holds the most points (the middle of the shifts that hold nearly as many: where the object
   fits in it), along the view its front goes to the points' front; repeated from there. What of a hand is left
   adds points on one side only, fewer than the object's.
Measured on 10 suite sequences with hands (dev split, 7 frames each, clicked at the visible object's middle; median
/ p75 / p90 centre error): the true orientation and size 8 / 17 / 30 mm (fitting all points instead of the surface:
18 / 29 / 59 mm), the true orientation and the category's typical size 19 / 45 / 69 mm, upright facing the camera
and the typical size 26 / 45 / 70 mm: the click gives the box's front and middle; its size and turn are the
annotator's (an outline, a face drag, a turn), and a click after them fits again.
An outline (a rectangle dragged on the view) gives the two sides across the view instead of the typical ones
(:func:`outline_box`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from sequences.camera import Camera

#: A point counts as clicked when it lies within this angle (deg) of the click's ray (a few screen pixels).
PICK_DEG = 1.0
#: ... and within this depth (m) of the nearest such point (the surface hit first, not what shows behind it).
PICK_DEPTH_BAND = 0.02
#: The box grown by this (m) on every side gathers the points the fit uses: room to walk onto the object.
FIT_MARGIN = 0.01
#: Fit rounds: a search across the view, then the depth from the front, each time from the last position.
FIT_ROUNDS = 4
#: The search across the view: this many shifts either way, up to half the box's largest side, then as many finer
#: ones between the coarse neighbours of the best.
SEARCH_STEPS = 10
FINE_STEPS = 4
#: The search along the view, in steps of this (m).
DEPTH_STEP = 0.002
#: Shifts whose box holds at least this share of the most points found form the plateau whose middle is taken.
PLATEAU_SHARE = 0.97
#: Along the view the box holds the points within this (m) of its faces (the sensor's noise), not the margin.
DEPTH_TOLERANCE = 0.002
#: An outline's front: this share of the points inside it lies in front (flying pixels, noise).
FRONT_QUANTILE = 0.05
#: Neighbouring pixels of one surface differ in depth by at most the larger of this (m) and this share of the depth
#: (at 0.6 m: 4.8 mm, a pixel spanning 1.1 mm: a surface turned up to 77 degrees from the view; fingers on an object
#: stand 1-2 cm proud of it). Chosen on the 10 suite sequences of the module's measurement: 4 / 6 / 10 mm (shares
#: 0.8 / 1.2 / 2 %) gave 8.3 / 10.2 / 11.1 mm median centre error with the true turn and size.
SURFACE_STEP_M = 0.004
SURFACE_STEP_SHARE = 0.008
#: Fewer points than this inside the box: no fit (the click stays where it hit).
MIN_FIT_POINTS = 30


def rotation(orientation) -> np.ndarray:
    return Rotation.from_quat(np.asarray(orientation, dtype=np.float64)).as_matrix()


def half_depth(orientation, extents, view) -> float:
    """How far (m) the box reaches from its centre toward the viewer along the unit direction ``view``: the support
    function of the box, sum over axes of |axis . view| times the half side."""
    return float(np.abs(rotation(orientation).T @ np.asarray(view, dtype=np.float64)) @ (np.asarray(extents, dtype=np.float64) / 2))


def pick_on_ray(points: np.ndarray, origin, direction, max_deg: float = PICK_DEG, band: float = PICK_DEPTH_BAND) -> np.ndarray | None:
    """The point a click along the ray (``origin``, ``direction``; world = camera frame) hits: among the points within
    ``max_deg`` of the ray, those within ``band`` m of the nearest, the one closest to the ray. None when none is near."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    rel = np.asarray(points, dtype=np.float64) - o
    t = rel @ d
    ahead = t > 1e-3
    if not np.any(ahead):
        return None
    rel, t = rel[ahead], t[ahead]
    off = np.linalg.norm(rel - t[:, None] * d, axis=1)
    near = off <= np.tan(np.radians(max_deg)) * t
    if not np.any(near):
        return None
    rel, t, off = rel[near], t[near], off[near]
    front = t <= t.min() + band
    k = np.argmin(np.where(front, off / t, np.inf))
    return o + rel[k]


class Fit(NamedTuple):
    """A fitted box position (3,) m, and the points it rests on (the count inside the box grown by the margin)."""

    position: np.ndarray
    points: int


def _across(view: np.ndarray) -> np.ndarray:
    """Two unit directions (3, 2) across the unit direction ``view``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(view[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(view, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(view, a)], axis=1)


def _plateau(local: np.ndarray, offsets: np.ndarray, half: np.ndarray, far: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Of the offsets (K, 3; box frame) whose box holds nearly the most of the points ``local`` (N, 3; box frame): their
    middle (the centre of the plateau where the object fits in the box), or with ``far`` the one farthest along that
    direction; and that most."""
    counts = np.array([np.count_nonzero(np.all(np.abs(local - o) <= half, axis=1)) for o in offsets])
    best = int(counts.max())
    near = offsets[counts >= PLATEAU_SHARE * best]
    if far is None:
        return near.mean(axis=0), best
    return near[np.argmax(near @ far)], best


def fit_position(points: np.ndarray, start, orientation, extents, margin: float = FIT_MARGIN, rounds: int = FIT_ROUNDS) -> Fit:
    """The box (orientation and extents kept) moved from ``start`` onto the points around it (see the module's steps).

    Across the view (the ray from the camera to the box centre), a search over shifts up to half the largest side:
    the box goes to the middle of the shifts that hold nearly the most points (the plateau where the object fits in
    it; what is attached adds points on one side only, and few). Along the view, the same search, but to the
    plateau's far end: the camera sees the object's front, so every shift toward the camera holds it, and the one
    that still holds it farthest back puts the box's front on the object's (a box's corner reaches further toward
    the camera than a round object's front: the half-depth of the box would put it too far back). Then again from
    there, ``rounds`` times at most."""
    R = rotation(orientation)
    extents = np.asarray(extents, dtype=np.float64)
    half = extents / 2 + margin
    centre = np.asarray(start, dtype=np.float64).copy()
    P = np.asarray(points, dtype=np.float64)
    P = P[np.linalg.norm(P - centre, axis=1) <= np.linalg.norm(extents) + extents.max()]  # what any shift can reach
    count = 0
    reach = extents.max() / 2
    for _ in range(rounds):
        view = centre / np.linalg.norm(centre)
        across = _across(view)
        local = (P - centre) @ R
        # across the view: coarse shifts, then fine ones around the best
        steps = np.linspace(-reach, reach, 2 * SEARCH_STEPS + 1)
        grid = np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 2)
        shift, count = _plateau(local, (grid @ across.T) @ R, half)
        fine = np.linspace(-1, 1, 2 * FINE_STEPS + 1) * (steps[1] - steps[0])
        grid = np.stack(np.meshgrid(fine, fine, indexing="ij"), axis=-1).reshape(-1, 2)
        shift, count = _plateau(local, shift + (grid @ across.T) @ R, half)
        if count < MIN_FIT_POINTS:
            break
        # along the view: the farthest shift that still holds nearly all
        depths = np.arange(-reach, reach + 1e-9, DEPTH_STEP)
        shift, count = _plateau(local, shift + np.outer(depths, R.T @ view), extents / 2 + DEPTH_TOLERANCE, far=R.T @ view)
        moved = centre + R @ shift
        done = np.linalg.norm(moved - centre) < 5e-4
        centre = moved
        if done:
            break
    return Fit(centre, count)


def surface_region(depth: np.ndarray, camera: Camera, seed, radius: float, step: float | None = None) -> np.ndarray:
    """(H, W) bool: the pixels of the surface the sensor pixel nearest the camera-frame point ``seed`` lies on, up to
    ``radius`` m from it: connected through neighbours whose depths differ by at most ``step`` m (default
    :func:`depth_step` at the seed's depth). Where something lies on the object (fingers), the depth jumps at its
    edge, and what lies behind it (a body, a wall) is separate; a hand that only touches the object's side may stay."""
    depth = np.asarray(depth, dtype=np.float64)
    seed = np.asarray(seed, dtype=np.float64)
    step = depth_step(seed[2]) if step is None else step
    uv, _ = camera.project(seed[None])
    u, v = uv[0]
    # a window around the seed reaching ``radius`` at the seed's depth
    r = int(np.ceil(radius * max(camera.fx, camera.fy) / max(seed[2] - radius, 0.05)))
    u0, u1 = max(int(round(u)) - r, 0), min(int(round(u)) + r + 1, depth.shape[1])
    v0, v1 = max(int(round(v)) - r, 0), min(int(round(v)) + r + 1, depth.shape[0])
    out = np.zeros(depth.shape, dtype=bool)
    if u0 >= u1 or v0 >= v1:
        return out
    window = depth[v0:v1, u0:u1]
    valid = np.isfinite(window) & (window > 0)
    us, vs = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
    z = np.where(valid, window, np.nan)
    near = valid & (((us - camera.cx) / camera.fx * z - seed[0]) ** 2 + ((vs - camera.cy) / camera.fy * z - seed[1]) ** 2
                    + (z - seed[2]) ** 2 <= radius ** 2)
    # a pixel at a jump (to any 4-neighbour, or to no measurement) belongs to no surface: it cuts the surfaces apart
    jump = np.zeros_like(near)
    with np.errstate(invalid="ignore"):
        dz_u = np.abs(np.diff(z, axis=1)) > step
        dz_v = np.abs(np.diff(z, axis=0)) > step
    jump[:, 1:] |= dz_u
    jump[:, :-1] |= dz_u
    jump[1:, :] |= dz_v
    jump[:-1, :] |= dz_v
    labels, _ = ndimage.label(near & ~jump)
    su, sv = int(round(u)) - u0, int(round(v)) - v0
    if not (0 <= sv < labels.shape[0] and 0 <= su < labels.shape[1]):
        return out
    label = labels[sv, su]
    if label == 0:  # the seed pixel is at a jump: the nearest labelled pixel
        ys, xs = np.nonzero(labels)
        if not len(ys):
            return out
        k = np.argmin((ys - sv) ** 2 + (xs - su) ** 2)
        label = labels[ys[k], xs[k]]
    out[v0:v1, u0:u1] = labels == label
    return out


def depth_step(z: float) -> float:
    """The largest depth difference (m) between neighbouring pixels of one surface at depth ``z`` m: a surface turned
    up to about 80 degrees from the view, a few times the sensor's noise there."""
    return max(SURFACE_STEP_M, SURFACE_STEP_SHARE * float(z))


def place_at(points: np.ndarray, clicked, orientation, extents) -> Fit:
    """A box at a clicked surface point (camera frame): its front on the point, then fitted to the points around it."""
    clicked = np.asarray(clicked, dtype=np.float64)
    view = clicked / np.linalg.norm(clicked)
    start = clicked + view * half_depth(orientation, extents, view)
    fit = fit_position(points, start, orientation, extents)
    if fit.points < MIN_FIT_POINTS:
        return Fit(start, fit.points)
    return fit


def place_on_surface(depth: np.ndarray, camera: Camera, clicked, orientation, extents, stride: int = 2) -> Fit:
    """A box placed at a clicked surface point (camera frame) of a depth image (H, W) m, fitted to the surface it lies
    on (the module's steps 2-3; all points around it where that surface is too small), on every ``stride``-th pixel."""
    extents = np.asarray(extents, dtype=np.float64)
    region = surface_region(depth, camera, clicked, np.linalg.norm(extents) / 2 + 2 * FIT_MARGIN)
    points = camera.backproject(depth, region, stride=stride)[0]
    if len(points) < MIN_FIT_POINTS:
        points = camera.backproject(depth, None, stride=stride)[0]
    return place_at(points, clicked, orientation, extents)


def screen_projection(points: np.ndarray, view_camera: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Screen coordinates (N, 2) in 0..1 (top left origin) and depths (N,) m of world points in a viewer camera."""
    R, t, fov, aspect = view_camera
    local = (np.asarray(points, dtype=np.float64) - np.asarray(t, dtype=np.float64)) @ np.asarray(R, dtype=np.float64)
    z = local[:, 2]
    scale = 0.5 / np.tan(fov / 2)  # screen heights per unit of y / z
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = 0.5 + scale * local[:, 0] / z / aspect
        sy = 0.5 + scale * local[:, 1] / z
    return np.stack([sx, sy], axis=1), z


def screen_ray(screen, view_camera: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The world ray (origin, unit direction) through a screen point (0..1, top left origin) of a viewer camera."""
    R, t, fov, aspect = view_camera
    tan = np.tan(fov / 2)
    local = np.array([(2 * screen[0] - 1) * tan * aspect, (2 * screen[1] - 1) * tan, 1.0])
    d = np.asarray(R, dtype=np.float64) @ local
    return np.asarray(t, dtype=np.float64).copy(), d / np.linalg.norm(d)


def outline_box(points: np.ndarray, view_camera: tuple, screen_min, screen_max, orientation, extents) -> tuple[np.ndarray, np.ndarray] | None:
    """The box an outline (a screen rectangle of a viewer camera) gives: the sides across the view measured from the
    rectangle at the object's depth, the side along the view scaled from ``extents`` by the same factor, the centre on
    the rectangle's middle ray, its front on the nearest surface inside the outline. Returns (position, extents), or
    None when no point lies inside the outline."""
    R_view = np.asarray(view_camera[0], dtype=np.float64)
    screen, z = screen_projection(points, view_camera)
    lo, hi = np.minimum(screen_min, screen_max), np.maximum(screen_min, screen_max)
    inside = (z > 1e-3) & np.all((screen >= lo) & (screen <= hi), axis=1)
    if inside.sum() < MIN_FIT_POINTS:
        return None
    depths = z[inside]
    R = rotation(orientation)
    extents = np.asarray(extents, dtype=np.float64)
    # which viewer axis (x across, y down, z along the view) each box axis lies closest to
    along = np.argmax(np.abs(R_view.T @ R), axis=0)
    front = float(np.quantile(depths, FRONT_QUANTILE))
    tan = np.tan(view_camera[2] / 2)
    sides = np.array([(hi[0] - lo[0]) * 2 * tan * view_camera[3], (hi[1] - lo[1]) * 2 * tan])  # per metre of depth
    new = extents.copy()
    centre_depth = front
    for _ in range(3):  # the outline is the silhouette at about the centre's depth
        across = sides * centre_depth
        measured = [i for i in range(3) if along[i] < 2]
        for i in measured:
            new[i] = across[along[i]]
        scale = np.mean([new[i] / extents[i] for i in measured]) if measured else 1.0
        for i in range(3):
            if along[i] == 2:
                new[i] = extents[i] * scale
        reach = float(np.abs(R_view[:, 2] @ R) @ (new / 2))
        centre_depth = front + reach
    origin, direction = screen_ray((lo + hi) / 2, view_camera)
    position = origin + direction * (centre_depth / (direction @ R_view[:, 2]))
    return position, new
