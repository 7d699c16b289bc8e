"""A PrimeSense-like sensor: noisy, holey, millimetre depth and shaded, textured, noisy colour.

Depth (metres in, uint16 millimetres out, 0 = no measurement):
- axial noise, Gaussian with sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m, independent per pixel;
- dropout at grazing angles: certain beyond ~87 degrees between ray and surface, none below ~72;
- random speckle holes (0.4% of pixels) and blob holes (a thresholded smooth random field);
- the projector's shadow: no depth where the way from the surface to the projector (7.5 cm to the
  camera's right, as on a PrimeSense) is blocked, the band left of every foreground edge;
- dropout next to depth jumps (> 3 cm) with probability 0.4;
- no measurement nearer than 0.35 m or farther than 4.5 m; rounding to millimetres.
With :class:`.options.SensorOptions` (``depth_measurement(..., options)``), also:
- flying pixels: a pixel next to a depth jump reads, with the given chance, a depth between the near
  and the far surface of its 3x3 neighbourhood (the correlation window straddles the edge);
- disparity quantisation: the sensor measures disparity f b / z in 1/8 pixel steps (f 580 px, b 7.5 cm),
  so depth comes in steps of z^2 / (8 f b): 1 mm at 0.6 m, 2.9 mm at 1 m.
Colour: procedural albedo per scene part (the object's texture: a seeded pattern, a label on a
plain body, or one plain colour; skin on the hand),
Lambert shading with ambient light, a slight lens blur (Gaussian, 0.6 px: one ray per pixel
would leave jagged edges no camera shows), Gaussian noise (sigma 2.5 levels).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..sensor_noise import depth_sigma
from .options import SensorOptions
from .render import Render
from .scene import HAND, OBJECT, PERSON, TABLE, WALL, Layout

MIN_RANGE, MAX_RANGE = 0.35, 4.5
#: The IR projector's position in the camera frame, metres (PrimeSense baseline 7.5 cm).
PROJECTOR = np.array([0.075, 0.0, 0.0])
SPECKLE_RATE = 0.004
EDGE_JUMP, EDGE_DROPOUT = 0.03, 0.4
COLOR_NOISE = 2.5
LENS_BLUR = 0.6  # pixels
AMBIENT = 0.35
#: The IR camera's focal length (pixels) times the projector baseline (metres), and the disparity step (pixels).
FOCAL_BASELINE = 580.0 * 0.075
DISPARITY_STEP = 1.0 / 8.0


def grazing_dropout_probability(cos_incidence: np.ndarray) -> np.ndarray:
    """Chance that a pixel has no depth, from |cos| of the ray-to-normal angle: 1 below 0.05, 0 above 0.3."""
    return np.clip((0.3 - cos_incidence) / 0.25, 0.0, 1.0)


def depth_jumps(z: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels with a 4-neighbour more than EDGE_JUMP metres nearer or farther (or one side unhit)."""
    jump = np.zeros(z.shape, dtype=bool)
    dx = np.abs(np.diff(z, axis=1)) > EDGE_JUMP
    dy = np.abs(np.diff(z, axis=0)) > EDGE_JUMP
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    jump[1:] |= dy
    jump[:-1] |= dy
    return jump


def quantised_depth(z: np.ndarray) -> np.ndarray:
    """Depth (metres, 0 = none) as a structured-light sensor reports it: disparity rounded to DISPARITY_STEP pixels."""
    with np.errstate(divide="ignore"):
        steps = np.rint(FOCAL_BASELINE / z / DISPARITY_STEP)
        return np.where((z > 0) & (steps > 0), FOCAL_BASELINE / (np.maximum(steps, 1) * DISPARITY_STEP), 0.0).astype(z.dtype)


def flying_depth(z: np.ndarray, jump: np.ndarray, chance: float, draw: np.ndarray, mix: np.ndarray) -> np.ndarray:
    """Depth (H, W) where, of the pixels next to a jump (``jump``) with a hit all around, those whose ``draw`` (uniform
    0..1) is below ``chance`` read ``mix`` (uniform 0..1) of the way from the nearest to the farthest depth in their
    3x3 neighbourhood: the flying pixels between a foreground edge and what lies behind it."""
    hit = z > 0
    near = ndimage.minimum_filter(np.where(hit, z, np.inf), size=3, mode="nearest")
    near = np.where(np.isfinite(near), near, z)
    far = ndimage.maximum_filter(z, size=3, mode="nearest")
    flying = jump & (draw < chance) & (ndimage.minimum_filter(hit, size=3, mode="nearest"))
    return np.where(flying, near + mix * (far - near), z).astype(z.dtype)


def depth_measurement(render: Render, rng: np.random.Generator, options: SensorOptions | None = None) -> np.ndarray:
    """The sensor's depth image (H, W) uint16 millimetres from a render (see the module notes).

    ``rng`` gives the noise, the dropout and the holes first, in that order, whatever the ``options``; the flying
    pixels' draws come after them. So a frame's noise is the same with any options, and without options (flying
    pixels and quantisation off) the image is the same as before either existed.
    """
    z = render.depth
    h, w = z.shape
    noise = rng.standard_normal(z.shape, dtype=np.float32)
    chance = rng.random(z.shape, dtype=np.float32)
    field = ndimage.zoom(rng.standard_normal(((h + 15) // 16, (w + 15) // 16), dtype=np.float32), 16, order=1)[:h, :w]
    jump = depth_jumps(z)
    if options is not None:
        z = flying_depth(z, jump, options.flying_pixels, rng.random(z.shape, dtype=np.float32), rng.random(z.shape, dtype=np.float32))
    noisy = z + noise * depth_sigma(z).astype(np.float32)
    if options is not None and options.quantisation:
        noisy = quantised_depth(noisy)
    # independent dropout causes combined into one chance of keeping the pixel, drawn once
    keep_chance = (1.0 - grazing_dropout_probability(render.cos_incidence)) * (1.0 - SPECKLE_RATE) * (1.0 - EDGE_DROPOUT * jump)
    keep = chance < keep_chance
    keep &= (z >= MIN_RANGE) & (z <= MAX_RANGE)  # also drops pixels where nothing was hit (z = 0)
    keep &= ~render.shadow
    keep &= field < 2.3  # about 1% of the image in smooth-edged blobs
    millimetres = np.clip(np.rint(noisy * np.float32(1000.0)), 0, 65535)
    return np.where(keep, millimetres, 0).astype(np.uint16)


@dataclass
class ObjectStyle:
    """Seeded appearance of the object: colours (RGB 0..1) and pattern sizes (metres, radians)."""

    base: np.ndarray
    band: np.ndarray
    accent: np.ndarray
    band_centre: float
    band_half: float
    stripe_period: float
    checker_angle: float
    checker_height: float
    texture: str = "pattern"  # pattern | label | plain (options.TEXTURES)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    import colorsys

    return np.array(colorsys.hsv_to_rgb(h, s, v))


def object_style(rng: np.random.Generator, height: float, texture: str = "pattern") -> ObjectStyle:
    """A random look of the given ``texture`` for an object of the given height (its y extent)."""
    hue = rng.uniform(0, 1)
    return ObjectStyle(
        texture=texture,
        base=_hsv(hue, rng.uniform(0.3, 0.8), rng.uniform(0.45, 0.9)),
        band=_hsv((hue + rng.uniform(0.25, 0.75)) % 1, rng.uniform(0.2, 0.9), rng.uniform(0.5, 0.95)),
        accent=_hsv(rng.uniform(0, 1), rng.uniform(0.5, 1.0), rng.uniform(0.15, 0.6)),
        band_centre=rng.uniform(-0.15, 0.15) * height,
        band_half=rng.uniform(0.12, 0.25) * height,
        stripe_period=rng.uniform(0.012, 0.03),
        checker_angle=np.pi / rng.integers(3, 8),
        checker_height=rng.uniform(0.008, 0.02),
    )


def object_albedo(points: np.ndarray, style: ObjectStyle) -> np.ndarray:
    """Albedo (N, 3) at object-frame points (N, 3). ``pattern``: base with stripes, a checkered band, a spot opposite
    +z; ``label``: a plain base with a label band round it, printed with rows of dark blocks (text) on one side;
    ``plain``: the base colour alone (most real mugs and bowls)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    angle = np.arctan2(x, z)
    colour = np.repeat(style.base[None], len(points), axis=0)
    if style.texture == "plain":
        return colour
    if style.texture == "label":
        in_band = np.abs(y - style.band_centre) < style.band_half
        colour[in_band] = style.band
        # "text": blocks on a third of the way round, rows a checker height apart
        rows = np.floor((y - style.band_centre) / style.checker_height)
        block = np.floor(angle / (0.4 * style.checker_angle))
        printed = in_band & (np.abs(angle - 0.5) < 1.0) & (np.abs(y - style.band_centre) < 0.8 * style.band_half)
        printed &= ((rows % 2) == 0) & (np.sin(block * 12.9898 + rows * 78.233) > -0.2)
        colour[printed] = style.accent
        return colour
    stripes = np.sin(2 * np.pi * y / style.stripe_period) > 0.6
    colour[stripes] *= 0.7
    in_band = np.abs(y - style.band_centre) < style.band_half
    checker = ((np.floor(angle / style.checker_angle) + np.floor(y / style.checker_height)) % 2) == 0
    colour[in_band] = style.band
    colour[in_band & checker] = style.accent
    spot = (np.abs(np.abs(angle) - np.pi) < 0.35) & (np.abs(y - style.band_centre) < style.band_half * 0.6)
    colour[spot] = 1.0 - style.band
    return colour


def scene_albedo(render: Render, object_pose: np.ndarray, style: ObjectStyle, layout: Layout) -> np.ndarray:
    """Albedo (H, W, 3) float32 of every pixel from its scene label and hit point."""
    label = render.label.reshape(-1)
    points = render.points.reshape(-1, 3)
    albedo = np.zeros((len(label), 3), dtype=np.float32)
    sel = label == OBJECT
    R, t = object_pose[:3, :3], object_pose[:3, 3]
    albedo[sel] = object_albedo((points[sel] - t) @ R, style)
    sel = label == HAND
    p = points[sel]
    albedo[sel] = layout.skin * (1.0 + 0.05 * np.sin(p[:, :1] * 400) * np.sin(p[:, 1:2] * 370))
    sel = label == PERSON
    p = points[sel]
    head = np.linalg.norm(p - layout.head_centre, axis=1) < layout.head_radius * 1.25
    hair = head & (p[:, 1] < layout.head_centre[1] - 0.2 * layout.head_radius)
    person = np.where(head[:, None], layout.skin, layout.shirt)
    person[hair] = layout.hair
    albedo[sel] = person * (1.0 + 0.06 * np.sin(p[:, :1] * 150 + p[:, 1:2] * 90))
    sel = label == WALL
    p = points[sel]
    wall = layout.wall_colour * (1.0 + 0.04 * np.sin(p[:, :1] * 7 + 1.3) * np.sin(p[:, 1:2] * 5))
    for poster in layout.posters:  # three rectangles, each a vectorised test over the wall pixels
        inside = (np.abs(p[:, 0] - poster[0]) < poster[2]) & (np.abs(p[:, 1] - poster[1]) < poster[3])
        wall[inside] = poster[4:7] * (0.8 + 0.2 * (np.sin(p[inside, 0] * 60) > 0))[:, None]
    albedo[sel] = wall
    sel = label == TABLE
    p = points[sel]
    grain = 0.85 + 0.15 * np.sin(p[:, 0] * 90 + 4 * np.sin(p[:, 2] * 9))
    albedo[sel] = layout.table_colour * grain[:, None]
    return albedo.reshape(*render.label.shape, 3)


def shade(render: Render, albedo: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Noise-free colour (H, W, 3) float32 in 0..255: albedo x (ambient + Lambert); dark where nothing was hit."""
    lambert = np.clip(render.normals @ light.astype(np.float32), 0.0, None)
    colour = albedo * ((AMBIENT + (1.0 - AMBIENT) * lambert)[..., None] * np.float32(255.0))
    colour[render.label == 0] = 20.0
    return colour.astype(np.float32, copy=False)


def add_color_noise(colour: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The camera's colour image (H, W, 3) uint8: noise-free colour, blurred by the lens, plus Gaussian noise."""
    blurred = ndimage.gaussian_filter(colour, sigma=(LENS_BLUR, LENS_BLUR, 0.0), truncate=2.5)
    noisy = blurred + rng.standard_normal(colour.shape, dtype=np.float32) * np.float32(COLOR_NOISE)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def color_image(render: Render, albedo: np.ndarray, light: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Shaded colour with noise (H, W, 3) uint8 (see :func:`shade` and :func:`add_color_noise`)."""
    return add_color_noise(shade(render, albedo, light), rng)
