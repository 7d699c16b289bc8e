"""The colour check of a spin the geometry leaves free (colour_spin.py), on a small synthetic mug.

A cylinder (the mug's body, axis y) with a knob on its -z side (the handle) turns about its axis
in front of a camera; a checkered colour band fixes the spin. Frames that see the knob pin the
spin down by their geometry; in the others any spin fits the points, and a stretch of them is
posed 12 deg off about the axis, as both chains of a real mug were: only the colours tell.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from annotate.tracking.colour_spin import COLOUR_RADIUS, RADIAL_WEIGHT, SPIN_GRID_DEG, ColourModel, ColourSpinCheck, preferred_spin, spin_matrix
from annotate.tracking.config import TrackingConfig
from evaluate.geometry import rotation_about_y
from sequences.camera import Camera

RADIUS, HEIGHT, KNOB_RADIUS = 0.04, 0.1, 0.014
KNOB_CENTRE = np.array([0.0, 0.0, -0.056])
CAMERA = Camera(fx=600.0, fy=600.0, cx=160.0, cy=120.0, width=320, height=240)


def _surface(step: float = 0.002) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Object-frame points (N, 3), outward normals (N, 3) and colours (N, 3) of the body and the knob, ~``step`` apart."""
    angles = np.arange(0.0, 2 * np.pi, step / RADIUS)
    heights = np.arange(-HEIGHT / 2, HEIGHT / 2, step)
    a, h = np.meshgrid(angles, heights)
    a, h = a.ravel(), h.ravel()
    body_n = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=1)
    body = body_n * RADIUS + np.stack([np.zeros_like(h), h, np.zeros_like(h)], axis=1)
    # a checkered band: 30 deg by 2 cm cells in four chromatically distinct colours, so that the band repeats
    # only after 120 deg, beyond the spins tried (SPIN_GRID_DEG)
    cell = ((np.floor(np.degrees(a) / 30.0) + 2 * np.floor(h / 0.02)) % 4).astype(int)
    colours = np.array([[0.8, 0.2, 0.2], [0.2, 0.3, 0.8], [0.2, 0.7, 0.2], [0.7, 0.7, 0.1]])[cell]
    rng = np.random.default_rng(0)
    knob_n = rng.normal(size=(int(4 * np.pi * KNOB_RADIUS**2 / step**2), 3))
    knob_n /= np.linalg.norm(knob_n, axis=1, keepdims=True)
    knob_n = knob_n[knob_n[:, 2] < 0.3]  # the half sticking out of the body
    knob = KNOB_CENTRE + KNOB_RADIUS * knob_n
    return np.concatenate([body, knob]), np.concatenate([body_n, knob_n]), np.concatenate([colours, np.full((len(knob), 3), 0.5)])


def _true_pose(i: int) -> np.ndarray:
    """Frame i: the knob faces the camera (object -z toward it) at frame 0 and turns away by 9 deg per frame."""
    T = np.eye(4)
    T[:3, :3] = rotation_about_y(np.radians(9.0 * i))
    T[:3, 3] = [0.0, 0.0, 0.5]
    return T


@dataclass
class _Scene:
    """Per frame: the visible camera-frame points and a colour image they were splatted into."""

    points: dict[str, np.ndarray] = field(default_factory=dict)
    pixels: dict[str, np.ndarray] = field(default_factory=dict)
    images: dict[str, np.ndarray] = field(default_factory=dict)

    def color(self, frame_id: str) -> np.ndarray:
        return self.images[frame_id]


def _behind_body(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(N,) bool: object-frame points whose ray from the camera crosses the body (seen from the side: in x-z)."""
    c = (-T[:3, :3].T @ T[:3, 3])[[0, 2]]
    d = points[:, [0, 2]] - c
    s = np.clip(-(d @ c) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    closest = c + s[:, None] * d
    inside = np.linalg.norm(points[:, [0, 2]], axis=1) < RADIUS * 0.999  # the knob's half inside the body
    return inside | ((np.linalg.norm(closest, axis=1) < RADIUS * 0.98) & (s < 0.999))


def _scene(frames: int) -> _Scene:
    points, normals, colours = _surface()
    scene = _Scene()
    for i in range(frames):
        T = _true_pose(i)
        cam = points @ T[:3, :3].T + T[:3, 3]
        n = normals @ T[:3, :3].T
        seen = np.einsum("ij,ij->i", n, -cam) > 0
        seen &= ~_behind_body(points, T)
        cam, rgb = cam[seen], colours[seen]
        u = np.round(CAMERA.fx * cam[:, 0] / cam[:, 2] + CAMERA.cx).astype(int)
        v = np.round(CAMERA.fy * cam[:, 1] / cam[:, 2] + CAMERA.cy).astype(int)
        image = np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8)
        order = np.argsort(-cam[:, 2])  # far first: the nearer surface wins a pixel
        image[v[order], u[order]] = np.round(rgb[order] * 255).astype(np.uint8)
        # every third point, in a scattered order like a voxel grid's (a regular grid's every k-th would alias)
        scene.points[str(i)] = cam[np.random.default_rng(i).permutation(len(cam))[::3]]
        scene.pixels[str(i)] = cam  # every visible point: the pixels, not voxel-averaged
        scene.images[str(i)] = image
    return scene


class _Tracker:
    """What ColourSpinCheck asks of a Tracker: its configuration, crops and a store with the sequence's colour images."""

    def __init__(self, scene: _Scene) -> None:
        self.config = TrackingConfig(min_points=40)
        self.scene = scene
        self.box = np.array([2 * RADIUS, HEIGHT, 2 * RADIUS])
        self.store = SimpleNamespace(stride=1, sequence=SimpleNamespace(camera=CAMERA, color=scene.color), crop=self._pixels)

    def _pixels(self, frame_id: str, pose: np.ndarray, extents: np.ndarray, margin: float, voxel: float | None) -> tuple[np.ndarray, np.ndarray]:
        assert voxel is None, "the colours are read per pixel"
        points = self.scene.pixels[frame_id]
        return points, np.zeros_like(points)

    def crop(self, frame_id: str, pose: np.ndarray, margin: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        points = self.scene.points[frame_id]
        return points, np.zeros_like(points)


@pytest.mark.parametrize("off_deg", [12.0, 4.0, 35.0])
def test_a_stretch_spun_off_where_only_the_colours_see_the_spin_is_found(off_deg):
    frames = 24
    scene = _scene(frames)
    model, _, _ = _surface(0.003)
    check = ColourSpinCheck(_Tracker(scene), model)
    poses = {str(i): _true_pose(i) for i in range(frames)}
    off = [str(i) for i in range(14, 18)]
    for f in off:  # posed off about the axis: the geometry fits as well
        poses[f] = poses[f] @ spin_matrix(check.axis, check.point, off_deg)
    spins = check.run(poses, {f: 0.9 for f in poses})
    assert set(off) <= set(spins), "the frames without the knob in view leave the spin to the colours"
    assert "0" not in spins, "a frame that sees the knob has its spin fixed by the geometry"
    # the colours match best that far back, to the grid's 1 deg (the stretch's ends share their window with a
    # frame at its true pose: their summed curves may settle between)
    assert all(abs(spins[f] + off_deg) <= 1.0 for f in off[1:-1]), spins
    assert all(abs(spins[f] + off_deg) <= off_deg / 2 for f in off), spins
    # frames at their true pose next to the stretch are not blamed for it
    fine = [f for f in spins if int(f) >= 21]  # beyond the window of curves summed with the stretch's
    assert fine
    assert all(abs(spins[f]) <= TrackingConfig().max_colour_spin_deg for f in fine), spins


def test_no_spin_is_preferred_where_the_colours_match_the_pose():
    flat = np.ones(len(SPIN_GRID_DEG))
    assert preferred_spin([flat, flat]) == 0.0
    dip = flat.copy()
    dip[0] = 0.5  # the first angle of the grid matches clearly better
    assert preferred_spin([dip]) == SPIN_GRID_DEG[0]
    # one frame ruling an angle out (inf: its geometry fits clearly worse there) rules it out for the window
    ruled = flat.copy()
    ruled[0] = np.inf
    assert preferred_spin([dip, ruled]) == 0.0
    assert preferred_spin([np.full(len(SPIN_GRID_DEG), np.nan)]) == 0.0


def test_a_frame_whose_colours_prefer_another_spin_is_flagged():
    from annotate.tracking.quality import flag_reasons

    config = TrackingConfig()
    assert not flag_reasons({"colour_spin_deg": config.max_colour_spin_deg}, config)
    reasons = flag_reasons({"colour_spin_deg": -config.max_colour_spin_deg - 2.5}, config)
    assert reasons and "colours" in reasons[0]


def test_the_colour_model_compares_each_pixel_with_the_nearest_model_pixel_within_its_radius():
    # two model pixels on a cylinder of radius 4 cm about y, 0.01 rad apart (0.4 mm): in 3D they are the nearest
    # ones within COLOUR_RADIUS
    a = np.array([0.0, 0.01])
    model_points = RADIUS * np.stack([np.sin(a), np.zeros(2), np.cos(a)], axis=1)
    model = ColourModel([(model_points, np.array([[0.5, 0.25, 0.25], [0.2, 0.2, 0.6]]))], np.array([0.0, 1.0, 0.0]), np.zeros(3))
    assert model.radius == pytest.approx(RADIUS)
    far = 0.2  # rad: 8 mm along the surface, near no model pixel
    pixels = np.array([model_points[0] + [0.0, 0.5 * COLOUR_RADIUS, 0.0], model_points[1], RADIUS * np.array([np.sin(far), 0.0, np.cos(far)])])
    chroma = np.array([[0.4, 0.3, 0.3], [0.2, 0.2, 0.6], [1.0, 0.0, 0.0]])
    for cylinder in (False, True):
        # L1 differences 0.2 and 0 over the two pixels that meet a model pixel
        assert model.cost(pixels, chroma, 2, cylinder) == pytest.approx(0.1)
        assert model.cost(pixels, chroma, 3, cylinder) == np.inf, "too few pixels meet the model: no evidence"


def test_on_the_cylinder_a_pixel_moved_across_the_surface_meets_the_model_pixel_at_its_angle_and_height():
    model = ColourModel([(np.array([[0.0, 0.0, RADIUS]]), np.array([[0.5, 0.25, 0.25]]))], np.array([0.0, 1.0, 0.0]), np.zeros(3))
    # depth noise: 3 mm out from the axis, beyond COLOUR_RADIUS in 3D, 0.9 mm on the cylinder (RADIAL_WEIGHT 0.3)
    across = np.array([[0.0, 0.0, RADIUS + 0.003]])
    assert np.linalg.norm(model.embed(across) - model.embed(model.points)) == pytest.approx(RADIAL_WEIGHT * 0.003)
    assert model.cost(across, np.array([[0.5, 0.25, 0.25]]), 1, cylinder=False) == np.inf
    assert model.cost(across, np.array([[0.4, 0.3, 0.3]]), 1) == pytest.approx(0.2)
    # ... but 3 mm along the surface (an angle of 0.075 rad) or up the axis it meets nothing
    along = np.array([[RADIUS * np.sin(0.075), 0.0, RADIUS * np.cos(0.075)], [0.0, 0.003, RADIUS]])
    for pixel in along:
        assert model.cost(pixel[None], np.array([[0.5, 0.25, 0.25]]), 1) == np.inf


def test_the_spin_is_sought_near_the_3d_lookups_verdict_where_the_label_repeats():
    flat = np.ones(len(SPIN_GRID_DEG))
    aliased = flat.copy()
    aliased[SPIN_GRID_DEG == -40.0] = 0.8  # the spin that undoes the error
    aliased[SPIN_GRID_DEG == 38.0] = 0.7  # the label's pattern repeated, matching a little better
    assert preferred_spin([aliased]) == 38.0
    assert preferred_spin([aliased], near=-37.0) == -40.0
    assert preferred_spin([aliased], near=0.0) == 0.0, "no clearly better angle within FINE_DEG of the pose"
