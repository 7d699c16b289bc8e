"""Reading colour, depth and label images with one-line errors naming the file.

Colour: 8-bit RGB (jpg or png). Depth: 16-bit PNG in sensor units (multiply by the camera's
``depth_scale`` for metres; 0 = no measurement). Every image must match the camera's size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .camera import Camera
from .errors import InputError

DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I")


def open_image(path: str | Path) -> Image.Image:
    """Open and decode an image, or raise InputError naming the file."""
    path = Path(path)
    try:
        image = Image.open(path)
        image.load()
    except FileNotFoundError as error:
        raise InputError(path, "file not found") from error
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise InputError(path, f"unreadable or corrupt image ({' '.join(str(error).split()) or error.__class__.__name__})") from error
    return image


def check_size(path: str | Path, shape: tuple[int, ...], camera: Camera) -> None:
    """Raise InputError unless an image of ``shape`` (H, W, ...) matches the camera."""
    if tuple(shape[:2]) != camera.shape:
        raise InputError(path, f"image is {shape[1]}x{shape[0]} but the camera is {camera.width}x{camera.height} (colour and depth must match the camera; see camera.yaml)")


def read_color(path: str | Path, camera: Camera) -> np.ndarray:
    """(H, W, 3) uint8 RGB."""
    image = open_image(path)
    if image.mode not in ("RGB", "RGBA", "L", "P"):
        raise InputError(path, f"colour image mode {image.mode} is not 8-bit RGB")
    array = np.asarray(image.convert("RGB"))
    check_size(path, array.shape, camera)
    return array


def read_depth_raw(path: str | Path, camera: Camera) -> np.ndarray:
    """(H, W) uint16 depth in sensor units."""
    image = open_image(path)
    if image.mode not in DEPTH_MODES:
        raise InputError(path, f"depth image is not 16-bit (mode {image.mode}); expected 16-bit PNG in sensor units")
    array = np.asarray(image)
    if array.dtype != np.uint16:
        if array.min(initial=0) < 0 or array.max(initial=0) > 65535:
            raise InputError(path, "depth image is not 16-bit (values outside 0..65535)")
        array = array.astype(np.uint16)
    check_size(path, array.shape, camera)
    return array


def read_depth(path: str | Path, camera: Camera) -> np.ndarray:
    """(H, W) float32 depth in metres (0 = no measurement)."""
    return read_depth_raw(path, camera).astype(np.float32) * np.float32(camera.depth_scale)


def read_labels(path: str | Path, camera: Camera) -> np.ndarray:
    """(H, W) uint8 label image (instance ids or a 0/255 mask); RGBA/RGB labels keep their first channel."""
    array = np.asarray(open_image(path))
    if array.ndim == 3:  # NOCS CAMERA masks are RGBA: the id is in the first channel
        array = array[..., 0]
    check_size(path, array.shape, camera)
    return array
