"""Frames as the strip algorithms read them: a pyramid from one reduced decode, native windows on demand.

The one module of this package that opens files, a thin adapter over ``workers.photo_io`` (tiled or striped
TIFF read block by block, never whole), so the algorithms themselves take arrays or anything sliced like one
(:class:`Windowed`) and stay testable on arrays.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Protocol

import numpy as np

from workers.algorithms.strips.pyramid import FramePyramid, build_pyramid
from workers.photo_io import WindowReader, read_reduced

GREEN = 1  # the channel used (BGR index): the source work runs on one channel, green is the sharpest


class Windowed(Protocol):
    """A frame read by window: ``frame[r0:r1, c0:c1]`` -> ``(h, w)`` or ``(h, w, C)`` uint8, and its
    ``shape`` ``(H, W[, C])``. A NumPy array is one; so is ``workers.photo_io.WindowReader``."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray: ...


def read_pyramid(path: str | Path, base_level: int, n_levels: int, channel: int = GREEN) -> FramePyramid:
    """The pyramid of a frame file from one reduced decode at ``base_level`` (``read_reduced``).

    Raises ValueError when the file cannot be decoded.
    """
    height, width = WindowReader(path).shape[:2]
    reduced = read_reduced(path, max(1, math.ceil(max(width, height) / 2**base_level)))
    if reduced is None:
        raise ValueError(f"{Path(path).name} cannot be decoded")
    image, size = reduced
    return build_pyramid(np.ascontiguousarray(image[..., channel]), size, base_level, n_levels)


def open_windows(path: str | Path) -> Windowed:
    """The frame file read by window (``workers.photo_io.WindowReader``)."""
    return WindowReader(path)
