"""NCC of mean-centred windows searched around predicted positions, with the sub-pixel peak (a parabola
through the maximum and its neighbours on each axis), batched and array-module generic (NumPy or CuPy)."""

from __future__ import annotations

from typing import Any

import numpy as np

from gpu_kernels.backend import get_array_module, to_host

NCC_CHUNK = 64  # points whose NCC surfaces are computed at once: 64 x 17^2 x 15^2 float32 = 17 MB


def normalised_windows(windows: Any) -> Any:
    """``(n, t, t)`` windows -> ``(n, t * t) float32`` mean-centred, unit norm (flat windows: zeros)."""
    xp = get_array_module(windows)
    flat = windows.reshape(len(windows), windows.shape[1] * windows.shape[2]).astype(xp.float32)
    flat -= flat.mean(axis=1, keepdims=True)
    norm = xp.sqrt((flat * flat).sum(axis=1, keepdims=True))
    return flat / xp.maximum(norm, 1e-6)


def ncc_peaks(templates: Any, search: Any, h: int, s: int, min_ncc: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel NCC peak of each ``(t * t)`` template over its ``(S, S)`` search window (``S = 2 (h + s) + 1``):
    ``(n, 2) float64`` offset (x, y) from the window centre, ``(n,) float32`` peak score, ``(n,) bool`` usable
    (score at least ``min_ncc``, peak not on the edge of the search, where no parabola fits)."""
    xp = get_array_module(search)
    surface = ncc_surfaces(templates, search, 2 * h + 1, 2 * s + 1)
    n, m = len(surface), 2 * s + 1
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, np.float32), np.zeros(0, bool)
    best = surface.reshape(n, m * m).argmax(axis=1)
    py, px = best // m, best % m
    k = xp.arange(n)
    peak = surface[k, py, px]
    ok = (peak >= min_ncc) & (px > 0) & (px < m - 1) & (py > 0) & (py < m - 1)
    pxc, pyc = xp.clip(px, 1, m - 2), xp.clip(py, 1, m - 2)  # where not ok, any valid neighbour
    dx = px - s + parabola_peak(surface[k, pyc, pxc - 1], peak, surface[k, pyc, pxc + 1])
    dy = py - s + parabola_peak(surface[k, pyc - 1, pxc], peak, surface[k, pyc + 1, pxc])
    offset = xp.stack([dx, dy], axis=1)
    return to_host(offset).astype(np.float64), to_host(peak).astype(np.float32), to_host(ok)


def ncc_surfaces(templates: Any, search: Any, t: int, m: int) -> Any:
    """``(n, m, m) float32`` NCC of each normalised ``(t * t)`` template with every ``t x t`` window of its
    ``(m + t - 1)^2`` search window (``cv2.matchTemplate``'s ``TM_CCOEFF_NORMED``, batched, array-module
    generic), ``NCC_CHUNK`` points at a time."""
    xp = get_array_module(search)
    n = len(search)
    idx = xp.arange(m)[:, None] + xp.arange(t)[None, :]  # (m, t): rows (or columns) of each shifted window
    out = xp.empty((n, m, m), xp.float32)
    for start in range(0, n, NCC_CHUNK):
        part = search[start : start + NCC_CHUNK].astype(xp.float32)
        windows = part[:, idx[:, None, :, None], idx[None, :, None, :]].reshape(len(part), m, m, t * t)
        windows -= windows.mean(axis=3, keepdims=True)
        norm = xp.sqrt((windows * windows).sum(axis=3))
        dot = (windows * templates[start : start + NCC_CHUNK, None, None, :]).sum(axis=3)
        out[start : start + NCC_CHUNK] = dot / xp.maximum(norm, 1e-6)
    return out


def parabola_peak(left: Any, centre: Any, right: Any) -> Any:
    """Offsets (-0.5 .. 0.5) of the vertices of the parabolas through three samples one apart, elementwise;
    0 where they do not open downwards."""
    xp = get_array_module(centre)
    den = left - 2.0 * centre + right
    safe = xp.where(den < 0, den, -1.0)
    return xp.where(den < 0, xp.clip(0.5 * (left - right) / safe, -0.5, 0.5), 0.0)
