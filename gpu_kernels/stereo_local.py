"""The source work's local stereo matcher: a 2-D window search with a soft epipolar constraint.

For a window D around (u0, v0) it picks the (du, dv) minimising

    E(du, dv) = sum over (u, v) in D of a(u, v) |I_L(u, v) - I_R(u + du, v + dv)|,
    a = w_d(u - u0, v - v0) * w_f(u, v; du, dv),

where ``w_d`` is a Gaussian of the distance from the window centre and ``w_f = 1 + lambda dist^2``
grows with the distance ``dist`` (px) of the candidate (u + du, v + dv) from the epipolar line
``F (u, v, 1)`` of the pixel. The vertical search (``dv`` in [-r, r] around the pixel's row) makes
the epipolar constraint soft, so a pair whose rectification is off by a pixel or so is still
matched, with ``F`` saying where the true line is. Without ``F`` the pair is taken as rectified
(the line of (u, v) is the row v in the right image).

Written as array operations over whole images (NumPy or CuPy, chosen by the input arrays): one
"slab" of costs for every horizontal candidate at a time, per vertical offset, aggregated by a
separable Gaussian (``w_d`` is separable), then a running minimum over the vertical offsets. The
winner gets an equiangular (V) fit along the horizontal axis (sub-pixel), its uniqueness ratio, and the
right view's disparity is read from the same costs (for a left-right check).

Memory plan, (H, W) image and n disparities: the slab, the running minimum and the winning vertical
offsets, 4 + 4 + 1 B per pixel and candidate (9 n B/px: 1.5 GB for a 2.6 MP frame and 64
disparities); split larger images into horizontal strips with a margin of ``window_radius +
vertical_radius`` rows.

No raw CUDA kernel yet: on CuPy the array ops run as CuPy kernels (elementwise and
``cupyx.scipy.ndimage.correlate1d``); a fused raw kernel would have this module as its oracle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpu_kernels.backend import get_array_module, ndimage_module


@dataclass(frozen=True)
class LocalMatch:
    """Per left pixel, (H, W) float32 arrays.

    ``disparity``: x_L - x_R of the winner in px (sub-pixel), NaN where no candidate is inside the
    right image; ``vertical``: y_R - y_L of the winner (whole px); ``cost``: E at the winner;
    ``ratio``: second-best E (horizontally more than 1 px away) over the best, >= 1, inf when there
    is no second; ``right_disparity``: the right view's disparity from the same costs (per right
    pixel, NaN where none).
    """

    disparity: Any
    vertical: Any
    cost: Any
    ratio: Any
    right_disparity: Any


def rectified_fundamental() -> np.ndarray:
    """F of an ideally rectified pair (x_R^T F x_L = 0 means y_R = y_L), (3, 3) float64."""
    return np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def epipolar_terms(fundamental: Any, shape: tuple[int, int], xp: Any) -> tuple[Any, Any, Any]:
    """Normalised lines l = F (u, v, 1) / |(l0, l1)| of every left pixel, split for fast distances.

    Returns ``(base, a, b)``, each (H, W) float32, such that the signed distance of the candidate
    (u + du, v + dv) from the line of (u, v) is ``base + a du + b dv`` (``base`` is the distance of
    (u, v) itself). ``fundamental`` (3, 3) maps left points to right lines, x_R^T F x_L = 0.
    """
    f = xp.asarray(fundamental, dtype=xp.float64)
    if f.shape != (3, 3):
        raise ValueError("fundamental must be a (3, 3) matrix")
    h, w = shape
    v, u = xp.meshgrid(xp.arange(h, dtype=xp.float64), xp.arange(w, dtype=xp.float64), indexing="ij")
    lines = [f[i, 0] * u + f[i, 1] * v + f[i, 2] for i in range(3)]
    norm = xp.sqrt(lines[0] ** 2 + lines[1] ** 2)
    norm = xp.where(norm > 1e-12, norm, 1.0)
    a, b = lines[0] / norm, lines[1] / norm
    base = a * u + b * v + lines[2] / norm
    return base.astype(xp.float32), a.astype(xp.float32), b.astype(xp.float32)


def window_weights(window_radius: int, sigma: float | None = None) -> np.ndarray:
    """1-D factor of w_d, (2 r + 1,) float32, unit sum; w_d(du, dv) = k[du] k[dv]. sigma: r / 2."""
    if window_radius < 0:
        raise ValueError("window_radius must be >= 0")
    s = window_radius / 2.0 if sigma is None else sigma
    x = np.arange(-window_radius, window_radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / max(s, 1e-6)) ** 2)
    return (k / k.sum()).astype(np.float32)


def _shifted(volume: Any, shifts: np.ndarray, fill: float) -> Any:
    """``out[i, :, x] = volume[i, :, x + shifts[i]]``, ``fill`` where x + shift is outside."""
    xp = get_array_module(volume)
    out = xp.full_like(volume, fill)
    w = volume.shape[2]
    for i, s in enumerate(shifts.tolist()):
        lo, hi = max(0, -s), min(w, w - s)
        if hi > lo:
            out[i, :, lo:hi] = volume[i, :, lo + s : hi + s]
    return out


def winner(volume: Any, disparities: np.ndarray) -> tuple[Any, Any, Any]:
    """Sub-pixel winner of an (n, H, W) cost volume along axis 0 (n disparities, ascending by 1).

    Returns ``disparity`` (H, W) float32 (NaN where every cost is inf), ``best`` cost and the
    uniqueness ``ratio`` (second best more than one step away / best). The sub-pixel offset is the
    vertex of the symmetric V through the best cost and its two neighbours, clipped to +-0.5.
    """
    xp = get_array_module(volume)
    n = volume.shape[0]
    k = volume.argmin(axis=0)
    take = lambda idx: xp.take_along_axis(volume, idx[None], axis=0)[0]  # noqa: E731
    best = take(k)
    left, right = take(xp.clip(k - 1, 0, n - 1)), take(xp.clip(k + 1, 0, n - 1))
    inner = (k > 0) & (k < n - 1) & xp.isfinite(left) & xp.isfinite(right)
    # An equiangular (V) fit rather than a parabola: SAD costs are V-shaped near the minimum and
    # a parabola pulls the vertex towards whole pixels (Shimizu & Okutomi 2005).
    denom = xp.maximum(left, right) - best
    safe = inner & (denom > 1e-12)
    offset = xp.where(safe, (left - right) / xp.where(safe, 2.0 * denom, 1.0), 0.0)
    offset = xp.clip(offset, -0.5, 0.5)
    steps = xp.arange(n)[:, None, None]
    others = xp.where(xp.abs(steps - k[None]) > 1, volume, xp.inf).min(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = xp.where(best > 0, others / xp.where(best > 0, best, 1.0), xp.where(others > 0, xp.inf, 1.0))
    disp = xp.asarray(disparities, dtype=xp.float32)[k] + offset.astype(xp.float32)
    disp = xp.where(xp.isfinite(best), disp, xp.nan)
    return disp.astype(xp.float32), best.astype(xp.float32), ratio.astype(xp.float32)


def _slab(
    left: Any, right_rows: Any, pad: int, disparities: np.ndarray, weight: Any | None, truncate: float | None
) -> Any:
    """Per-pixel costs a_f |I_L - I_R| (before w_d) of every disparity for one vertical offset."""
    xp = get_array_module(left)
    h, w = left.shape
    slab = xp.empty((len(disparities), h, w), dtype=xp.float32)
    for i, d in enumerate(disparities.tolist()):
        slab[i] = xp.abs(left - right_rows[:, pad - d : pad - d + w])
    if truncate is not None:
        xp.minimum(slab, xp.float32(truncate), out=slab)
    if weight is not None:
        slab *= weight
    return slab


def match_local(
    left: Any,
    right: Any,
    num_disparities: int = 64,
    min_disparity: int = 0,
    *,
    vertical_radius: int = 1,
    fundamental: Any | None = None,
    epipolar_weight: float = 0.5,
    window_radius: int = 4,
    sigma: float | None = None,
    truncate: float | None = None,
) -> LocalMatch:
    """Match every left pixel by the windowed, epipolar-weighted sum of absolute differences.

    Parameters
    ----------
    left, right : (H, W) real arrays, NumPy or CuPy (both the same), grey levels (any scale)
    num_disparities, min_disparity : horizontal candidates d = x_L - x_R in
        [min_disparity, min_disparity + num_disparities), i.e. du = -d
    vertical_radius : vertical candidates dv = y_R - y_L in [-r, r]; 0 is a 1-D search
    fundamental : (3, 3) F with x_R^T F x_L = 0; default the rectified one
    epipolar_weight : lambda of w_f = 1 + lambda dist^2, dist the candidate's distance (px) from
        the pixel's epipolar line; 0 ignores F (a hard band of +-r rows)
    window_radius, sigma : D is (2 r + 1)^2 px, w_d a Gaussian of standard deviation sigma (r / 2)
    truncate : clamp |I_L - I_R| to this before weighting (robust to occlusions); None: no clamp

    Follows the local method of the source work (a 2-D search with a soft epipolar constraint);
    the left-right check and filling are the caller's (``workers.algorithms.disparity.local``).
    """
    xp = get_array_module(left, right)
    if left.shape != right.shape or left.ndim != 2:
        raise ValueError("left and right must be (H, W) images of the same shape")
    if num_disparities < 1 or vertical_radius < 0:
        raise ValueError("num_disparities must be >= 1 and vertical_radius >= 0")
    h, w = left.shape
    nd = ndimage_module(xp)
    lf, rf = left.astype(xp.float32), right.astype(xp.float32)
    disparities = np.arange(min_disparity, min_disparity + num_disparities)
    pad = int(max(abs(int(disparities[0])), abs(int(disparities[-1]))))
    padded = xp.pad(rf, ((vertical_radius, vertical_radius), (pad, pad)), mode="edge")
    kernel = xp.asarray(window_weights(window_radius, sigma))
    f = rectified_fundamental() if fundamental is None else fundamental
    terms = epipolar_terms(f, (h, w), xp) if epipolar_weight > 0 else None
    x = xp.arange(w)[None, None, :]
    centre_out = (x - xp.asarray(disparities)[:, None, None] < 0) | (x - xp.asarray(disparities)[:, None, None] >= w)
    du = xp.asarray(-disparities, dtype=xp.float32)[:, None, None]
    best = xp.full((num_disparities, h, w), xp.inf, dtype=xp.float32)
    best_dv = xp.zeros((num_disparities, h, w), dtype=xp.int8)
    rows = xp.arange(h)
    # 0, -1, 1, -2, 2, ...: on equal cost the smaller vertical offset wins (strict < below).
    for dv in sorted(range(-vertical_radius, vertical_radius + 1), key=lambda s: (abs(s), s)):
        weight = None
        if terms is not None:
            base, a, b = terms
            dist = base[None] + a[None] * du + b[None] * xp.float32(dv)
            weight = 1.0 + xp.float32(epipolar_weight) * dist * dist
        right_rows = padded[vertical_radius + dv : vertical_radius + dv + h]
        slab = _slab(lf, right_rows, pad, disparities, weight, truncate)
        slab = nd.correlate1d(nd.correlate1d(slab, kernel, axis=1, mode="nearest"), kernel, axis=2, mode="nearest")
        slab[centre_out | ((rows + dv < 0) | (rows + dv >= h))[None, :, None]] = xp.inf
        better = slab < best
        best = xp.where(better, slab, best)
        best_dv = xp.where(better, xp.int8(dv), best_dv)
        del slab, better, weight
    disp, cost, ratio = winner(best, disparities)
    steps = xp.where(xp.isfinite(disp), xp.rint(disp - xp.float32(min_disparity)), 0)
    k = xp.clip(steps, 0, num_disparities - 1).astype(xp.int64)
    vertical = xp.take_along_axis(best_dv, k[None], axis=0)[0].astype(xp.float32)
    right_view, _, _ = winner(_shifted(best, disparities, math.inf), disparities)
    return LocalMatch(disp, vertical, cost, ratio, right_view)
