"""RANSAC for the epipole model of a pure translation between two views (the one model of the
source work that OpenCV lacks): a point, its match and the epipole are collinear,
``(p1 x p2) . e = 0`` in homogeneous coordinates.

The minimal sample is 2 matches (the epipole is the intersection of their two lines). All hypotheses
are drawn at once and scored in one (hypotheses x matches) array operation, which is what makes it
fast on a GPU; the best is refined by least squares over its inliers. Coordinates are normalised
first (Hartley 1997), and an epipole at infinity (sideways motion) is handled like any other.

Memory plan: 3 floats per match and hypothesis; 1000 hypotheses x 100k matches = 1.2 GB in float32,
so hypotheses are scored in chunks of ``chunk`` rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gpu_kernels.backend import get_array_module, to_host


@dataclass(frozen=True)
class Epipole:
    """``e`` (3,) homogeneous pixel coordinates (unit norm; e[2] = 0 at infinity), ``inliers`` (N,) bool."""

    e: Any
    inliers: Any


def _normaliser(points: np.ndarray) -> np.ndarray:
    centre = points.mean(axis=0)
    scale = np.sqrt(2.0) / max(float(np.linalg.norm(points - centre, axis=1).mean()), 1e-12)
    return np.array([[scale, 0, -scale * centre[0]], [0, scale, -scale * centre[1]], [0, 0, 1.0]])


def epipole_residuals(e: Any, p1: Any, p2: Any) -> Any:
    """Distance of each ``p2`` to the line through ``p1`` and ``e`` (and vice versa), averaged.

    ``e`` (K, 3) hypotheses, ``p1``, ``p2`` (N, 3) homogeneous with last coordinate 1; returns (K, N).
    """
    xp = get_array_module(p1)
    l2 = xp.cross(e[:, None, :], p1[None, :, :])  # line through e and p1, in which p2 should lie
    l1 = xp.cross(e[:, None, :], p2[None, :, :])
    d2 = xp.abs((l2 * p2[None]).sum(axis=2)) / xp.maximum(xp.hypot(l2[..., 0], l2[..., 1]), 1e-12)
    d1 = xp.abs((l1 * p1[None]).sum(axis=2)) / xp.maximum(xp.hypot(l1[..., 0], l1[..., 1]), 1e-12)
    return 0.5 * (d1 + d2)


def ransac_epipole(
    p1: Any, p2: Any, threshold_px: float = 1.0, hypotheses: int = 500, seed: int = 0, chunk: int = 256
) -> Epipole:
    """Robust epipole of matches ``p1`` -> ``p2``, (N, 2) pixel (x, y), for a purely translating camera.

    ``threshold_px`` is the inlier distance to the epipolar line, in pixels.
    """
    xp = get_array_module(p1)
    n = len(p1)
    if n < 2:
        return Epipole(xp.asarray([0.0, 0.0, 1.0]), xp.zeros(n, bool))
    T = _normaliser(np.concatenate([to_host(p1), to_host(p2)]).astype(np.float64))
    T_dev = xp.asarray(T)
    h1, h2 = _homogeneous(p1) @ T_dev.T, _homogeneous(p2) @ T_dev.T
    threshold = threshold_px * T[0, 0]  # in normalised units
    lines = xp.cross(h1, h2)
    samples = xp.asarray(np.random.default_rng(seed).choice(n, size=(hypotheses, 2)))  # host RNG: same on any device
    candidates = xp.cross(lines[samples[:, 0]], lines[samples[:, 1]])
    candidates /= xp.maximum(xp.linalg.norm(candidates, axis=1, keepdims=True), 1e-12)
    counts = xp.concatenate(
        [
            (epipole_residuals(candidates[k : k + chunk], h1, h2) < threshold).sum(axis=1)
            for k in range(0, hypotheses, chunk)
        ]
    )
    e = candidates[int(counts.argmax())]
    for _ in range(3):  # refine on the inliers, then re-select them
        inliers = epipole_residuals(e[None], h1, h2)[0] < threshold
        if int(inliers.sum()) < 2:
            break
        e = _least_squares(lines[inliers])
    inliers = epipole_residuals(e[None], h1, h2)[0] < threshold
    e_pixels = xp.linalg.solve(T_dev, e)
    return Epipole(e_pixels / xp.linalg.norm(e_pixels), inliers)


def _least_squares(lines: Any) -> Any:
    """Unit ``e`` minimising sum((l . e)^2) over lines scaled to unit normal: the smallest right
    singular vector."""
    xp = get_array_module(lines)
    unit = lines / xp.maximum(xp.hypot(lines[:, 0], lines[:, 1])[:, None], 1e-12)
    return xp.linalg.svd(unit, full_matrices=False)[2][-1]


def _homogeneous(points: Any) -> Any:
    xp = get_array_module(points)
    pts = points.astype(xp.float64)
    return xp.concatenate([pts, xp.ones((len(pts), 1))], axis=1)
