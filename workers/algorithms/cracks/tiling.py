"""Per-pixel maps of large rasters computed tile by tile, each tile with a margin of context.

A filter bank or a small network over a whole 100-megapixel specimen raster holds tens of bytes per pixel
per channel; computed over tiles of ``tile_px`` with ``margin_px`` of context on every side (cut off
afterwards) it holds that only for one tile, and gives the same map wherever the margin covers the
function's reach (its receptive field, its widest Gaussian's three sigmas).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def map_in_tiles(
    image: np.ndarray,
    function: Callable[[np.ndarray], np.ndarray],
    tile_px: int = 1024,
    margin_px: int = 128,
    align: int = 8,
) -> np.ndarray:
    """``function(image)`` computed over overlapping tiles.

    Parameters
    ----------
    image : (H, W, ...) array.
    function : maps an (h, w, ...) window to an (h, w) float map (a pixel-aligned answer).
    tile_px : edge of the tiles kept, px (rounded up to a multiple of ``align``).
    margin_px : context added on each side of a tile (rounded up to a multiple of ``align``), px.
    align : window origins are multiples of this, so a function that halves the image (pyramids, pooling)
        sees the same pixel grid in every window as in the whole image.

    Returns
    -------
    (H, W) float32 map; the image itself is passed whole when it fits in one tile with its margins.
    """
    if tile_px < 1 or margin_px < 0 or align < 1:
        raise ValueError(f"tile_px >= 1, margin_px >= 0, align >= 1 expected, got {tile_px}, {margin_px}, {align}")
    tile = -(-tile_px // align) * align
    margin = -(-margin_px // align) * align
    height, width = image.shape[:2]
    if height <= tile + 2 * margin and width <= tile + 2 * margin:
        return np.asarray(function(image), dtype=np.float32)
    out = np.empty((height, width), np.float32)
    for top in range(0, height, tile):
        for left in range(0, width, tile):
            y0, x0 = max(top - margin, 0), max(left - margin, 0)
            y1, x1 = min(top + tile + margin, height), min(left + tile + margin, width)
            window = np.asarray(function(image[y0:y1, x0:x1]), dtype=np.float32)
            if window.shape != (y1 - y0, x1 - x0):
                raise ValueError(f"function answered shape {window.shape} for a window of {(y1 - y0, x1 - x0)}")
            bottom, right = min(top + tile, height), min(left + tile, width)
            out[top:bottom, left:right] = window[top - y0 : bottom - y0, left - x0 : right - x0]
    return out
