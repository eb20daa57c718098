"""Pictures of a surface for the viewer: a colour ramp of a value, shaded by the slope of the terrain.

``shaded_relief`` is a hypsometric tint (colour by elevation) multiplied by a hillshade (Horn 1981, the slope
and aspect of GDAL's ``gdaldem hillshade``: a light from the north-west, 45 degrees up); ``colour_ramp`` alone
colours a disparity map. The ramps are lists of (fraction, (r, g, b)) stops; ``legend`` gives the stops in
the value's units for the viewer's legend.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

Ramp = tuple[tuple[float, tuple[int, int, int]], ...]

# Hypsometric tints: lowland green, yellow, tan and brown slopes, white tops.
TERRAIN: Ramp = (
    (0.0, (44, 123, 82)),
    (0.2, (122, 175, 96)),
    (0.4, (226, 220, 150)),
    (0.6, (200, 156, 100)),
    (0.8, (146, 101, 72)),
    (1.0, (245, 245, 245)),
)
# Perceptually ordered, dark (far) to bright (near), after matplotlib's viridis.
DISPARITY: Ramp = (
    (0.0, (68, 1, 84)),
    (0.25, (59, 82, 139)),
    (0.5, (33, 145, 140)),
    (0.75, (94, 201, 98)),
    (1.0, (253, 231, 37)),
)


def value_range(
    values: np.ndarray, valid: np.ndarray, percentiles: tuple[float, float] = (2.0, 98.0)
) -> tuple[float, float]:
    """The range a ramp spans: the ``percentiles`` of the valid values (a flat surface gets +-1)."""
    data = values[valid & np.isfinite(values)]
    if data.size == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(data, percentiles))
    if hi - lo < 1e-6:
        lo, hi = lo - 1.0, hi + 1.0
    return lo, hi


def colour_ramp(values: np.ndarray, lo: float, hi: float, ramp: Ramp) -> np.ndarray:
    """(H, W) values -> (H, W, 3) uint8 RGB, linear between the stops, clamped outside [lo, hi]."""
    t = np.clip((np.nan_to_num(values, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    stops = np.array([s for s, _ in ramp])
    colours = np.array([c for _, c in ramp], np.float64)
    rgb = np.stack([np.interp(t, stops, colours[:, k]) for k in range(3)], axis=-1)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def hillshade(
    height: np.ndarray, resolution: float, azimuth_deg: float = 315.0, altitude_deg: float = 45.0
) -> np.ndarray:
    """(H, W) float32 illumination in [0, 1] of a height grid (m, ``resolution`` m cells, north up), Horn's
    3x3 slope; NaN cells take their nearest neighbours' heights first (they are masked by the caller)."""
    z = _filled(height)
    kx = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], np.float32) / (8.0 * resolution)
    dzdx = cv2.filter2D(z, cv2.CV_32F, kx, borderType=cv2.BORDER_REPLICATE)
    dzdy = -cv2.filter2D(z, cv2.CV_32F, kx.T, borderType=cv2.BORDER_REPLICATE)  # rows grow southwards
    slope = np.arctan(np.hypot(dzdx, dzdy))
    aspect = np.arctan2(-dzdx, -dzdy)  # direction the slope faces, from north, clockwise
    zenith, azimuth = np.radians(90.0 - altitude_deg), np.radians(azimuth_deg)
    shade = np.cos(zenith) * np.cos(slope) + np.sin(zenith) * np.sin(slope) * np.cos(azimuth - aspect)
    return np.clip(shade, 0.0, 1.0).astype(np.float32)


def shaded_relief(height: np.ndarray, resolution: float, lo: float, hi: float, ramp: Ramp = TERRAIN) -> np.ndarray:
    """(H, W, 3) uint8 RGB: the ramp of ``height`` between ``lo`` and ``hi`` darkened by its hillshade
    (a quarter of the light is ambient, so shadowed slopes keep their tint)."""
    light = 0.25 + 0.75 * hillshade(height, resolution) / np.cos(np.radians(45.0))
    rgb = colour_ramp(height, lo, hi, ramp).astype(np.float32) * np.clip(light, 0.0, 1.25)[..., None]
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def legend(lo: float, hi: float, ramp: Ramp) -> list[dict[str, object]]:
    """The ramp's stops at their values: ``[{"value": v, "colour": "#rrggbb"}, ...]``."""
    return [{"value": lo + s * (hi - lo), "colour": "#{:02x}{:02x}{:02x}".format(*c)} for s, c in ramp]


def _filled(height: np.ndarray) -> np.ndarray:
    """Heights with NaN cells replaced by the nearest valid cell's (a Euclidean distance transform)."""
    z = height.astype(np.float32)
    missing = ~np.isfinite(z)
    if not missing.any():
        return z
    if missing.all():
        return np.zeros_like(z)
    _, (rows, cols) = ndimage.distance_transform_edt(missing, return_indices=True)
    return np.asarray(z[rows, cols], np.float32)
