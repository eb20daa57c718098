"""Gain steps between the CCD sub-images of a strip camera's frame, measured in the frames themselves.

An aerial strip frame is joined, across its width, from ``n`` sub-images of equal width, each read out with
gain of its own: the ground is continuous across a join, the brightness steps. The steps are the camera's, the
same in every frame, and consecutive frames of a strip lie one above the other, so their overlaps compare a
sub-image with itself and cancel the steps: they cannot be found from the overlaps. They are found instead in
each frame's own rows, at native resolution, where the ground is continuous from one pixel to the next: each
side's two columns nearest the join extrapolate the other side's first column linearly, and the log brightness
there differs from the extrapolation by the log of the step (the ground's own curvature averages out over the
rows and frames). The steps chained from the left give each sub-image's gain.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

DARK = 8.0  # levels: darker pixels carry only noise in log space


def segment_of_columns(width: int, segments: int) -> np.ndarray:
    """(width,) int: the sub-image of each column of a frame (or a copy of it) ``width`` px wide joined from
    ``segments`` sub-images of equal width: the one its centre falls in."""
    return np.minimum(((np.arange(width) + 0.5) * segments / width).astype(int), segments - 1)


def join_columns(native_width: int, segments: int) -> np.ndarray:
    """(segments - 1,) int: the first native column of sub-images 1, 2, ..."""
    return np.ceil(np.arange(1, segments) * native_width / segments - 0.5).astype(int)


def ccd_gains(columns_of: Callable[[int, int, int], np.ndarray], frames: list[int], native_width: int,
              segments: int) -> np.ndarray:  # fmt: skip
    """(segments,) float64 gain of each sub-image (geometric mean 1) of frames ``native_width`` px wide.

    ``columns_of(k, c0, c1)`` gives frame ``k``'s native columns ``c0:c1``, (H, c1 - c0, 3) uint8, all rows.
    Per join, the median over every row of every frame of
    ``(3 L[J] - 3 L[J-1] - L[J+1] + L[J-2]) / 2``, ``L`` the log brightness and ``J`` the join's first column:
    the mean of the step measured from each side's linear extrapolation.
    """
    steps = np.zeros(segments - 1)
    for j, first in enumerate(join_columns(native_width, segments)):
        if first < 2 or first + 2 > native_width:
            continue  # a sub-image narrower than 2 px: nothing to extrapolate from
        values = [_row_steps(columns_of(k, first - 2, first + 2)) for k in frames]
        found = np.concatenate(values) if values else np.zeros(0)
        steps[j] = float(np.median(found)) if len(found) else 0.0
    log_gains = np.concatenate([[0.0], np.cumsum(steps)])
    return np.exp(log_gains - log_gains.mean())


def _row_steps(window: np.ndarray) -> np.ndarray:
    """(n,) float64 log step of each bright row of a (H, 4, 3) window centred on a join."""
    grey = window.astype(np.float64).mean(axis=2)
    bright = (grey > DARK).all(axis=1)
    a, b, c, d = (np.log(grey[bright, i]) for i in range(4))
    return (3 * c - 3 * b - d + a) / 2


def column_brightness(width: int, gains: np.ndarray) -> np.ndarray:
    """(width,) float32 factor that undoes ``gains`` (one per sub-image) in each column of a ``width`` px copy."""
    return (1.0 / gains[segment_of_columns(width, len(gains))]).astype(np.float32)
