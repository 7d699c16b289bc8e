"""Reading one frame's colour, depth and instance-mask images, with one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from sequences.camera import Camera
from sequences.errors import InputError


def _open(path: Path) -> Image.Image:
    try:
        image = Image.open(path)
        image.load()
    except FileNotFoundError as error:
        raise InputError(path, "file not found") from error
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise InputError(path, f"unreadable or corrupt image ({error.__class__.__name__})") from error
    return image


def _check_shape(path: Path, shape: tuple[int, ...], camera: Camera) -> None:
    if tuple(shape[:2]) != camera.shape:
        raise InputError(path, f"image is {shape[1]}x{shape[0]} but the camera is {camera.width}x{camera.height}")


def read_color(path: str | Path, camera: Camera) -> np.ndarray:
    """(H, W, 3) uint8 RGB."""
    path = Path(path)
    array = np.asarray(_open(path).convert("RGB"))
    _check_shape(path, array.shape, camera)
    return array


def read_depth(path: str | Path, camera: Camera) -> np.ndarray:
    """(H, W) float32 depth in metres (0 = no measurement) from a 16-bit PNG in sensor units."""
    path = Path(path)
    image = _open(path)
    if image.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise InputError(path, f"depth image is not 16-bit (mode {image.mode})")
    array = np.asarray(image)
    _check_shape(path, array.shape, camera)
    return array.astype(np.float32) * np.float32(camera.depth_scale)


def read_instance_ids(path: str | Path, camera: Camera) -> np.ndarray:
    """(H, W) uint8 instance ids (NOCS: 255 = background)."""
    path = Path(path)
    image = _open(path)
    array = np.asarray(image)
    if array.ndim == 3:  # NOCS CAMERA masks are RGBA: the id is in the first channel
        array = array[..., 0]
    _check_shape(path, array.shape, camera)
    return array
