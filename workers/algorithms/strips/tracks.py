"""Tracks: tie points of several pairs joined where they observe the same point of a frame, so that a point
seen in frames i, i + 1 and i + 2 (strips with more than 50 % forward overlap) ties all three and the
adjustment is a block rather than a chain of pairs."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from workers.algorithms.strips.fine import PairTies


@dataclass(frozen=True)
class Tracks:
    """Observations grouped into tracks, sorted by track then frame, one observation per track and frame.

    Attributes
    ----------
    track : (M,) int64 track id, 0 .. n_tracks - 1.
    frame : (M,) int64 frame index.
    xy : (M, 2) float64 native pixel (x, y).
    conflicts : tracks dropped because they held two different points of one frame.
    """

    track: np.ndarray
    frame: np.ndarray
    xy: np.ndarray
    conflicts: int

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0

    def lengths(self) -> np.ndarray:
        """``(n_tracks,) int64``: frames each track is seen in."""
        return np.bincount(self.track, minlength=self.n_tracks)


class DisjointSet:
    """Union-find over ``n`` items (path halving, union by size), the textbook structure."""

    def __init__(self, n: int) -> None:
        self.parent = np.arange(n)
        self.size = np.ones(n, np.int64)

    def find(self, i: int) -> int:
        parent = self.parent
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def union(self, i: int, j: int) -> None:
        ri, rj = self.find(i), self.find(j)
        if ri == rj:
            return
        if self.size[ri] < self.size[rj]:
            ri, rj = rj, ri
        self.parent[rj] = ri
        self.size[ri] += self.size[rj]

    def labels(self) -> np.ndarray:
        """``(n,) int64`` root of every item."""
        return np.array([self.find(i) for i in range(len(self.parent))], np.int64)


def build_tracks(pairs: Sequence[PairTies], merge_px: float = 0.25) -> Tracks:
    """Join the tie points of ``pairs`` into tracks by union-find of their observations.

    Every tie point is two observations ``(frame, x, y)``, united; observations of one frame closer than
    ``merge_px`` are the same point and are united too (a point of a carried pair, :func:`carry_ties`, is
    exactly the point it was carried from). A track that ends up with two observations of one frame more
    than ``2 merge_px`` apart joined two different points by a false tie, and is dropped; observations of
    one frame within that are averaged.

    Parameters
    ----------
    pairs : tie points of frame pairs, each with its ``frames``.
    merge_px : distance, native px, below which two observations of one frame are one.

    Returns
    -------
    Tracks of at least two frames.
    """
    # Observations 2k and 2k + 1 are tie point k's in its two frames.
    frame = np.concatenate(
        [np.tile(np.asarray(p.frames, np.int64), len(p.points_a)) for p in pairs] or [np.zeros(0, np.int64)]
    )
    frame = frame.astype(np.int64)
    xy = np.concatenate(
        [np.stack([p.points_a, p.points_b], axis=1).reshape(-1, 2) for p in pairs] or [np.zeros((0, 2))]
    )
    sets = DisjointSet(len(frame))
    for k in range(0, len(frame), 2):
        sets.union(k, k + 1)
    for f in np.unique(frame):
        rows = np.flatnonzero(frame == f)
        for i, j in cKDTree(xy[rows]).query_pairs(merge_px):
            sets.union(int(rows[i]), int(rows[j]))
    return _collapse(sets.labels(), frame, xy, merge_px)


def _collapse(root: np.ndarray, frame: np.ndarray, xy: np.ndarray, merge_px: float) -> Tracks:
    """One observation per (track, frame), mean of the merged ones; drop conflicting and one-frame tracks."""
    if len(root) == 0:
        return Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), 0)
    keys, group = np.unique(np.column_stack([root, frame]), axis=0, return_inverse=True)
    group = group.ravel()
    count = np.bincount(group)
    mean = np.column_stack([np.bincount(group, xy[:, d]) for d in (0, 1)]) / count[:, None]
    spread = np.zeros(len(keys))
    np.maximum.at(spread, group, np.linalg.norm(xy - mean[group], axis=1))
    tracks, first = np.unique(keys[:, 0], return_inverse=True)
    first = first.ravel()
    bad = np.zeros(len(tracks), bool)
    bad[first[spread > 2 * merge_px]] = True
    frames_per_track = np.bincount(first, minlength=len(tracks))
    good = ~bad & (frames_per_track >= 2)
    renumber = np.cumsum(good) - 1
    keep = good[first]
    return Tracks(renumber[first[keep]], keys[keep, 1], mean[keep], int(bad.sum()))
