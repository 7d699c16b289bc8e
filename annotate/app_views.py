"""2D views of the session: the colour image with the projected box, the frame timeline, the sensor's view.

The scene's world frame is the current frame's OpenCV camera frame (metres; the scene's up is -y),
so the sensor sits at the origin looking along +z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from evaluate.geometry import BOX_EDGES, box_corners, pose_matrix
from sequences.camera import Camera

#: Edge colours by the object axis they run along (x red, y green, z blue), RGB.
AXIS_COLORS = np.array([[235, 70, 60], [70, 220, 90], [70, 140, 255]], dtype=np.uint8)
#: Timeline colours by frame status, RGB.
STATUS_COLORS = {
    "manual": (40, 170, 70),
    "refined": (50, 110, 230),
    "tracked": (130, 195, 245),
    "flagged": (225, 45, 45),
    "none": (70, 70, 70),
}


@dataclass(frozen=True)
class TintedFace:
    """A box face drawn filled and labelled, in the 3D view and on the colour image alike: object ``axis`` (0 x, 1 y,
    2 z), the side ``sign`` (+1, -1), RGB ``color``, the word written on it."""

    name: str
    axis: int
    sign: int
    color: tuple[int, int, int]
    label: str


#: The faces that show which way the box is: the top (+y, green) and the front / handle side (-z, blue, as in
#: REDWOOD75 and NOCS).
TINTED_FACES = (TintedFace("up", 1, 1, (70, 220, 90), "top"), TintedFace("front", 2, -1, (70, 140, 255), "front"))
#: Opacity of the tinted faces (0-1): the points and the image show through.
TINT_OPACITY = 0.35


def edge_axes() -> np.ndarray:
    """Object axis (0, 1, 2) along which each of the 12 :data:`BOX_EDGES` runs."""
    a, b = BOX_EDGES[:, 0], BOX_EDGES[:, 1]
    bits = a ^ b  # corner index bits: 4 = x, 2 = y, 1 = z
    return np.where(bits == 4, 0, np.where(bits == 2, 1, 2))


def face_corners(axis: int, sign: int) -> np.ndarray:
    """Indices into :func:`box_corners` of the 4 corners of a face, in order around it."""
    bit = {0: 4, 1: 2, 2: 1}[axis]
    others = [b for b in (4, 2, 1) if b != bit]
    base = bit if sign > 0 else 0
    return np.array([base, base + others[0], base + others[0] + others[1], base + others[1]])


def project_box(camera: Camera, position, orientation, extents) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (8, 2) and depths (8,) of the box corners in the image."""
    corners = box_corners(extents, pose_matrix(position, orientation))
    return camera.project(corners)


def face_centre(extents, axis: int, sign: int) -> np.ndarray:
    """The centre (3,) of a box face, object frame (m)."""
    centre = np.zeros(3)
    centre[axis] = sign * float(np.asarray(extents, dtype=np.float64)[axis]) / 2
    return centre


def draw_box(image: np.ndarray, camera: Camera, position, orientation, extents, width: int = 2, scale: float = 1.0, labels: bool = True) -> np.ndarray:
    """A copy of ``image`` with the box's edges drawn (coloured by axis), the top and front faces tinted and (with
    ``labels``) their words written at their centres.

    ``image`` (h, w, 3) uint8 is the camera's image resized by ``scale`` (e.g. 0.5 for a half-size
    preview). Edges with a corner behind the camera are left out rather than drawn wrapped around.
    """
    uv, z = project_box(camera, position, orientation, extents)
    # pixel centres stay at integer coordinates when resizing by ``scale``
    uv = (uv + 0.5) * scale - 0.5
    base = Image.fromarray(np.asarray(image, dtype=np.uint8)).convert("RGBA")
    overlay = Image.new("RGBA", base.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(overlay)
    in_front = z > 1e-3
    alpha = round(255 * TINT_OPACITY)
    for face in TINTED_FACES:
        idx = face_corners(face.axis, face.sign)
        if np.all(in_front[idx]):
            draw.polygon([tuple(map(float, uv[i])) for i in idx], fill=(*face.color, alpha))
    for (a, b), axis in zip(BOX_EDGES, edge_axes()):
        if in_front[a] and in_front[b]:
            draw.line([tuple(map(float, uv[a])), tuple(map(float, uv[b]))], fill=tuple(int(c) for c in AXIS_COLORS[axis]) + (255,), width=width)
    # the words at the faces' centres, where the face is in front of the camera
    T = pose_matrix(position, orientation)
    for face in TINTED_FACES if labels else ():
        centre = T[:3, :3] @ face_centre(extents, face.axis, face.sign) + T[:3, 3]
        if centre[2] > 1e-3:
            uv_centre, _ = camera.project(centre[None])
            u, v = (uv_centre[0] + 0.5) * scale - 0.5
            draw.text((float(u), float(v)), face.label, fill=(255, 255, 255, 255), anchor="mm", stroke_width=1, stroke_fill=(0, 0, 0, 255))
    return np.asarray(Image.alpha_composite(base, overlay).convert("RGB"))


#: When several frames share a pixel column, the one that most needs attention is shown.
STATUS_PRIORITY = ("manual", "refined", "tracked", "none", "flagged")


def timeline_image(statuses: list[str], current: int, width: int = 600, height: int = 28) -> np.ndarray:
    """A strip (height, width, 3) uint8: one coloured cell per frame by status, the current frame marked.

    With more frames than pixel columns, a column shows the most urgent status of its frames
    (a flagged frame is never hidden).
    """
    n = max(len(statuses), 1)
    rank = np.array([STATUS_PRIORITY.index(s) for s in statuses] or [STATUS_PRIORITY.index("none")])
    palette = np.array([STATUS_COLORS[s] for s in STATUS_PRIORITY], dtype=np.uint8)
    first = np.minimum((np.arange(width) * n) // width, n - 1)  # first frame of each pixel column
    # most urgent rank over each column's frames [first[c], first[c + 1]); a repeated index (fewer
    # frames than columns) gives that frame's own rank
    column_rank = np.maximum.reduceat(rank, first)
    strip = np.repeat(palette[column_rank][None, :, :], height, axis=0)
    lo = (current * width) // n
    hi = max(((current + 1) * width) // n, lo + 2)
    strip[: height // 4, lo:hi] = 255  # white marks above and below the current frame
    strip[-(height // 4) :, lo:hi] = 255
    return strip


def timeline_legend() -> str:
    """Markdown legend of the timeline colours."""
    spans = [f"<span style='color:rgb{STATUS_COLORS[s]}'>&#9632;</span> {s}" for s in STATUS_COLORS]
    return " &nbsp; ".join(spans)


def sensor_fov(camera: Camera) -> float:
    """Vertical field of view of the sensor, radians."""
    return 2.0 * math.atan2(camera.height / 2.0, camera.fy)


def sensor_view(camera: Camera, median_depth: float) -> dict:
    """Viewer camera at the sensor, looking down the optical axis at the data, with the sensor's field of view.

    In the world frame (the current frame's camera frame): position, look_at, up (-y), fov (rad).
    """
    return {
        "position": np.zeros(3),
        "look_at": np.array([0.0, 0.0, max(float(median_depth), 0.1)]),
        "up": np.array([0.0, -1.0, 0.0]),
        "fov": sensor_fov(camera),
    }
