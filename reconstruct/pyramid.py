"""Min / max image pyramids: the extreme value of an image over any pixel rectangle in four look-ups.

Level 0 is the image; level L (up to a top level) holds the extreme over tiles of 2^L x 2^L pixels
(tiles past the image's edge padded with the reduction's identity). A rectangle no wider and no taller than 2^L
pixels touches at most 2 x 2 tiles of level L, so its extreme is that of those four tiles: a
bound over a slightly larger area, never a value from outside the tiles that cover it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Pyramid:
    """Levels of one reduction (np.minimum or np.maximum), flattened into one array."""

    flat: np.ndarray  # every level, C order, concatenated
    offsets: np.ndarray  # (levels,) int64: where each level starts in ``flat``
    widths: np.ndarray  # (levels,) int64: tiles per row at each level
    reduce: np.ufunc

    @property
    def levels(self) -> int:
        return len(self.offsets)


def build(image: np.ndarray, reduce: np.ufunc, top: int = 6) -> Pyramid:
    """Pyramid of a 2-D image for ``reduce`` (np.minimum or np.maximum), levels 0 .. ``top``.

    The image is padded once with the reduction's identity (the padding never wins) to whole tiles of the top level.
    """
    identity = np.inf if reduce is np.minimum else -np.inf
    image = np.asarray(image)
    tile = 2 ** top
    h, w = image.shape
    level = np.full((-(-h // tile) * tile, -(-w // tile) * tile), identity, dtype=image.dtype)
    level[:h, :w] = image
    levels = [level.reshape(-1)]
    widths = [level.shape[1]]
    for _ in range(top):
        quads = level.reshape(level.shape[0] // 2, 2, level.shape[1] // 2, 2)
        level = reduce(reduce(quads[:, 0, :, 0], quads[:, 0, :, 1]), reduce(quads[:, 1, :, 0], quads[:, 1, :, 1]))
        levels.append(level.reshape(-1))
        widths.append(level.shape[1])
    offsets = np.cumsum([0] + [len(a) for a in levels[:-1]])
    return Pyramid(np.concatenate(levels), np.asarray(offsets, np.int64), np.asarray(widths, np.int64), reduce)


def rectangle_level(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The lowest level whose tiles are at least ``rows`` x ``cols`` pixels (int arrays >= 1)."""
    size = np.maximum(rows, cols).astype(np.float64)
    return np.ceil(np.log2(size)).astype(np.int64)


def query(pyramid: Pyramid, y0: np.ndarray, y1: np.ndarray, x0: np.ndarray, x1: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Extreme over the inclusive pixel rectangles [y0, y1] x [x0, x1], at ``level`` (from :func:`rectangle_level`).

    The result bounds the extreme over each rectangle (equal to it when the rectangle fills its tiles);
    rectangles larger than the top level's tiles (``level`` >= ``pyramid.levels``) get NaN, which
    compares false with anything.
    """
    too_large = level >= pyramid.levels
    level = np.minimum(level, pyramid.levels - 1)
    base, width = pyramid.offsets[level], pyramid.widths[level]
    ty0, ty1, tx0, tx1 = y0 >> level, y1 >> level, x0 >> level, x1 >> level
    f, r = pyramid.flat, pyramid.reduce
    out = r(r(f[base + ty0 * width + tx0], f[base + ty0 * width + tx1]), r(f[base + ty1 * width + tx0], f[base + ty1 * width + tx1]))
    out[too_large] = np.nan
    return out
