"""Brute-force descriptor matching: L2 distances by a matrix product, two nearest neighbours, Lowe's
ratio test, optional mutual check and constraint masks, processed in row blocks.

Memory plan: descriptors themselves, (Na + Nb) * D * 4 bytes; per block of R rows, the distance
block (R * Nb * 4), its mask (R * Nb) and a temporary (R * Nb * 4): about 9 * R * Nb bytes. The block
height is chosen from ``memory_budget`` so 20k x 20k descriptors match in a few hundred MB.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from gpu_kernels.backend import get_array_module

MaskFn = Callable[[slice], Any]
"""Given the rows of a block (a slice of ``a``), the (rows, Nb) bool mask of allowed pairs."""

BYTES_PER_PAIR = 9


@dataclass(frozen=True)
class Matches:
    """``index_a``, ``index_b`` (M,) int64; ``distance`` (M,) float32 L2 distance of each match."""

    index_a: Any
    index_b: Any
    distance: Any


def block_rows(n_b: int, memory_budget: int) -> int:
    """Rows per block so that one block's working arrays fit ``memory_budget`` bytes."""
    return max(1, memory_budget // (BYTES_PER_PAIR * max(n_b, 1)))


def match_descriptors(
    desc_a: Any,
    desc_b: Any,
    ratio: float = 0.8,
    mutual: bool = True,
    allowed: MaskFn | None = None,
    memory_budget: int = 256 * 2**20,
) -> Matches:
    """Match rows of ``desc_a`` (Na, D) to rows of ``desc_b`` (Nb, D), float32.

    A row matches its nearest allowed neighbour when that is closer than ``ratio`` times the second
    nearest allowed one (a row with a single allowed candidate passes); with ``mutual``, also only when
    it is that neighbour's nearest allowed row. Ties go to the lower index.
    """
    xp = get_array_module(desc_a)
    a, b = desc_a.astype(xp.float32, copy=False), desc_b.astype(xp.float32, copy=False)
    n_a, n_b = len(a), len(b)
    if n_a == 0 or n_b == 0:
        empty = xp.zeros(0, xp.int64)
        return Matches(empty, empty, xp.zeros(0, xp.float32))
    norm_b = (b * b).sum(axis=1)
    best, d1, d2 = xp.empty(n_a, xp.int64), xp.empty(n_a, xp.float32), xp.empty(n_a, xp.float32)
    col_d, col_i = xp.full(n_b, xp.inf, xp.float32), xp.full(n_b, -1, xp.int64)
    step = block_rows(n_b, memory_budget)
    for start in range(0, n_a, step):
        rows = slice(start, min(start + step, n_a))
        dist = _squared_distances(a[rows], b, norm_b, allowed(rows) if allowed is not None else None)
        best[rows], d1[rows], d2[rows] = _two_smallest(dist)
        _update_column_minima(dist, start, col_d, col_i)
    keep = xp.isfinite(d1) & (d1 < (ratio * ratio) * d2)
    if mutual:
        keep &= col_i[best] == xp.arange(n_a)
    index_a = xp.nonzero(keep)[0]
    return Matches(index_a, best[index_a], xp.sqrt(d1[index_a]))


def _squared_distances(a: Any, b: Any, norm_b: Any, mask: Any | None) -> Any:
    xp = get_array_module(a)
    dist = (a * a).sum(axis=1)[:, None] + norm_b[None, :] - 2.0 * (a @ b.T)
    xp.maximum(dist, 0.0, out=dist)  # rounding can make a zero distance slightly negative
    if mask is not None:
        dist[~mask] = xp.inf
    return dist


def _two_smallest(dist: Any) -> tuple[Any, Any, Any]:
    xp = get_array_module(dist)
    rows = xp.arange(dist.shape[0])
    best = dist.argmin(axis=1)
    d1 = dist[rows, best]
    dist[rows, best] = xp.inf
    d2 = dist.min(axis=1) if dist.shape[1] > 1 else xp.full_like(d1, xp.inf)
    dist[rows, best] = d1  # restore: the column minima still need it
    return best, d1, d2


def _update_column_minima(dist: Any, start: int, col_d: Any, col_i: Any) -> None:
    xp = get_array_module(dist)
    block_best = dist.argmin(axis=0)
    block_d = dist[block_best, xp.arange(dist.shape[1])]
    better = block_d < col_d  # strict: an earlier block keeps a tie
    col_d[better] = block_d[better]
    col_i[better] = block_best[better] + start
