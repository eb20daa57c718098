"""The volume of a stereo DEM's surface above (and below) a base plane inside a polygon: a stockpile, a pit.

The polygon comes in lon/lat and is carried into the DSM's CRS (a UTM zone, metres); the cells whose centres
fall inside it (``rasterio.features.geometry_mask``) are summed: their height above the base times the cell's
area on that grid. The base is a plane through the surface along the polygon's edge (least squares over the
cells the edge crosses, as a surveyor takes the toe of a stockpile), the lowest of those, or an elevation given.
Cells without a value inside the polygon are left out and counted, so the answer says how much it rests on.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.features import geometry_mask
from rasterio.windows import Window

from api.errors import InvalidInputError, TooLargeError
from api.tiler import lonlat_transformer

MAX_CELLS = 25_000_000  # DSM cells one request may sum (about 100 MB of float32 at once)


def dsm_volume(dsm_path: Path, mask_path: Path | None, polygon: list[tuple[float, float]], base: Any) -> dict[str, Any]:
    """Volume above and below ``base`` ("fit", "lowest" or an elevation in metres) of the DSM inside ``polygon``
    ((lon, lat) vertices, the ring closed or not). 422 for a polygon outside the DSM or without area, 413 for one
    over ``MAX_CELLS`` cells."""
    with rasterio.open(dsm_path) as src:
        lon, lat = np.array(polygon, np.float64).T
        xs, ys = (np.asarray(v, np.float64) for v in lonlat_transformer(src.crs.to_wkt()).transform(lon, lat))
        if not (np.isfinite(xs).all() and np.isfinite(ys).all()):  # far outside the DSM's UTM zone
            raise InvalidInputError(f"polygon: it lies outside the DSM (beyond what its grid, {src.crs}, reaches)")
        window = _window(src, xs, ys)
        z = src.read(1, window=window, masked=True).astype(np.float64)
        transform = src.window_transform(window)
        epsg = src.crs.to_epsg()
    state = _read_state(mask_path, window) if mask_path is not None else None
    ring = [(float(x), float(y)) for x, y in zip(xs, ys, strict=True)]
    inside = geometry_mask([{"type": "Polygon", "coordinates": [[*ring, ring[0]]]}], z.shape, transform, invert=True)
    if not inside.any():
        raise InvalidInputError(
            "polygon: it holds no cell of the DSM (it misses the surface, or is too small or not a closed area)"
        )
    valid = inside & ~np.ma.getmaskarray(z) & np.isfinite(z.filled(np.nan))
    rows, cols = np.nonzero(valid)
    cx, cy = _centres(transform, rows, cols)
    plane, base_info = _base(base, z, transform, xs, ys)
    height = z.data[rows, cols] - (plane[0] * cx + plane[1] * cy + plane[2])
    cell_area = abs(transform.a * transform.e - transform.b * transform.d)
    measured = int(np.count_nonzero(valid & (state == 1))) if state is not None else int(valid.sum())
    return {
        "crs": f"EPSG:{epsg}" if epsg else None,
        "cell_m": round(math.sqrt(cell_area), 4),
        "cells": int(inside.sum()),
        "area_m2": round(float(inside.sum() * cell_area), 3),
        "with_value_share": round(float(valid.sum() / inside.sum()), 4),
        "measured_share": round(measured / float(inside.sum()), 4),
        "base": base_info,
        "volume_above_m3": round(float(np.clip(height, 0, None).sum() * cell_area), 3),
        "volume_below_m3": round(float(np.clip(-height, 0, None).sum() * cell_area), 3),
        "net_m3": round(float(height.sum() * cell_area), 3),
    }


def _window(src: Any, xs: np.ndarray, ys: np.ndarray) -> Window:
    """The DSM's cells under the polygon's bounds, a cell of margin round, within the DSM."""
    inverse = ~src.transform
    cols, rows = inverse @ (
        np.array([xs.min(), xs.max(), xs.min(), xs.max()]),
        np.array([ys.min(), ys.min(), ys.max(), ys.max()]),
    )
    c0, c1 = max(0, math.floor(cols.min()) - 1), min(src.width, math.ceil(cols.max()) + 1)
    r0, r1 = max(0, math.floor(rows.min()) - 1), min(src.height, math.ceil(rows.max()) + 1)
    if c1 <= c0 or r1 <= r0:
        raise InvalidInputError("polygon: it lies outside the DSM")
    if (c1 - c0) * (r1 - r0) > MAX_CELLS:
        raise TooLargeError(
            f"polygon: its bounds span {(c1 - c0) * (r1 - r0)} DSM cells, over {MAX_CELLS}; draw a smaller one"
        )
    return Window(c0, r0, c1 - c0, r1 - r0)


def _read_state(path: Path, window: Window) -> np.ndarray | None:
    if not path.exists():
        return None
    with rasterio.open(path) as src:
        return np.asarray(src.read(1, window=window))


def _centres(transform: Any, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = transform.c + (cols + 0.5) * transform.a + (rows + 0.5) * transform.b
    y = transform.f + (cols + 0.5) * transform.d + (rows + 0.5) * transform.e
    return x, y


def _base(
    base: Any, z: np.ma.MaskedArray, transform: Any, xs: np.ndarray, ys: np.ndarray
) -> tuple[tuple[float, float, float], dict[str, Any]]:
    """The base plane ``(a, b, c)``, z = a x + b y + c on the DSM's grid, and what the answer says of it."""
    if isinstance(base, int | float):
        return (0.0, 0.0, float(base)), {"kind": "elevation", "elevation_m": float(base)}
    ex, ey, ez = _edge_samples(z, transform, xs, ys)
    if ez.size < 3:
        raise InvalidInputError("polygon: the surface has too few values along its edge for a base; give an elevation")
    if base == "lowest":
        return (0.0, 0.0, float(ez.min())), {"kind": "lowest", "elevation_m": round(float(ez.min()), 3)}
    design = np.column_stack([ex - ex.mean(), ey - ey.mean(), np.ones_like(ex)])
    (a, b, c), *_ = np.linalg.lstsq(design, ez, rcond=None)
    c0 = float(c - a * ex.mean() - b * ey.mean())
    misfit = float(np.sqrt(np.mean((design @ np.array([a, b, c]) - ez) ** 2)))
    info = {
        "kind": "fit",
        "elevation_m": round(float(c), 3),  # at the edge's centroid
        "slope_percent": round(100 * math.hypot(a, b), 3),
        "edge_rms_m": round(misfit, 3),
        "edge_samples": int(ez.size),
    }
    return (float(a), float(b), c0), info


def _edge_samples(
    z: np.ma.MaskedArray, transform: Any, xs: np.ndarray, ys: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surface along the polygon's edge: points every half cell on each side, each read from its cell (once
    per cell), where the cell has a value."""
    step = 0.5 * math.sqrt(abs(transform.a * transform.e - transform.b * transform.d))
    px, py = [], []
    for k in range(len(xs)):
        x0, y0, x1, y1 = xs[k], ys[k], xs[(k + 1) % len(xs)], ys[(k + 1) % len(ys)]
        n = max(1, int(math.hypot(x1 - x0, y1 - y0) / step))
        t = np.arange(n) / n
        px.append(x0 + t * (x1 - x0))
        py.append(y0 + t * (y1 - y0))
    x, y = np.concatenate(px), np.concatenate(py)
    inverse = ~transform
    col, row = inverse @ (x, y)
    row, col = np.floor(row).astype(np.int64), np.floor(col).astype(np.int64)
    keep = (row >= 0) & (row < z.shape[0]) & (col >= 0) & (col < z.shape[1])
    cells = np.unique(np.column_stack([row[keep], col[keep]]), axis=0)
    if cells.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    has = ~np.ma.getmaskarray(z)[cells[:, 0], cells[:, 1]] & np.isfinite(z.data[cells[:, 0], cells[:, 1]])
    cells = cells[has]
    cx, cy = _centres(transform, cells[:, 0], cells[:, 1])
    return cx, cy, z.data[cells[:, 0], cells[:, 1]]
