"""Which frame pairs to match: flight order and GPS neighbours, or all pairs for small flights."""

from __future__ import annotations

import numpy as np

EARTH_RADIUS_M = 6_371_000.0


def local_metres(latlon: np.ndarray) -> np.ndarray:
    """(N, 2) lat, lon degrees -> (N, 2) east, north metres around their mean (equirectangular;
    good to well under 1% over a flight's extent, which is all pair selection needs)."""
    lat0 = np.radians(latlon[:, 0].mean())
    d = np.radians(latlon - latlon.mean(axis=0))
    return np.column_stack([d[:, 1] * np.cos(lat0), d[:, 0]]) * EARTH_RADIUS_M


def candidate_pairs(
    n: int, positions: np.ndarray | None, max_gap: int, neighbours: int, exhaustive_max: int
) -> list[tuple[int, int]]:
    """Frame pairs (i < j) worth matching.

    Parameters
    ----------
    n : number of frames, in flight order.
    positions : (n, 2) float metres, or None without GPS.
    max_gap : pairs up to this far apart in flight order (used with GPS, or for large flights).
    neighbours : with GPS, also each frame's this many nearest frames by position (crossing lines).
    exhaustive_max : without GPS, every pair when n is at most this.
    """
    if positions is None and n <= exhaustive_max:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    pairs = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + max_gap + 1))}
    if positions is not None and neighbours > 0:
        dist = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=2)
        np.fill_diagonal(dist, np.inf)
        for i in range(n):
            for j in np.argsort(dist[i])[: min(neighbours, n - 1)]:  # the frame itself sorts last (inf)
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)
