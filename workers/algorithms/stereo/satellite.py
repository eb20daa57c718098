"""Stereo through RPC camera models: correspondences the models generate, the pair's affine rectification,
the disparity range its heights span, and triangulation of a disparity map back to the ground.

A grid of left pixels is localised at several heights (``Rpc.localize``) and projected into the right photo
(``Rpc.project``): exact correspondences of known ground points, which fix the affine epipolar geometry of
the pair (``rectification.affine_rectification``) and, after rectification, how disparity maps to height.
A matched pixel is then triangulated by Gauss-Newton on (lon, lat, height), minimising its reprojection
error in both photos (the RPC intersection of Grodecki & Dial 2003), from a start interpolated from those
correspondences.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from workers.algorithms.stereo.rectification import Rectification, affine_rectification
from workers.algorithms.stereo.rpc import Rpc

GRID = 15  # correspondences per side of the left photo
LEVELS = 5  # heights they are generated at (odd: the middle one is the reference, zero disparity)
CHUNK = 100_000  # pixels triangulated at a time (a few hundred bytes each)


@dataclass(frozen=True)
class Correspondences:
    """``left``, ``right`` (N, 2) pixels of the ground points ``lon``, ``lat``, ``height`` (N,); ``reference``
    (N,) bool, those at the middle height."""

    left: np.ndarray
    right: np.ndarray
    lon: np.ndarray
    lat: np.ndarray
    height: np.ndarray
    reference: np.ndarray


def rpc_correspondences(
    rpc_l: Rpc, rpc_r: Rpc, size_l: tuple[int, int], heights: tuple[float, float]
) -> Correspondences:
    """``GRID`` x ``GRID`` left pixels over the photo, localised at ``LEVELS`` heights in ``heights`` (m) and
    projected into the right photo."""
    w, h = size_l
    lo, hi = heights
    if not hi > lo:
        raise ValueError(f"the height range must be increasing, got {lo} to {hi} m")
    cols, rows, levels = np.meshgrid(
        np.linspace(0, w - 1, GRID), np.linspace(0, h - 1, GRID), np.linspace(lo, hi, LEVELS), indexing="ij"
    )
    lon, lat = rpc_l.localize(cols.ravel(), rows.ravel(), levels.ravel())
    xr, yr = rpc_r.project(lon, lat, levels.ravel())
    left = np.column_stack([cols.ravel(), rows.ravel()])
    right = np.column_stack([xr, yr])
    if not np.isfinite(right).all() or not np.isfinite(lon).all():
        raise ValueError("the RPC models do not map the left photo into the right one over these heights")
    reference = np.isclose(levels.ravel(), 0.5 * (lo + hi))
    return Correspondences(left, right, lon, lat, levels.ravel(), reference)


def rpc_rectification(corr: Correspondences, size_l: tuple[int, int]) -> Rectification:
    """The pair's affine rectification from its RPC correspondences (zero disparity at the middle height)."""
    return affine_rectification(corr.left, corr.right, corr.reference, size_l)


def rectified_disparities(corr: Correspondences, rect: Rectification) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rectified left (x, y) and disparity x_L - x_R of each correspondence, (N,) each."""
    xl, yl = _homography(rect.left, corr.left)
    xr, _ = _homography(rect.right, corr.right)
    return xl, yl, xl - xr


def height_disparity_range(corr: Correspondences, rect: Rectification, margin_px: float = 4.0) -> tuple[int, int]:
    """``(min_disparity, num_disparities)`` that the heights of the correspondences span, widened by
    ``margin_px``, ``num_disparities`` a multiple of 16."""
    _, _, d = rectified_disparities(corr, rect)
    low = int(np.floor(d.min() - margin_px))
    count = int(np.ceil((d.max() + margin_px - low) / 16.0) * 16)
    return low, max(count, 16)


def triangulate_rpc(
    rpc_l: Rpc,
    rpc_r: Rpc,
    corr: Correspondences,
    rect: Rectification,
    x: np.ndarray,
    y: np.ndarray,
    disparity: np.ndarray,
    iterations: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ground points of rectified left pixels (x, y) whose match is (x - disparity, y).

    Parameters
    ----------
    rpc_l, rpc_r : the photos' models; corr, rect : the pair's correspondences and rectification
    x, y, disparity : (N,) float64 rectified left pixels and their disparities, px

    Returns
    -------
    lon, lat, height : (N,) float64 degrees, degrees, metres
    residual : (N,) float64 RMS reprojection error in the two photos, px (what the rectification's affine
        approximation leaves, and nothing a wrong disparity can show: that error lies along the epipolar line)
    """
    x, y, disparity = (np.asarray(v, np.float64).ravel() for v in (x, y, disparity))
    start = _initial_model(corr, rect)
    out = [np.empty(len(x)) for _ in range(4)]
    for s in range(0, len(x), CHUNK):
        part = slice(s, s + CHUNK)
        xl, yl = _homography(np.linalg.inv(rect.left), np.column_stack([x[part], y[part]]))
        xr, yr = _homography(np.linalg.inv(rect.right), np.column_stack([x[part] - disparity[part], y[part]]))
        guess = start(x[part], y[part], disparity[part])
        target = np.column_stack([xl, yl, xr, yr])
        for k, values in enumerate(_intersect(rpc_l, rpc_r, target, guess, iterations)):
            out[k][part] = values
    return out[0], out[1], out[2], out[3]


def _homography(h: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.column_stack([points, np.ones(len(points))]) @ h.T
    return p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]


def _quadratic(u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.column_stack([np.ones_like(u), u, v, w, u * u, v * v, w * w, u * v, u * w, v * w])


def _initial_model(
    corr: Correspondences, rect: Rectification
) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """(x, y, d) -> (lon, lat, h) (N, 3): a quadratic fitted to the correspondences, normalised inputs."""
    xs, ys, ds = rectified_disparities(corr, rect)
    scale = np.array([max(np.ptp(xs), 1.0), max(np.ptp(ys), 1.0), max(np.ptp(ds), 1.0)])
    centre = np.array([xs.mean(), ys.mean(), ds.mean()])
    design = _quadratic(*((np.column_stack([xs, ys, ds]) - centre) / scale).T)
    coeffs, *_ = np.linalg.lstsq(design, np.column_stack([corr.lon, corr.lat, corr.height]), rcond=None)

    def start(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> np.ndarray:
        u = (np.column_stack([x, y, d]) - centre) / scale
        return np.asarray(_quadratic(*u.T) @ coeffs)

    return start


def _intersect(
    rpc_l: Rpc, rpc_r: Rpc, target: np.ndarray, guess: np.ndarray, iterations: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton on (lon, lat, h), steps in the left model's normalised units; target (N, 4) px."""
    units = np.abs(np.array([rpc_l.long_scale, rpc_l.lat_scale, rpc_l.height_scale]))
    steps = units * 1e-6

    def residual(g: np.ndarray) -> np.ndarray:
        cl, rl = rpc_l.project(g[:, 0], g[:, 1], g[:, 2])
        cr, rr = rpc_r.project(g[:, 0], g[:, 1], g[:, 2])
        return np.column_stack([cl, rl, cr, rr]) - target

    g = guess.copy()
    r0 = residual(g)
    # The start is close (a quadratic through exact correspondences): the Jacobian taken there serves every
    # step (the chord method), a third of the projections of a full Gauss-Newton.
    jac = np.empty((len(g), 4, 3))
    for k in range(3):
        moved = g.copy()
        moved[:, k] += steps[k]
        jac[:, :, k] = (residual(moved) - r0) / 1e-6  # per normalised unit: a well-scaled system
    normal = np.einsum("nik,nil->nkl", jac, jac)
    ok = np.abs(np.linalg.det(normal)) > 1e-300
    inverse = np.zeros_like(normal)
    inverse[ok] = np.linalg.inv(normal[ok])
    for _ in range(iterations):
        rhs = -np.einsum("nik,ni->nk", jac, r0)
        g += np.einsum("nkl,nl->nk", inverse, rhs) * units
        r0 = residual(g)
    return g[:, 0], g[:, 1], g[:, 2], np.sqrt(np.mean(r0 * r0, axis=1))
