"""Least-squares refinement of a homography by its geometric (transfer) error."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from workers.algorithms.mosaic.alignment import apply_homography


def refine_homography(H: np.ndarray, points_a: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """``H`` refined to the least squares of the transfer error ``|H a - b|`` (Levenberg-Marquardt,
    ``scipy.optimize.least_squares``), parametrised in coordinates normalised per axis (Hartley 1997,
    anisotropic, as the overlap of a strip pair is far longer than wide) so the parameters are of one scale.

    Parameters
    ----------
    H : (3, 3) a px -> b px, the start.
    points_a, points_b : (N, 2) float pixel (x, y), N >= 4, matched rows.

    Returns
    -------
    (3, 3) float64, ``H[2, 2] = 1``.
    """
    T_a, T_b = _normaliser(points_a), _normaliser(points_b)
    back = np.linalg.inv(T_b)
    pa = apply_homography(T_a, points_a)
    start = T_b @ H @ np.linalg.inv(T_a)
    start = start / start[2, 2]

    def residual(p: np.ndarray) -> np.ndarray:  # in b px: the normalised axes have different units
        return (apply_homography(back @ np.append(p, 1.0).reshape(3, 3), pa) - points_b).ravel()

    fit = least_squares(residual, start.ravel()[:8], method="lm")
    refined = back @ np.append(fit.x, 1.0).reshape(3, 3) @ T_a
    return refined / refined[2, 2]


def _normaliser(points: np.ndarray) -> np.ndarray:
    """``(3, 3)``: points -> zero mean, unit standard deviation on each axis."""
    mean, std = points.mean(axis=0), points.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    return np.array([[1 / std[0], 0, -mean[0] / std[0]], [0, 1 / std[1], -mean[1] / std[1]], [0, 0, 1.0]])
