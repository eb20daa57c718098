"""Window descriptors and normalised cross-correlation matching (the source work's Harris + NCC path).

A descriptor is the image window around a point, mean-centred and scaled to unit length, so the NCC
of two windows is the dot product of their descriptors and the whole score matrix one matrix product.

Memory plan: (N, (2h+1)^2) float32 descriptors, 4 (2h+1)^2 bytes per point (1.7 kB for h = 10); the
score matrix Na * Nb * 4 bytes plus its mask (1 byte per pair).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gpu_kernels.backend import get_array_module


@dataclass(frozen=True)
class NccMatches:
    """``index_a``, ``index_b`` (M,) int64 and their NCC ``score`` (M,) float32 in [-1, 1]."""

    index_a: Any
    index_b: Any
    score: Any


def window_descriptors(image: Any, xy: Any, half: int) -> tuple[Any, Any]:
    """Descriptors of the (2 half + 1)^2 windows centred on integer points ``xy`` (N, 2) (x, y).

    Returns
    -------
    descriptors : (M, (2 half + 1)^2) float32, mean 0, norm 1 (flat windows: all zeros)
    kept : (M,) int64 indices into ``xy`` of the points whose window lies inside the image
    """
    xp = get_array_module(image)
    h, w = image.shape[:2]
    x, y = xy[:, 0].astype(xp.int64), xy[:, 1].astype(xp.int64)
    kept = xp.nonzero((x >= half) & (y >= half) & (x < w - half) & (y < h - half))[0]
    offsets = xp.arange(-half, half + 1)
    rows = y[kept][:, None, None] + offsets[None, :, None]
    cols = x[kept][:, None, None] + offsets[None, None, :]
    windows = image[rows, cols].reshape(len(kept), -1).astype(xp.float32)
    windows -= windows.mean(axis=1, keepdims=True)
    norm = xp.sqrt((windows * windows).sum(axis=1, keepdims=True))
    return windows / xp.maximum(norm, 1e-12), kept


def match_ncc(
    desc_a: Any, desc_b: Any, threshold: float = 0.8, mutual: bool = True, allowed: Any | None = None
) -> NccMatches:
    """Best NCC partner of every row of ``desc_a`` among the allowed columns of ``desc_b``.

    ``allowed`` (Na, Nb) bool is applied before the argmax, so a forbidden pair can never win. A match
    needs a score above ``threshold`` and, with ``mutual``, to be its partner's best row too.
    """
    xp = get_array_module(desc_a)
    if len(desc_a) == 0 or len(desc_b) == 0:
        empty = xp.zeros(0, xp.int64)
        return NccMatches(empty, empty, xp.zeros(0, xp.float32))
    score = desc_a @ desc_b.T
    if allowed is not None:
        score[~allowed] = -xp.inf
    best = score.argmax(axis=1)
    best_score = score[xp.arange(len(desc_a)), best]
    keep = best_score > threshold
    if mutual:
        keep &= score.argmax(axis=0)[best] == xp.arange(len(desc_a))
    index_a = xp.nonzero(keep)[0]
    return NccMatches(index_a, best[index_a], best_score[index_a])
