"""Rational polynomial camera models (RPC00B): projection, localisation, fitting.

A satellite image's RPCs map ground (longitude, latitude, height above the ellipsoid) to image
(sample, line) as ratios of cubic polynomials of normalised coordinates (NITF STDI-0002 RPC00B; GDAL's
``RPC`` metadata domain, rasterio's ``dataset.rpcs``)::

    sample = samp_num(L, P, H) / samp_den(L, P, H) * samp_scale + samp_off
    L = (lon - long_off) / long_scale,  P = (lat - lat_off) / lat_scale,  H = (h - height_off) / height_scale

Pixel coordinates here follow RPC00B and the rest of this package: (0, 0) is the centre of the first pixel.
GDAL's ``RPCTransformer`` answers in its own convention, (0, 0) the first pixel's corner (``+ 0.5``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

TERMS = 20  # monomials of a cubic in three variables


def monomials(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """The 20 RPC00B terms in their standard order, (20, N) float64, for (N,) normalised coordinates."""
    t = np.empty((TERMS, len(L)))
    t[0], t[1], t[2], t[3] = 1.0, L, P, H
    np.multiply(L, P, out=t[4])
    np.multiply(L, H, out=t[5])
    np.multiply(P, H, out=t[6])
    np.multiply(L, L, out=t[7])
    np.multiply(P, P, out=t[8])
    np.multiply(H, H, out=t[9])
    np.multiply(t[4], H, out=t[10])  # P L H
    np.multiply(t[7], L, out=t[11])  # L^3
    np.multiply(t[8], L, out=t[12])  # L P^2
    np.multiply(t[9], L, out=t[13])  # L H^2
    np.multiply(t[7], P, out=t[14])  # L^2 P
    np.multiply(t[8], P, out=t[15])  # P^3
    np.multiply(t[9], P, out=t[16])  # P H^2
    np.multiply(t[7], H, out=t[17])  # L^2 H
    np.multiply(t[8], H, out=t[18])  # P^2 H
    np.multiply(t[9], H, out=t[19])  # H^3
    return t


@dataclass(frozen=True, eq=False)
class Rpc:
    """One image's RPC00B model; field names as rasterio's ``RPC.to_dict()`` (coefficients (20,) float64)."""

    height_off: float
    height_scale: float
    lat_off: float
    lat_scale: float
    long_off: float
    long_scale: float
    line_off: float
    line_scale: float
    samp_off: float
    samp_scale: float
    line_num_coeff: np.ndarray
    line_den_coeff: np.ndarray
    samp_num_coeff: np.ndarray
    samp_den_coeff: np.ndarray

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name.endswith("_coeff"):
                arr = np.asarray(value, dtype=np.float64).ravel()
                if arr.shape != (TERMS,) or not np.isfinite(arr).all():
                    raise ValueError(f"RPC {f.name} must be {TERMS} finite numbers")
                object.__setattr__(self, f.name, arr)
            else:
                number = float(value)
                if not np.isfinite(number) or (f.name.endswith("_scale") and number == 0.0):
                    raise ValueError(f"RPC {f.name} must be a finite{' non-zero' if 'scale' in f.name else ''} number")
                object.__setattr__(self, f.name, number)

    # -- conversions ------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Rpc:
        """From rasterio's ``RPC.to_dict()`` (or ``to_json``); ``ValueError`` naming what is missing or bad."""
        if not isinstance(data, dict):
            raise ValueError("RPC metadata must be a mapping")
        names = [f.name for f in fields(cls)]
        missing = [n for n in names if data.get(n) is None]
        if missing:
            raise ValueError(f"RPC metadata lacks {', '.join(missing)}")
        try:
            return cls(**{n: data[n] for n in names})
        except (TypeError, ValueError) as exc:
            raise ValueError(str(exc)) from None

    def to_json(self) -> dict[str, Any]:
        return {
            f.name: (getattr(self, f.name).tolist() if f.name.endswith("_coeff") else getattr(self, f.name))
            for f in fields(self)
        }

    # -- mappings ---------------------------------------------------------------------------------
    def _normalised(self, lon: Any, lat: Any, h: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lon, lat, h = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (lon, lat, h)))
        return (
            (lon - self.long_off) / self.long_scale,
            (lat - self.lat_off) / self.lat_scale,
            (h - self.height_off) / self.height_scale,
        )

    def _project_normalised(self, L: np.ndarray, P: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        shape = L.shape
        coeffs = np.stack([self.samp_num_coeff, self.samp_den_coeff, self.line_num_coeff, self.line_den_coeff])
        s_num, s_den, l_num, l_den = coeffs @ monomials(L.ravel(), P.ravel(), H.ravel())
        col = s_num / s_den * self.samp_scale + self.samp_off
        row = l_num / l_den * self.line_scale + self.line_off
        return col.reshape(shape), row.reshape(shape)

    def project(self, lon: Any, lat: Any, h: Any) -> tuple[np.ndarray, np.ndarray]:
        """Ground (degrees, degrees, metres) -> pixel (column, row), arrays of the broadcast shape."""
        return self._project_normalised(*self._normalised(lon, lat, h))

    def localize(self, col: Any, row: Any, h: Any, iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """Pixel (column, row) at height ``h`` (m) -> ground (lon, lat) degrees, by Newton's method.

        Starts from the model's centre; the 2x2 Jacobian is taken by central differences in normalised
        coordinates. Converges to well under 1e-6 px in a few steps inside the model's validity box.
        """
        col, row, h = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (col, row, h)))
        H = (h - self.height_off) / self.height_scale
        L, P = np.zeros_like(H), np.zeros_like(H)
        eps = 1e-6
        for _ in range(iterations):
            c0, r0 = self._project_normalised(L, P, H)
            cl1, rl1 = self._project_normalised(L + eps, P, H)
            cp1, rp1 = self._project_normalised(L, P + eps, H)
            a, b = (cl1 - c0) / eps, (cp1 - c0) / eps
            c, d = (rl1 - r0) / eps, (rp1 - r0) / eps
            det = a * d - b * c
            det = np.where(np.abs(det) > 1e-300, det, 1e-300)
            dc, dr = col - c0, row - r0
            L = L + (d * dc - b * dr) / det
            P = P + (a * dr - c * dc) / det
        return L * self.long_scale + self.long_off, P * self.lat_scale + self.lat_off

    @property
    def height_range(self) -> tuple[float, float]:
        """The heights the model was fitted over (offset -+ scale), m."""
        return self.height_off - abs(self.height_scale), self.height_off + abs(self.height_scale)


def fit_rpc(lon: np.ndarray, lat: np.ndarray, h: np.ndarray, col: np.ndarray, row: np.ndarray) -> Rpc:
    """Fit an RPC00B model to ground -> pixel samples by linear least squares (terrain-independent fit).

    Parameters
    ----------
    lon, lat, h : (N,) float64 ground points, degrees and metres, spread over a 3-D box (a grid of
        several heights: a single height plane leaves the height terms undetermined)
    col, row : (N,) float64 their pixels, (0, 0) the centre of the first pixel

    Each of sample and line is solved as ``num(t) - y * (den(t) - 1) = y`` with ``den``'s constant term
    1 (Tao & Hu 2001, the direct least-squares solution), minimum-norm where the data cannot tell terms
    apart (a near-affine camera leaves the denominator free). Offsets are the samples' mid-ranges and
    scales their half-ranges, so normalised coordinates lie in [-1, 1].
    """
    arrays = [np.asarray(v, dtype=np.float64).ravel() for v in (lon, lat, h, col, row)]
    if len({len(a) for a in arrays}) != 1 or len(arrays[0]) < 2 * TERMS:
        raise ValueError(f"fit_rpc needs at least {2 * TERMS} samples of equal length")
    off = [0.5 * (a.min() + a.max()) for a in arrays]
    scale = [max(0.5 * (a.max() - a.min()), 1e-9) for a in arrays]
    lon_n, lat_n, h_n, col_n, row_n = ((a - o) / s for a, o, s in zip(arrays, off, scale, strict=True))
    t = monomials(lon_n, lat_n, h_n).T  # (N, 20)

    def solve(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        design = np.concatenate([t, -y[:, None] * t[:, 1:]], axis=1)
        x, *_ = np.linalg.lstsq(design, y, rcond=1e-12)
        return x[:TERMS], np.concatenate([[1.0], x[TERMS:]])

    samp_num, samp_den = solve(col_n)
    line_num, line_den = solve(row_n)
    return Rpc(
        height_off=off[2],
        height_scale=scale[2],
        lat_off=off[1],
        lat_scale=scale[1],
        long_off=off[0],
        long_scale=scale[0],
        line_off=off[4],
        line_scale=scale[4],
        samp_off=off[3],
        samp_scale=scale[3],
        line_num_coeff=line_num,
        line_den_coeff=line_den,
        samp_num_coeff=samp_num,
        samp_den_coeff=samp_den,
    )


def ground_sample_distance(rpc: Rpc, col: float, row: float, h: float) -> float:
    """Side of the ground square one pixel covers at (col, row) and height ``h``, metres (local sphere)."""
    lon, lat = rpc.localize([col, col + 1.0, col], [row, row, row + 1.0], h)
    metres_per_degree = 6378137.0 * np.pi / 180.0
    east = (lon - lon[0]) * metres_per_degree * np.cos(np.radians(lat[0]))
    north = (lat - lat[0]) * metres_per_degree
    area = abs(east[1] * north[2] - east[2] * north[1])
    return float(np.sqrt(area))
