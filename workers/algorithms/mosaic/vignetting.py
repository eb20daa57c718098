"""Radial brightness fall-off (vignetting) of the camera, estimated from the frames' overlaps.

A frame's pixel is ``I = g_k V(rho) L``: the ground's radiance ``L``, the frame's gain ``g_k`` and the lens'
fall-off ``V(rho) = exp(c1 rho^2 + c2 rho^4)``, ``rho`` the distance from the frame's centre over its
half-diagonal. Where frames i and j see the same ground, ``log I_i - log I_j`` is linear in ``c1``, ``c2`` and
the log gains, so one least-squares solve over overlap pixels finds the fall-off (one camera: every frame
shares it) without any flat-field image (Goldman & Chen 2005, with a polynomial in rho^2).
"""

from __future__ import annotations

import numpy as np

MAX_SAMPLES_PER_PAIR = 4000  # overlap pixels used per frame pair (evenly spread)
MIN_SAMPLES = 500  # fewer overlap pixels in all: no estimate (the fall-off stays 0)
GAIN_PRIOR = 0.1  # weight of log g_k = 0 per sample, fixing the gauge (a common gain is not vignetting)
DARK = 8.0  # pixels darker than this (levels) carry only noise in log space


def radius2(map_x: np.ndarray, map_y: np.ndarray, width: int, height: int) -> np.ndarray:
    """rho^2 of frame pixel positions (OpenCV centres) in a ``width`` x ``height`` frame: 0 at its centre, 1 at
    its corners."""
    cx, cy = (width - 1) / 2, (height - 1) / 2
    return (((map_x - cx) ** 2 + (map_y - cy) ** 2) / (cx * cx + cy * cy)).astype(np.float32)


def falloff(rho2: np.ndarray, vignette: tuple[float, float]) -> np.ndarray:
    """V(rho) of the model, from rho^2 (float32, same shape)."""
    c1, c2 = vignette
    return np.exp(np.float32(c1) * rho2 + np.float32(c2) * rho2 * rho2).astype(np.float32)


def fit_vignetting(images: list[np.ndarray], masks: list[np.ndarray], rho2: list[np.ndarray]) -> tuple[float, float]:
    """(c1, c2) of the fall-off from frames rendered on one grid: (H, W, 3) float32 images, (H, W) bool masks
    where each frame has data, and (H, W) float32 rho^2 of each pixel in that frame. (0, 0) without enough
    overlap to tell."""
    n = len(images)
    rows, rhs = [], []
    luminance = [np.log(np.maximum(im.mean(axis=2), 1.0)) for im in images]
    bright = [im.mean(axis=2) > DARK for im in images]
    for i in range(n):
        for j in range(i + 1, n):
            both = np.flatnonzero((masks[i] & masks[j] & bright[i] & bright[j]).ravel())
            if len(both) < 50:
                continue
            take = both[np.linspace(0, len(both) - 1, min(MAX_SAMPLES_PER_PAIR, len(both))).astype(int)]
            ri, rj = rho2[i].ravel()[take].astype(np.float64), rho2[j].ravel()[take].astype(np.float64)
            block = np.zeros((len(take), 2 + n))
            block[:, 0], block[:, 1] = ri - rj, ri * ri - rj * rj
            block[:, 2 + i], block[:, 2 + j] = 1.0, -1.0
            rows.append(block)
            rhs.append(luminance[i].ravel()[take] - luminance[j].ravel()[take])
    if not rows or sum(len(r) for r in rows) < MIN_SAMPLES:
        return 0.0, 0.0
    A, b = np.vstack(rows), np.concatenate(rhs)
    prior = np.zeros((n, 2 + n))
    prior[np.arange(n), 2 + np.arange(n)] = GAIN_PRIOR * np.sqrt(len(b) / n)
    A, b = np.vstack([A, prior]), np.concatenate([b, np.zeros(n)])
    # a robust pass: residuals beyond 3 MADs (moving things, parallax, misregistration) are dropped once
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    r = A @ x - b
    mad = np.median(np.abs(r[:-n])) * 1.4826 + 1e-9
    keep = np.concatenate([np.abs(r[:-n]) < 3 * mad, np.ones(n, bool)])
    x = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
    # a lens darkens towards its corners: a fit that brightens them has found the sun's hot spot or the
    # ground's relief, not the lens (the Brighton strip's frames give c1 = +0.13), and is not applied
    c1, c2 = float(np.clip(x[0], -2.0, 0.0)), float(np.clip(x[1], -2.0, 2.0))
    if c1 == 0.0 or c1 + c2 > 0.0:
        return 0.0, 0.0
    return c1, c2
