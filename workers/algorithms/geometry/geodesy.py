"""From the mosaic plane to map coordinates: UTM zone choice and a similarity fitted to GPS fixes."""

from __future__ import annotations

import numpy as np

# Image rows grow downwards, northings upwards: the plane is flipped before the (reflection-free)
# similarity, so a nadir photo is never mirrored.
FLIP_Y = np.diag([1.0, -1.0, 1.0])


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of the WGS84 UTM zone holding (lat, lon): 326zz north, 327zz south."""
    if not (-80.0 <= lat <= 84.0):
        raise ValueError(f"latitude {lat} is outside UTM coverage (-80..84)")
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


def lonlat_to_utm(lonlat: np.ndarray, epsg: int) -> np.ndarray:
    """(N, 2) lon, lat degrees -> (N, 2) easting, northing metres (pyproj, ~20 MiB, imported by a job that has GPS
    rather than by every worker that imports this module)."""
    from pyproj import Transformer

    tr = Transformer.from_crs(4326, epsg, always_xy=True)
    e, n = tr.transform(lonlat[:, 0], lonlat[:, 1])
    return np.column_stack([e, n])


def utm_to_lonlat(en: np.ndarray, epsg: int) -> np.ndarray:
    """(N, 2) easting, northing metres -> (N, 2) lon, lat degrees."""
    from pyproj import Transformer  # see lonlat_to_utm

    tr = Transformer.from_crs(epsg, 4326, always_xy=True)
    lon, lat = tr.transform(en[:, 0], en[:, 1])
    return np.column_stack([lon, lat])


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity ``dst ~ s R src + t`` without reflection (Umeyama 1991).

    Parameters
    ----------
    src, dst : (N, 2) float64, N >= 2 distinct points.

    Returns
    -------
    (3, 3) float64 homogeneous matrix.
    """
    if len(src) < 2 or len(src) != len(dst):
        raise ValueError("fit_similarity needs at least 2 point pairs of equal count")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    var = (a**2).sum() / len(src)
    if var <= 0:
        raise ValueError("fit_similarity needs distinct source points")
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ d @ Vt
    scale = np.trace(np.diag(S) @ d) / var
    M = np.eye(3)
    M[:2, :2] = scale * R
    M[:2, 2] = mu_d - scale * R @ mu_s
    return M


def similarity_scale(M: np.ndarray) -> float:
    """Scale factor of a similarity matrix (map units per source unit)."""
    return float(np.sqrt(abs(np.linalg.det(M[:2, :2]))))
