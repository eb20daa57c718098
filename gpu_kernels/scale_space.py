"""SIFT scale space (Lowe 2004, sec. 3; the layout of OpenCV's SIFT), built one octave at a time.

Octave ``o`` has pixels ``2**o`` input pixels apart (``o = -1``: the input upsampled twice, as Lowe
recommends for small features; ``+1``: every second pixel, for huge frames). It holds ``levels + 3``
Gaussian images with blur ``sigma0 * 2**(s / levels)`` in its own pixels, and their ``levels + 2``
differences. The next octave starts from the Gaussian image of twice the base blur, decimated.

Memory plan: an octave of an (H, W) level is (2 levels + 5) float32 images: 44 B/px for levels = 3.
Built as a generator, at most one octave (and the next one's base) is alive, so the peak is that of
the first octave: 176 B per input pixel with ``first_octave = -1``, 44 with 0 and 11 with +1.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from gpu_kernels.backend import get_array_module, ndimage_module
from gpu_kernels.filters import gaussian_blur


@dataclass(frozen=True)
class Octave:
    """One octave: ``gaussians`` (levels + 3, H, W) and ``dog`` (levels + 2, H, W), float32."""

    index: int
    gaussians: Any
    dog: Any

    @property
    def spacing(self) -> float:
        """Input pixels between two pixels of this octave."""
        return 2.0**self.index


def level_sigmas(levels: int, sigma0: float) -> list[float]:
    """Blur of each Gaussian image of an octave, in the octave's own pixels."""
    return [sigma0 * 2.0 ** (s / levels) for s in range(levels + 3)]


def octave_count(height: int, width: int, first_octave: int, min_size: int = 8) -> int:
    """Octaves until the smaller side falls under ``min_size`` pixels."""
    return max(1, int(math.floor(math.log2(min(height, width) / min_size))) - first_octave + 1)


def scale_space(
    image: Any,
    first_octave: int = -1,
    octaves: int | None = None,
    levels: int = 3,
    sigma0: float = 1.6,
    assumed_blur: float = 0.5,
) -> Iterator[Octave]:
    """Yield the octaves of an (H, W) image (uint8 or float), from ``first_octave`` upwards.

    ``assumed_blur`` is the blur the camera already gave the input, in input pixels.
    """
    if first_octave not in (-1, 0, 1):
        raise ValueError("first_octave must be -1, 0 or +1")
    if levels < 1 or sigma0 <= 0:
        raise ValueError("levels must be >= 1 and sigma0 > 0")
    xp = get_array_module(image)
    img = image.astype(xp.float32) / (255.0 if image.dtype == xp.uint8 else 1.0)
    base = _resample(img, first_octave)
    present = assumed_blur * 2.0 ** (-first_octave)  # the input's blur in the first octave's pixels
    base = gaussian_blur(base, math.sqrt(max(sigma0**2 - present**2, 0.01)))
    height, width = img.shape[:2]
    n = octave_count(height, width, first_octave) if octaves is None else octaves
    sigmas = level_sigmas(levels, sigma0)
    for o in range(first_octave, first_octave + n):
        gaussians = [base]
        for s in range(1, levels + 3):
            gaussians.append(gaussian_blur(gaussians[-1], math.sqrt(sigmas[s] ** 2 - sigmas[s - 1] ** 2)))
        stack = xp.stack(gaussians)
        yield Octave(o, stack, stack[1:] - stack[:-1])
        base = stack[levels][::2, ::2]  # blur 2 sigma0 here is sigma0 in the next octave's pixels
        if min(base.shape) < 2:
            return


def _resample(img: Any, first_octave: int) -> Any:
    if first_octave == 0:
        return img
    if first_octave == 1:
        return img[::2, ::2]
    # Twice the size, linear interpolation on pixel centres (as cv2.resize INTER_LINEAR).
    xp = get_array_module(img)
    h, w = img.shape
    ys = (xp.arange(2 * h, dtype=xp.float32) + 0.5) / 2 - 0.5
    xs = (xp.arange(2 * w, dtype=xp.float32) + 0.5) / 2 - 0.5
    grid = xp.stack(xp.meshgrid(ys, xs, indexing="ij"))
    return ndimage_module(xp).map_coordinates(img, grid, order=1, mode="nearest").astype(xp.float32)
