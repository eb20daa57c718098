"""Harris corners (Harris & Stephens 1988) as in the source work, array-module generic.

Sobel 3x3 gradients, a 3x3 weighting of the structure tensor (Gaussian, or box as in
``cv2.cornerHarris``), response ``det - k trace^2``, local-maximum suppression in a radius, threshold,
then compaction of the response matrix into a list of points ordered by response. The compaction
uses prefix sums (each kept pixel's output slot is the running count of kept pixels before it), the
way the source work's CUDA kernels do it; on NumPy it is equivalent to ``nonzero``.

Memory plan, (H, W) image: float32 input 4 B/px; gradients 8; tensor products 12 (the gradients are
freed as they are used); response 4; suppression mask 1 and prefix sums 4 (int32). Peak about 24 B/px
with float32 everything, 16 B/px when the input is 8-bit and the gradients are dropped early. The
list of points is 12 B per kept point. For larger images, run tile by tile with a margin of
``radius + 2`` px (see ``harris_corners``'s ``tile`` argument): results equal the untiled ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from gpu_kernels.backend import get_array_module, ndimage_module
from gpu_kernels.filters import separable, sobel

WINDOWS = {"gaussian": (0.25, 0.5, 0.25), "box": (1.0, 1.0, 1.0)}


@dataclass(frozen=True)
class Corners:
    """Corners ordered by decreasing response: ``xy`` (N, 2) float32 pixel (x, y), ``response`` (N,)."""

    xy: Any
    response: Any


def harris_response(
    image: Any, k: float = 0.04, window: Literal["gaussian", "box"] = "gaussian", scale: float = 1.0
) -> Any:
    """Harris response of an (H, W) image (any real dtype; computed in float32).

    ``window="box", scale=1 / (4 * 3 * 255)`` reproduces ``cv2.cornerHarris(img8, 3, 3, k)``: OpenCV
    scales the Sobel derivatives by 1 / (2^(ksize-1) * blockSize * 255) for 8-bit input.
    """
    xp = get_array_module(image)
    img = image.astype(xp.float32, copy=False)
    dx, dy = sobel(img)
    dx *= xp.float32(scale)
    dy *= xp.float32(scale)
    w = WINDOWS[window]
    a = separable(dx * dx, w, w)
    c = separable(dy * dy, w, w)
    b = separable(dx * dy, w, w)
    del dx, dy
    return a * c - b * b - xp.float32(k) * (a + c) ** 2


def suppress_non_maxima(response: Any, radius: int, threshold: float) -> Any:
    """(H, W) bool: pixels above ``threshold`` that are the maximum of their (2r+1)^2 neighbourhood."""
    xp = get_array_module(response)
    peak = ndimage_module(xp).maximum_filter(response, size=2 * radius + 1, mode="constant", cval=-np.inf)
    return (response == peak) & (response > threshold)


def compact(mask: Any, response: Any) -> Corners:
    """Kept pixels of ``mask`` as a list ordered by decreasing response, by prefix sums."""
    xp = get_array_module(mask)
    flat = mask.ravel()
    slot = xp.cumsum(flat, dtype=xp.int64) - 1  # output index of each kept pixel
    n = int(slot[-1]) + 1 if flat.size else 0
    # Scatter every pixel's index to its slot; pixels not kept all go to a spare slot n.
    scattered = xp.empty(n + 1, dtype=xp.int64)
    scattered[xp.where(flat, slot, n)] = xp.arange(flat.size, dtype=xp.int64)
    index = scattered[:n]
    values = response.ravel()[index]
    order = xp.argsort(-values, kind="stable")
    index, values = index[order], values[order]
    w = mask.shape[1]
    xy = xp.stack([index % w, index // w], axis=1).astype(xp.float32)
    return Corners(xy, values)


def cap_per_cell(corners: Corners, shape: tuple[int, int], cell_px: int, per_cell: int) -> Corners:
    """Keep the ``per_cell`` strongest corners of each ``cell_px`` square, so points spread over the
    image instead of crowding its most textured part; order by response is kept."""
    xp = get_array_module(corners.xy)
    cols = -(-shape[1] // cell_px)
    cell = (corners.xy[:, 1].astype(xp.int64) // cell_px) * cols + corners.xy[:, 0].astype(xp.int64) // cell_px
    order = xp.argsort(cell, kind="stable")  # within a cell, still by decreasing response
    sorted_cell = cell[order]
    first = xp.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = xp.empty_like(order)
    rank[order] = xp.arange(order.size) - first
    keep = rank < per_cell
    return Corners(corners.xy[keep], corners.response[keep])


def harris_corners(
    image: Any,
    radius: int = 3,
    threshold: float = 1e-4,
    k: float = 0.04,
    window: Literal["gaussian", "box"] = "gaussian",
    scale: float | None = None,
    cell_px: int | None = None,
    per_cell: int = 8,
    tile: int | None = None,
) -> Corners:
    """Corners of an (H, W) image: response, suppression, compaction, optional per-cell cap.

    ``scale`` defaults to 1/255 for 8-bit input (so ``threshold`` means the same for 8-bit and
    [0, 1] float images). With ``tile``, the image is processed in tiles of that many rows and columns
    plus a margin, and the result is the same as without.
    """
    xp = get_array_module(image)
    if scale is None:
        scale = 1.0 / 255.0 if image.dtype == xp.uint8 else 1.0
    if tile is None:
        response = harris_response(image, k, window, scale)
        corners = compact(suppress_non_maxima(response, radius, threshold), response)
    else:
        corners = _tiled(image, tile, radius, threshold, k, window, scale)
    if cell_px is not None:
        corners = cap_per_cell(corners, image.shape[:2], cell_px, per_cell)
    return corners


def _tiled(
    image: Any, tile: int, radius: int, threshold: float, k: float, window: Literal["gaussian", "box"], scale: float
) -> Corners:
    # The response at a pixel depends on pixels up to 2 away (Sobel + window), the suppression on
    # responses up to ``radius`` away: a margin of radius + 2 makes every tile's core exact. Image
    # borders stay image borders (mirror), because the margin is clipped to the image.
    xp = get_array_module(image)
    h, w = image.shape[:2]
    margin = radius + 2
    xy, resp = [], []
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            ya, xa = max(y0 - margin, 0), max(x0 - margin, 0)
            yb, xb = min(y0 + tile + margin, h), min(x0 + tile + margin, w)
            r = harris_response(image[ya:yb, xa:xb], k, window, scale)
            c = compact(suppress_non_maxima(r, radius, threshold), r)
            gx, gy = c.xy[:, 0] + xa, c.xy[:, 1] + ya
            core = (gx >= x0) & (gx < x0 + tile) & (gy >= y0) & (gy < y0 + tile)
            xy.append(xp.stack([gx[core], gy[core]], axis=1))
            resp.append(c.response[core])
    all_xy, all_resp = xp.concatenate(xy), xp.concatenate(resp)
    order = xp.lexsort(xp.stack([all_xy[:, 0], all_xy[:, 1], -all_resp]))
    return Corners(all_xy[order], all_resp[order])
