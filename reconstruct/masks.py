"""Per-frame instance masks of the visible object: the posed mesh ray-cast headless (Open3D RaycastingScene).

A pixel is in the mask where the mesh is hit and the measured depth does not lie in front of the
mesh by more than ``tolerance`` (a hand or another object occluding it); missing depth keeps the
pixel (nothing says it is occluded). The default tolerance, 1 cm, is cpas_toolbox's own for
REDWOOD75. Masks are written by :mod:`reconstruct.export` as ``OUT/masks/<sequence>/<frame id>.png``
(uint8, 0 = background, 255 = object).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import trimesh

from evaluate.rendering import MeshRenderer, visible_mask
from sequences.camera import Camera

DEFAULT_TOLERANCE = 0.01

__all__ = ["DEFAULT_TOLERANCE", "MeshRenderer", "mask_png_bytes", "render_masks", "visible_mask"]


def render_masks(
    mesh: trimesh.Trimesh,
    poses: Mapping[str, np.ndarray],
    camera: Camera,
    depth: Mapping[str, np.ndarray] | Callable[[str], np.ndarray] | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
) -> dict[str, np.ndarray]:
    """Masks (H, W) bool per frame id for ``mesh`` (object frame) at ``poses`` (object to camera).

    ``depth`` gives the measured depth (metres, 0 = none) per frame id, as a mapping or a function
    (e.g. ``sequence.depth``); without it the masks are the full silhouettes.
    """
    renderer = MeshRenderer(mesh, camera)
    out = {}
    for frame_id, pose in poses.items():  # loop over frames; pixels are vectorised
        measured = None
        if depth is not None:
            measured = depth(frame_id) if callable(depth) else depth[frame_id]
        out[frame_id] = visible_mask(renderer.depth(pose), measured, tolerance)
    return out


def mask_png_bytes(mask: np.ndarray) -> bytes:
    """PNG bytes of a mask: uint8, 0 = background, 255 = object."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(buffer, format="PNG", compress_level=1)  # a mask is runs: level 1 is near the best
    return buffer.getvalue()
