"""Physical-constraint masks for matching, as in the source work: which (a, b) pairs may match at
all. Each returns a (len(a), len(b)) bool array; combine them with ``&`` and pass the rows of a block.

Memory plan: 1 byte per pair; the matchers build them block by block, never whole.
"""

from __future__ import annotations

from typing import Any

from gpu_kernels.backend import get_array_module


def same_value(values_a: Any, values_b: Any) -> Any:
    """Pairs with equal labels: the same octave, or the same DoG extremum sign."""
    return values_a[:, None] == values_b[None, :]


def shift_window(xy_a: Any, xy_b: Any, shift: tuple[float, float], radius: float) -> Any:
    """Pairs where ``b`` lies within ``radius`` px of ``a + shift`` (an expected shift from GPS or a
    coarse transform). ``xy_*``: (N, 2) pixel (x, y)."""
    xp = get_array_module(xy_a)
    predicted = xy_a + xp.asarray(shift, dtype=xy_a.dtype)
    d2 = ((predicted[:, None, :] - xy_b[None, :, :]) ** 2).sum(axis=2)
    return d2 <= radius * radius


def angle_window(angle_a: Any, angle_b: Any, max_difference_deg: float) -> Any:
    """Pairs whose keypoint orientations differ by at most ``max_difference_deg`` (the no-rotation
    assumption between frames of one flight line)."""
    xp = get_array_module(angle_a)
    diff = xp.abs(angle_a[:, None] - angle_b[None, :]) % 360.0
    return xp.minimum(diff, 360.0 - diff) <= max_difference_deg
