"""Tiny Redwood-layout sequences written on the fly for reader tests (no rendering)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def write_frame(root: Path, color_name: str, depth_name: str, size=(640, 480), depth_mm: int = 800, seed: int = 0) -> None:
    """Write one colour (jpg/png by the name's suffix) and one 16-bit depth frame."""
    rng = np.random.default_rng(seed)
    w, h = size
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(root / "rgb" / color_name)
    depth = np.full((h, w), depth_mm, dtype=np.uint16)
    depth[: h // 4] = 0  # some missing measurements
    Image.fromarray(depth).save(root / "depth" / depth_name)


def redwood_sequence(root: Path, n: int = 5, size=(640, 480), period_us: int = 33_333, depth_offset_us: int = 2_500) -> Path:
    """A sequence with Redwood names where depth numbering is offset by one from colour."""
    for i in range(n):
        t = 7_000_000 + i * period_us
        write_frame(root, f"{210 + i:07d}-{t:012d}.jpg", f"{211 + i:07d}-{t + depth_offset_us:012d}.png", size, 600 + 10 * i, seed=i)
    return root
