"""Reduced copies of a strip frame, one per pyramid level (level ``k``: every side divided by ``2**k``),
and the maps between their pixels and the frame's native pixels."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class FramePyramid:
    """Reduced copies of one frame.

    Attributes
    ----------
    images : tuple of (H_k, W_k) uint8, one channel
        ``images[k - base_level]`` is level ``k``; level ``base_level`` is the finest held.
    base_level : int
        The pyramid level of ``images[0]``.
    full_size : tuple of int
        ``(width, height)`` of the frame at native resolution.
    """

    images: tuple[np.ndarray, ...]
    base_level: int
    full_size: tuple[int, int]

    @property
    def levels(self) -> range:
        """The levels held, finest first."""
        return range(self.base_level, self.base_level + len(self.images))

    def image(self, level: int) -> np.ndarray:
        """``(H_k, W_k) uint8`` copy at ``level``; ValueError for a level not held."""
        if level not in self.levels:
            raise ValueError(f"level {level} not held (levels {self.levels.start}..{self.levels.stop - 1})")
        return self.images[level - self.base_level]

    def to_level(self, level: int) -> np.ndarray:
        """``(3, 3) float64``: native px -> ``level`` px.

        Pixel centres sit at integers on both (OpenCV's convention), so ``x_k = (x + 0.5) f - 0.5`` with ``f``
        the ratio of the sides (the exact one: reduced sides are rounded).
        """
        h, w = self.image(level).shape[:2]
        fx, fy = w / self.full_size[0], h / self.full_size[1]
        return np.array([[fx, 0.0, 0.5 * fx - 0.5], [0.0, fy, 0.5 * fy - 0.5], [0.0, 0.0, 1.0]])


def build_pyramid(base: np.ndarray, full_size: tuple[int, int], base_level: int, n_levels: int) -> FramePyramid:
    """A :class:`FramePyramid` of ``n_levels`` levels from the ``(H, W) uint8`` copy at ``base_level``.

    Each coarser level is the 2 x 2 area average of the one before (``cv2.INTER_AREA``), so one reduced
    decode of the frame serves every level.
    """
    if base.ndim != 2:
        raise ValueError(f"a pyramid is built from one channel, got shape {base.shape}")
    if n_levels < 1 or base_level < 0:
        raise ValueError("n_levels must be >= 1 and base_level >= 0")
    images = [np.ascontiguousarray(base)]
    for _ in range(n_levels - 1):
        h, w = images[-1].shape
        if min(h, w) < 4:
            break
        size = (max(1, round(w / 2)), max(1, round(h / 2)))
        images.append(cv2.resize(images[-1], size, interpolation=cv2.INTER_AREA))
    return FramePyramid(tuple(images), base_level, full_size)


def coarsest_level(frame_size: tuple[int, int], min_short_px: int = 48) -> int:
    """The coarsest level whose copy keeps at least ``min_short_px`` px across the frame's short side
    (level 5 for a 75000 x 1800 frame: 2344 x 56 px); 0 when the frame itself is that small."""
    short = min(frame_size)
    level = 0
    while short / 2 ** (level + 1) >= min_short_px:
        level += 1
    return level
