"""Gain steps between the CCD sub-images of a strip camera's frame, measured in the frames themselves.

An aerial strip frame is joined, across its width, from ``n`` sub-images of equal width, each read out with
gain of its own: the ground is continuous across a join, the brightness steps. The steps are the camera's, the
same in every frame, and consecutive frames of a strip lie one above the other, so their overlaps compare a
sub-image with itself and cancel the steps: they cannot be found from the overlaps. They are found instead in
each frame's own rows, at native resolution, where the ground is continuous from one pixel to the next: each
side's two columns nearest the join extrapolate the other side's first column linearly, and the log brightness
there differs from the extrapolation by the log of the step (the ground's own curvature averages out over the
rows and frames). The steps chained from the left give each sub-image's gain.

In a JPEG-coded frame a join that falls inside an 8 px DCT block is smeared over the block by the quantised
high frequencies, and the extrapolation finds about 0.55 of its step there. Such a join is measured instead
between the two columns just outside its block, which keeps the block's low frequencies: unbiased, since the
ground is the same on average either side, but with more spread, so it needs the rows of many frames. On
synthetic strips (quality 90, 8000 px wide, 600 rows) the steps inside blocks were found with a mean error of
0.15-0.21 of their size from 40 frames, against 0.47 by extrapolation; from 6 frames both about 0.5.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor

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
              segments: int, blocks: Mapping[int, int] | None = None, threads: int = 1) -> np.ndarray:  # fmt: skip
    """(segments,) float64 gain of each sub-image (geometric mean 1) of frames ``native_width`` px wide.

    ``columns_of(k, c0, c1)`` gives frame ``k``'s native columns ``c0:c1``, (H, c1 - c0, 3) uint8, all rows.
    ``blocks``: frame -> the width of the blocks its codec transforms (8 for JPEG; missing or 1: none). Per
    join, the median over every row of every frame of ``(3 L[J] - 3 L[J-1] - L[J+1] + L[J-2]) / 2``, ``L`` the
    log brightness and ``J`` the join's first column (the mean of the step measured from each side's linear
    extrapolation); where ``J`` falls inside a block ``[b, b + block)``, ``L[b + block] - L[b - 1]``. Frame by
    frame, every join of one before the next (a frame read by window is opened once: join by join, each of 40
    strip frames had been opened 31 times, 12.4 s of compose's plan), on ``threads`` threads.
    """
    joins = join_columns(native_width, segments)

    def of_frame(k: int) -> list[np.ndarray]:
        return [_steps_at(columns_of, k, first, (blocks or {}).get(k, 1), native_width) for first in joins]

    with ThreadPoolExecutor(max(1, threads)) as pool:
        per_frame = list(pool.map(of_frame, frames))
    steps = np.zeros(segments - 1)
    for j in range(len(joins)):
        values = np.concatenate([found[j] for found in per_frame]) if per_frame else np.zeros(0)
        steps[j] = float(np.median(values)) if len(values) else 0.0
    log_gains = np.concatenate([[0.0], np.cumsum(steps)])
    return np.exp(log_gains - log_gains.mean())


def _steps_at(columns_of: Callable[[int, int, int], np.ndarray], k: int, first: int, block: int,
              native_width: int) -> np.ndarray:  # fmt: skip
    """(n,) float64 log step of each bright row of frame ``k`` at the join whose first column is ``first``."""
    start = first // block * block
    if start == first:  # on a block edge, or no blocks: extrapolate each side across the join
        if first < 2 or first + 2 > native_width:
            return np.zeros(0)  # a sub-image narrower than 2 px: nothing to extrapolate from
        return _row_steps(columns_of(k, first - 2, first + 2))
    if start < 1 or start + block >= native_width:
        return np.zeros(0)  # the block holding the join touches the frame's edge
    window = columns_of(k, start - 1, start + block + 1)
    grey = window[:, [0, -1]].astype(np.float64).mean(axis=2)
    bright = (grey > DARK).all(axis=1)
    return np.log(grey[bright, 1]) - np.log(grey[bright, 0])


def _row_steps(window: np.ndarray) -> np.ndarray:
    """(n,) float64 log step of each bright row of a (H, 4, 3) window centred on a join."""
    grey = window.astype(np.float64).mean(axis=2)
    bright = (grey > DARK).all(axis=1)
    a, b, c, d = (np.log(grey[bright, i]) for i in range(4))
    return (3 * c - 3 * b - d + a) / 2


def column_brightness(width: int, gains: np.ndarray) -> np.ndarray:
    """(width,) float32 factor that undoes ``gains`` (one per sub-image) in each column of a ``width`` px copy."""
    return (1.0 / gains[segment_of_columns(width, len(gains))]).astype(np.float32)
