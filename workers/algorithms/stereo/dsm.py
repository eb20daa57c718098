"""Gridding triangulated points into a digital surface model (DSM) on a projected grid.

Each point is splatted onto the four cell centres around it with bilinear weights, and a cell's height is the
weighted mean of what reached it: a cell is *measured* when points from checked disparities give it at least
``min_weight`` (a quarter of a point by default), else *filled* when points from filled disparities (an
occlusion or a rejected match, filled from the background side) do. Cells no point reaches, inside the
footprint of the points, are filled (with ``fill``) by linear interpolation between the cells around them
(normalised Gaussian convolution where a hole is open to the footprint's edge), up to ``max_fill_cells``
away, and flagged filled too. Nothing outside the footprint is invented.

Grid convention: rasterio's affine (a, b, c, d, e, f), north up, ``resolution`` m square cells whose corners
sit on multiples of the resolution; cell (row, col) has its centre at
(c + (col + 0.5) resolution, f - (row + 0.5) resolution).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import QhullError

NO_DATA, MEASURED, FILLED = 0, 1, 2  # values of ``Dsm.state``
MAX_CELLS = 200_000_000  # a grid larger than this is refused (a wrong resolution or a runaway point)


@dataclass(frozen=True, eq=False)
class Dsm:
    """``height`` (H, W) float32 m, NaN where there is no data; ``state`` (H, W) uint8, NO_DATA, MEASURED or
    FILLED per cell; ``transform`` rasterio's (a, b, c, d, e, f); ``epsg`` the projected CRS;
    ``resolution`` m."""

    height: np.ndarray
    state: np.ndarray
    transform: tuple[float, float, float, float, float, float]
    epsg: int
    resolution: float

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Easting and northing of every cell centre, (H, W) each."""
        rows, cols = np.mgrid[0 : self.height.shape[0], 0 : self.height.shape[1]]
        a, _, c, _, e, f = self.transform
        return c + (cols + 0.5) * a, f + (rows + 0.5) * e


def grid_dsm(
    east: np.ndarray,
    north: np.ndarray,
    height: np.ndarray,
    measured: np.ndarray,
    resolution: float,
    epsg: int,
    *,
    min_weight: float = 0.25,
    fill: bool = True,
    max_fill_cells: int = 64,
) -> Dsm:
    """Grid points into a DSM.

    Parameters
    ----------
    east, north, height : (N,) float64 points in the projected CRS ``epsg``, metres
    measured : (N,) bool, True for points of checked disparities, False for filled ones
    resolution : cell size, m
    min_weight : splatted weight a cell needs to take a height from its points
    fill : fill the cells no point reaches inside the points' footprint (flagged FILLED)
    max_fill_cells : fill no further than this many cells from a cell with a height
    """
    keep = np.isfinite(east) & np.isfinite(north) & np.isfinite(height)
    east, north, height, measured = east[keep], north[keep], height[keep], measured[keep].astype(bool)
    if len(east) == 0:
        raise ValueError("no points to grid")
    if not resolution > 0:
        raise ValueError("the DSM resolution must be positive")
    x0 = np.floor(east.min() / resolution) * resolution
    y1 = np.ceil(north.max() / resolution) * resolution
    width = int(np.ceil((east.max() - x0) / resolution)) + 1
    rows = int(np.ceil((y1 - north.min()) / resolution)) + 1
    if width * rows > MAX_CELLS:
        raise ValueError(f"the DSM would be {width}x{rows} cells; choose a coarser resolution")
    fx, fy = (east - x0) / resolution - 0.5, (y1 - north) / resolution - 0.5
    values = np.full((rows, width), np.nan, np.float32)
    state = np.zeros((rows, width), np.uint8)
    for flag, chosen in ((FILLED, ~measured), (MEASURED, measured)):  # measured cells overwrite filled ones
        total, weight = _splat(fx[chosen], fy[chosen], height[chosen], (rows, width))
        cells = weight >= min_weight
        values[cells] = (total[cells] / weight[cells]).astype(np.float32)
        state[cells] = flag
    if fill:
        footprint = _footprint(fx, fy, (rows, width))
        values, state = _fill_holes(values, state, footprint, max_fill_cells)
    transform = (float(resolution), 0.0, float(x0), 0.0, -float(resolution), float(y1))
    return Dsm(values, state, transform, int(epsg), float(resolution))


def _splat(fx: np.ndarray, fy: np.ndarray, values: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear splatting: per cell the sum of weight x value and of weights, (H, W) float64 each."""
    rows, cols = shape
    j0, i0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    tx, ty = fx - j0, fy - i0
    total = np.zeros(rows * cols)
    weight = np.zeros(rows * cols)
    for di, dj, w in ((0, 0, (1 - tx) * (1 - ty)), (0, 1, tx * (1 - ty)), (1, 0, (1 - tx) * ty), (1, 1, tx * ty)):
        i, j = i0 + di, j0 + dj
        inside = (i >= 0) & (i < rows) & (j >= 0) & (j < cols)
        index = i[inside] * cols + j[inside]
        total += np.bincount(index, weights=w[inside] * values[inside], minlength=rows * cols)
        weight += np.bincount(index, weights=w[inside], minlength=rows * cols)
    return total.reshape(shape), weight.reshape(shape)


def _footprint(fx: np.ndarray, fy: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool cells inside the convex hull of the points."""
    points = np.column_stack([fx, fy])
    hull = cv2.convexHull(np.round(points).astype(np.int32))
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    return mask > 0


def _fill_holes(
    values: np.ndarray, state: np.ndarray, footprint: np.ndarray, max_cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """Holes within ``max_cells`` of a height: linear interpolation over a Delaunay triangulation of the cells
    around them (exact on a plane), and what that cannot reach (a hole open to the footprint's edge) by
    normalised Gaussian convolution at doubling widths."""
    known = state != NO_DATA
    holes = footprint & ~known
    if not holes.any() or not known.any():
        return values, state
    reach = cv2.distanceTransform((~known).astype(np.uint8), cv2.DIST_L2, 5)
    holes &= reach <= max_cells
    out, new_state = values.copy(), state.copy()
    ring = known & (cv2.dilate(holes.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=2) > 0)
    rows, cols = np.nonzero(holes)
    ring_rows, ring_cols = np.nonzero(ring)
    if len(ring_rows) >= 3 and len(rows):
        try:
            linear = LinearNDInterpolator(np.column_stack([ring_cols, ring_rows]), values[ring_rows, ring_cols])
            inside = linear(np.column_stack([cols, rows]))
        except QhullError:  # the ring's cells on one line: no triangles
            inside = np.full(len(rows), np.nan)
        done = np.isfinite(inside)
        out[rows[done], cols[done]] = inside[done]
        new_state[rows[done], cols[done]] = FILLED
        holes[rows[done], cols[done]] = False
    return _convolve_fill(out, new_state, known, holes, max_cells)


def _convolve_fill(
    out: np.ndarray, state: np.ndarray, known: np.ndarray, holes: np.ndarray, max_cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised Gaussian convolution of the known cells at doubling widths until ``holes`` are filled."""
    data = np.where(known, out, 0.0).astype(np.float32)
    weight = known.astype(np.float32)
    new_state = state
    sigma = 1.0
    left = holes.copy()
    while left.any() and sigma <= 2 * max_cells:
        num = cv2.GaussianBlur(data, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        den = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        ready = left & (den > 1e-3)
        out[ready] = num[ready] / den[ready]
        new_state[ready] = FILLED
        left &= ~ready
        sigma *= 2.0
    return out, new_state
