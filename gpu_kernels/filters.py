"""Separable filters and the Gaussian pyramid, array-module generic (NumPy or CuPy).

Borders follow OpenCV's default, BORDER_REFLECT_101 (``mode="mirror"`` in scipy/cupyx ndimage), so
results can be compared with OpenCV pixel for pixel.

Memory plan: a separable filter of an (H, W) float32 image needs the input, one intermediate and the
output: 12 bytes/px. ``gaussian_pyramid`` adds 1/3 of the base level for all smaller levels together.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from gpu_kernels.backend import get_array_module, ndimage_module

SOBEL_DERIVATIVE = (-1.0, 0.0, 1.0)
SOBEL_SMOOTH = (1.0, 2.0, 1.0)


def separable(image: Any, kernel_x: Any, kernel_y: Any) -> Any:
    """Correlate ``image`` (H, W) with ``kernel_y`` down the columns and ``kernel_x`` along the rows."""
    xp = get_array_module(image)
    nd = ndimage_module(xp)
    kx = xp.asarray(kernel_x, dtype=image.dtype)
    ky = xp.asarray(kernel_y, dtype=image.dtype)
    return nd.correlate1d(nd.correlate1d(image, ky, axis=0, mode="mirror"), kx, axis=1, mode="mirror")


def gaussian_kernel(sigma: float, radius: int | None = None) -> np.ndarray:
    """Normalised 1-D Gaussian, radius ``ceil(3 sigma)`` by default (float64, host)."""
    if sigma <= 0:
        raise ValueError("sigma must be positive")
    r = int(math.ceil(3.0 * sigma)) if radius is None else radius
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def gaussian_blur(image: Any, sigma: float) -> Any:
    """Separable Gaussian blur of an (H, W) float image."""
    k = gaussian_kernel(sigma)
    return separable(image, k, k)


def sobel(image: Any) -> tuple[Any, Any]:
    """3x3 Sobel derivatives (d/dx, d/dy) of an (H, W) float image, unscaled as ``cv2.Sobel``."""
    return separable(image, SOBEL_DERIVATIVE, SOBEL_SMOOTH), separable(image, SOBEL_SMOOTH, SOBEL_DERIVATIVE)


def gaussian_pyramid(image: Any, levels: int, sigma: float = 1.0) -> list[Any]:
    """``levels`` images, each blurred and decimated by 2 from the one before (level 0 = ``image``)."""
    if levels < 1:
        raise ValueError("levels must be >= 1")
    out = [image]
    for _ in range(levels - 1):
        if min(out[-1].shape[:2]) < 2:
            break
        out.append(gaussian_blur(out[-1], sigma)[::2, ::2])
    return out
