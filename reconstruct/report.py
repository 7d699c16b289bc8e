"""Per-sequence report (plain JSON figures) and a preview: the mesh outline over a few frames."""

from __future__ import annotations

import io
import json
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image
from scipy import ndimage

from .masks import MeshRenderer

if TYPE_CHECKING:
    from sequences.reader import Sequence

    from .pipeline import Reconstruction

OUTLINE_RGB = (255, 40, 40)


def report_json(report: dict) -> str:
    """The report as indented JSON text (numpy values made plain)."""

    def plain(value):
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, np.generic):
            return value.item()
        raise TypeError(f"not JSON-serialisable: {type(value)}")

    return json.dumps(report, indent=1, default=plain)


def outline(mask: np.ndarray, width: int = 2) -> np.ndarray:
    """(H, W) bool: the pixels of ``mask`` within ``width`` pixels of its border."""
    return mask & ~ndimage.binary_erosion(mask, iterations=width)


def preview_frames(ids: list[str], count: int = 4) -> list[str]:
    """Up to ``count`` frame ids spread evenly over ``ids``."""
    if len(ids) <= count:
        return list(ids)
    return [ids[i] for i in np.linspace(0, len(ids) - 1, count).round().astype(int)]


def preview_image(reconstruction: "Reconstruction", sequence: "Sequence", masks: dict[str, np.ndarray] | None = None, count: int = 4) -> np.ndarray:
    """(H', W', 3) uint8: up to ``count`` frames at half size, 2 per row, with the mesh silhouette outlined in red.

    Uses ``masks`` (visible masks) where given, else renders the silhouette.
    """
    ids = preview_frames(sorted(reconstruction.poses, key=sequence.index), count)
    renderer = None
    tiles = []
    for frame_id in ids:
        image = sequence.color(frame_id).copy()
        mask = None if masks is None else masks.get(frame_id)
        if mask is None:
            renderer = renderer or MeshRenderer(reconstruction.mesh, sequence.camera)
            mask = renderer.depth(reconstruction.poses[frame_id]) > 0
        image[outline(mask)] = OUTLINE_RGB
        tiles.append(np.asarray(Image.fromarray(image).reduce(2)))
    while len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i : i + 2], axis=1) for i in range(0, len(tiles), 2)]
    return np.concatenate(rows, axis=0)


def preview_png_bytes(reconstruction: "Reconstruction", sequence: "Sequence", masks: dict[str, np.ndarray] | None = None) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(preview_image(reconstruction, sequence, masks)).save(buffer, format="PNG")
    return buffer.getvalue()
