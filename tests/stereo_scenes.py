"""Stereo pairs with known truth: a satellite-like pair with RPCs over a known terrain, and a rectified pair.

``make_rpc_pair`` renders two views of a procedural terrain (smooth hills and ridges, about 40 m of relief)
seen by two far-away pinhole cameras looking 15 degrees forward and backward along track (base-to-height
ratio 0.54), each turned by a few degrees of yaw, at about 1 m per pixel. Each view's ground -> pixel
mapping is fitted by an RPC00B model over a 3-D grid (residual well under 0.001 px) and written as a
single-band 16-bit GeoTIFF (11-bit values) with the RPCs in its metadata and no geotransform, as a
satellite image product comes. Every pixel is the mean of 3 x 3 rays traced to the terrain and a texture
draped on it, plus sensor noise.

World frame: UTM easting and northing (``epsg``) and height above the ellipsoid, metres.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from pyproj import Transformer
from rasterio.rpc import RPC

from tests.scenes import make_texture
from workers.algorithms.stereo import Rpc, fit_rpc

ORBIT_M = 500_000.0  # camera distance above the scene, m: a nearly parallel projection, as from orbit


@dataclass(frozen=True)
class PinholeView:
    """A camera far above the scene: ``X_cam = R (X - C)``, world = (E, N, h) metres."""

    R: np.ndarray
    C: np.ndarray
    f: float
    cx: float
    cy: float
    width: int
    height: int

    def project(self, e: np.ndarray, n: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = (np.stack([e, n, h], axis=-1) - self.C) @ self.R.T
        return self.f * p[..., 0] / p[..., 2] + self.cx, self.f * p[..., 1] / p[..., 2] + self.cy

    def rays(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """World directions (..., 3) of pixels."""
        cam = np.stack([(col - self.cx) / self.f, (row - self.cy) / self.f, np.ones_like(col)], axis=-1)
        return cam @ self.R  # R.T @ d per pixel


@dataclass(frozen=True)
class RpcPair:
    """Two GeoTIFFs with RPCs and their truth: ``height(e, n)`` of the terrain in the UTM zone ``epsg``."""

    left: Path
    right: Path
    views: tuple[PinholeView, PinholeView]
    rpcs: tuple[Rpc, ...]
    rpc_fit_px: float  # largest RPC misfit over random points in the fitting box, px
    epsg: int
    centre: tuple[float, float]  # scene centre, easting and northing
    base_height: float  # m
    relief_m: float
    gsd_m: float

    def height(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Terrain height (m) at easting, northing."""
        x, y = np.asarray(e) - self.centre[0], np.asarray(n) - self.centre[1]
        return terrain_height(x, y, self.base_height, self.relief_m)

    def visible(self, e: np.ndarray, n: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Ground points (on the terrain at e, n) seen by both views: inside both frames (``margin_px`` from
        their edges) and with nothing of the terrain between them and either camera."""
        e, n = np.asarray(e, np.float64), np.asarray(n, np.float64)
        h = self.height(e, n)
        seen = np.ones(e.shape, bool)
        for view in self.views:
            col, row = view.project(e, n, h)
            seen &= (col >= margin_px) & (col <= view.width - 1 - margin_px)
            seen &= (row >= margin_px) & (row <= view.height - 1 - margin_px)
            towards = view.C - np.stack([e, n, h], axis=-1)
            towards /= towards[..., 2:3]  # per metre of height
            for rise in np.arange(1.0, 2.0 * self.relief_m, 1.0):  # march up the ray, past the highest hill
                p = np.stack([e, n, h], axis=-1) + rise * towards
                seen &= p[..., 2] >= self.height(p[..., 0], p[..., 1]) - 1e-6
        return seen


def make_rpc_pair(
    out_dir: Path,
    size: tuple[int, int] = (300, 280),
    gsd_m: float = 1.0,
    relief_m: float = 40.0,
    view_deg: float = 15.0,
    yaw_deg: tuple[float, float] = (4.0, -7.0),
    noise: float = 2.0,
    seed: int = 0,
    origin_lonlat: tuple[float, float] = (8.55, 47.37),
) -> RpcPair:
    """Render the pair (``size`` = width, height px each) into ``out_dir`` as ``left.tif`` and ``right.tif``.

    ``view_deg``: each camera looks this far from the vertical, the left one from the south (forward), the
    right one from the north; ``yaw_deg``: their image columns turned from east by this much; ``noise``:
    standard deviation of the sensor noise, grey levels of 2047.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    lon0, lat0 = origin_lonlat
    epsg = (32600 if lat0 >= 0 else 32700) + int((lon0 + 180) // 6) % 60 + 1
    e0, n0 = Transformer.from_crs(4326, epsg, always_xy=True).transform(lon0, lat0)
    base = 420.0
    target = np.array([e0, n0, terrain_height(0.0, 0.0, base, relief_m)])
    views = (_view(target, size, gsd_m, view_deg, yaw_deg[0]), _view(target, size, gsd_m, -view_deg, yaw_deg[1]))
    pair = RpcPair(out_dir / "left.tif", out_dir / "right.tif", views, (), 0.0, epsg, (e0, n0), base, relief_m, gsd_m)
    rng = np.random.default_rng(seed)
    texture_gsd = gsd_m / 2.0
    span = 1.6 * max(size) * gsd_m
    side = int(span / texture_gsd)
    texture = cv2.cvtColor(make_texture(side, side, seed=seed), cv2.COLOR_BGR2GRAY)
    rpcs, misfit = [], 0.0
    for view, path in zip(pair.views, (pair.left, pair.right), strict=True):
        image = _render(pair, view, texture.astype(np.float32), texture_gsd)
        counts = np.clip(np.rint(image / 255.0 * 1900.0 + 60.0 + rng.normal(0, noise, image.shape)), 0, 2047)
        rpc, fit_px = _fitted_rpc(pair, view)
        misfit = max(misfit, fit_px)
        _write_geotiff(path, counts.astype(np.uint16), rpc)
        rpcs.append(rpc)
    return dataclasses.replace(pair, rpcs=(rpcs[0], rpcs[1]), rpc_fit_px=misfit)


def terrain_height(x: Any, y: Any, base: float, relief: float) -> np.ndarray:
    """Height (m) at x, y metres east and north of the scene centre: three hills and a hollow of ``relief``
    scale, a rolling ripple and a gentle slope; slopes stay under 0.5, so 15 degree views see all of it."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return (
        base
        + relief * np.exp(-((x - 40) ** 2 + (y - 25) ** 2) / (2 * 55.0**2))
        + 0.6 * relief * np.exp(-((x + 70) ** 2 + (y + 50) ** 2) / (2 * 40.0**2))
        - 0.35 * relief * np.exp(-((x + 30) ** 2 + (y - 90) ** 2) / (2 * 35.0**2))
        + 0.08 * relief * np.sin(x / 19.0) * np.cos(y / 23.0)
        + 0.02 * x
    )


def _view(target: np.ndarray, size: tuple[int, int], gsd: float, tilt_deg: float, yaw_deg: float) -> PinholeView:
    """A camera ``ORBIT_M`` above ``target`` looking at it ``tilt_deg`` from the vertical (from the south when
    positive), its columns turned ``yaw_deg`` from east, ``gsd`` m per px at the target."""
    C = target + ORBIT_M * np.array([0.0, -math.tan(math.radians(tilt_deg)), 1.0])
    forward = (target - C) / np.linalg.norm(target - C)
    across = np.array([math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg)), 0.0])
    x_axis = across - (across @ forward) * forward
    x_axis /= np.linalg.norm(x_axis)
    R = np.stack([x_axis, np.cross(forward, x_axis), forward])
    w, h = size
    return PinholeView(R, C, float(np.linalg.norm(target - C)) / gsd, (w - 1) / 2.0, (h - 1) / 2.0, w, h)


def _ground(pair: RpcPair, view: PinholeView, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Easting, northing where the pixels' rays meet the terrain (fixed-point iteration on height)."""
    d = view.rays(col, row)
    h = np.full(col.shape, pair.base_height)
    for _ in range(12):  # contracts by slope x tan(view angle) < 0.3 per step: 0.3^12 x 40 m < 0.1 mm
        t = (h - view.C[2]) / d[..., 2]
        e, n = view.C[0] + t * d[..., 0], view.C[1] + t * d[..., 1]
        h = pair.height(e, n)
    return e, n


def _render(pair: RpcPair, view: PinholeView, texture: np.ndarray, texture_gsd: float) -> np.ndarray:
    """(H, W) float grey levels 0-255: the mean of 3 x 3 rays per pixel."""
    th, tw = texture.shape
    acc = np.zeros((view.height, view.width), np.float64)
    rows, cols = np.mgrid[0 : view.height, 0 : view.width].astype(np.float64)
    for dy in (-1 / 3, 0.0, 1 / 3):
        for dx in (-1 / 3, 0.0, 1 / 3):
            e, n = _ground(pair, view, cols + dx, rows + dy)
            tx = ((e - pair.centre[0]) / texture_gsd + (tw - 1) / 2).astype(np.float32)
            ty = ((pair.centre[1] - n) / texture_gsd + (th - 1) / 2).astype(np.float32)
            acc += cv2.remap(texture, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return acc / 9.0


def _fitted_rpc(pair: RpcPair, view: PinholeView) -> tuple[Rpc, float]:
    """The view's RPC fitted over its footprint (+10 %) and the terrain's heights (+-30 m), and its misfit."""
    corners_c = np.array([0, view.width - 1, 0, view.width - 1], np.float64)
    corners_r = np.array([0, 0, view.height - 1, view.height - 1], np.float64)
    e, n = _ground(pair, view, corners_c, corners_r)
    pad = 0.1 * max(np.ptp(e), np.ptp(n))
    lo_h, hi_h = pair.base_height - 30.0, pair.base_height + pair.relief_m + 30.0
    to_lonlat = Transformer.from_crs(pair.epsg, 4326, always_xy=True)

    def samples(es: np.ndarray, ns: np.ndarray, hs: np.ndarray) -> tuple[np.ndarray, ...]:
        lon, lat = to_lonlat.transform(es, ns)
        col, row = view.project(es, ns, hs)
        return np.asarray(lon), np.asarray(lat), hs, col, row

    E, N, H = np.meshgrid(
        np.linspace(e.min() - pad, e.max() + pad, 15),
        np.linspace(n.min() - pad, n.max() + pad, 15),
        np.linspace(lo_h, hi_h, 5),
        indexing="ij",
    )
    rpc = fit_rpc(*samples(E.ravel(), N.ravel(), H.ravel()))
    rng = np.random.default_rng(1)
    lon, lat, hs, col, row = samples(
        rng.uniform(e.min(), e.max(), 2000), rng.uniform(n.min(), n.max(), 2000), rng.uniform(lo_h, hi_h, 2000)
    )
    c2, r2 = rpc.project(lon, lat, hs)
    return rpc, float(np.hypot(c2 - col, r2 - row).max())


def _write_geotiff(path: Path, counts: np.ndarray, rpc: Rpc) -> None:
    """A single-band uint16 GeoTIFF with RPC metadata and no geotransform (as a satellite L1 product)."""
    profile = {"driver": "GTiff", "width": counts.shape[1], "height": counts.shape[0], "count": 1, "dtype": "uint16"}
    with rasterio.open(path, "w", **profile, rpcs=RPC(**rpc.to_json())) as dst:
        dst.write(counts, 1)


def make_rectified_pair(
    seed: int = 0, size: tuple[int, int] = (200, 120), d_back: float = 6.5, d_front: float = 14.25
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left, right (H, W) uint8 and the left view's true disparity of a rectified pair: a background plane
    at ``d_back`` px and a box in front of it at ``d_front`` (right(x) = scene(x + d))."""
    w, h = size
    rng = np.random.default_rng(seed)

    def texture() -> np.ndarray:
        img = cv2.GaussianBlur(rng.random((h, w + 40)).astype(np.float32), (0, 0), 1.0)
        return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)

    back, front = texture(), texture()
    x = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0)
    y = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    box = lambda xs: (xs >= 0.4 * w) & (xs < 0.75 * w) & (y >= 0.25 * h) & (y < 0.75 * h)  # noqa: E731
    sample = lambda img, xs: cv2.remap(img, xs, y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)  # noqa: E731
    left = np.where(box(x), front[:, :w], back[:, :w])
    right = np.where(box(x + d_front), sample(front, x + d_front), sample(back, x + d_back))
    truth = np.where(box(x), d_front, d_back).astype(np.float32)
    noisy = lambda img: np.clip(img + rng.normal(0, 1.5, img.shape), 0, 255).astype(np.uint8)  # noqa: E731
    return noisy(left), noisy(right), truth


@dataclass(frozen=True)
class DsmAccuracy:
    """A DSM against the terrain: ``median_error_m`` of its measured cells, ``completeness`` the share of
    ground cells (seen by both views, away from their edges) measured within ``tolerance_m``, over ``cells``."""

    median_error_m: float
    completeness: float
    cells: int
    tolerance_m: float


def dsm_accuracy(pair: RpcPair, dsm_path: Path, mask_path: Path, margin_px: float = 5.0) -> DsmAccuracy:
    """Score ``dsm.tif`` (and ``dsm_mask.tif``: 1 measured) against the pair's terrain at the cell centres."""
    with rasterio.open(dsm_path) as src:
        assert src.crs.to_epsg() == pair.epsg
        height = src.read(1, masked=True).filled(np.nan)
        rows, cols = np.mgrid[0 : src.height, 0 : src.width]
        east, north = rasterio.transform.xy(src.transform, rows.ravel(), cols.ravel())
    with rasterio.open(mask_path) as src:
        measured = src.read(1) == 1
    e, n = np.asarray(east).reshape(height.shape), np.asarray(north).reshape(height.shape)
    ground = pair.visible(e, n, margin_px)
    error = np.abs(height - pair.height(e, n))
    good = measured & np.isfinite(error)
    tolerance = pair.gsd_m
    return DsmAccuracy(
        float(np.median(error[good & ground])),
        float((good & (error <= tolerance))[ground].mean()),
        int(ground.sum()),
        tolerance,
    )


def make_rig_pair(
    out_dir: Path,
    rig: Any,
    plane: tuple[float, float, float] = (1500.0, 0.3, 0.0),
    texture_mm: float = 1.5,
    seed: int = 0,
) -> tuple[Path, Path]:
    """A calibrated rig's two photos (``StereoRig``: distorted lenses, toed in) of a textured plane
    Z = z0 + a X + b Y in the left camera's frame (``plane`` = (z0, a, b), mm), as PNGs in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    z0, a, b = plane
    side = int(2400 / texture_mm)
    texture = cv2.cvtColor(make_texture(side, side, seed=seed), cv2.COLOR_BGR2GRAY).astype(np.float32)
    paths = []
    for name, camera, rotation, origin in (
        ("left", rig.left, np.eye(3), np.zeros(3)),
        ("right", rig.right, rig.R, rig.right_centre),
    ):
        v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
        rays = camera.unproject(np.column_stack([u.ravel(), v.ravel()])) @ rotation  # in the left frame
        s = (z0 + a * origin[0] + b * origin[1] - origin[2]) / (rays[:, 2] - a * rays[:, 0] - b * rays[:, 1])
        points = origin + s[:, None] * rays
        tx = (points[:, 0] / texture_mm + (side - 1) / 2).reshape(u.shape).astype(np.float32)
        ty = (points[:, 1] / texture_mm + (side - 1) / 2).reshape(u.shape).astype(np.float32)
        image = cv2.remap(texture, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        paths.append(out_dir / f"{name}.png")
        cv2.imwrite(str(paths[-1]), np.clip(image, 0, 255).astype(np.uint8))
    return paths[0], paths[1]
