"""Grey levels for matching: a pair of photos brought to 8 bits by one stretch, so they stay comparable."""

from __future__ import annotations

import cv2
import numpy as np


def to_8bit_pair(
    left: np.ndarray, right: np.ndarray, percentiles: tuple[float, float] = (0.5, 99.5)
) -> tuple[np.ndarray, np.ndarray]:
    """Both photos as uint8 (shape kept): 8-bit photos unchanged, deeper ones (an 11-bit satellite product in
    16-bit samples) stretched linearly from the ``percentiles`` of both together to 0-255."""
    if left.dtype == np.uint8 and right.dtype == np.uint8:
        return left, right
    sample = np.concatenate([left[::4, ::4].ravel(), right[::4, ::4].ravel()]).astype(np.float64)
    lo, hi = np.percentile(sample, percentiles)
    scale = 255.0 / max(hi - lo, 1e-9)
    return tuple(  # type: ignore[return-value]
        np.clip(np.rint((image.astype(np.float64) - lo) * scale), 0, 255).astype(np.uint8) for image in (left, right)
    )


def grey8(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey of an (H, W) or (H, W, 3) BGR uint8 photo."""
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def same_channels(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both colour (BGR) only when both are: a grey photo with a colour one is matched in grey."""
    if left.ndim == right.ndim:
        return left, right
    return grey8(left), grey8(right)
