"""align_frames' rule for a pair that pulls a neighbouring pair away from its own fit: it drops the weakest
pair touching the strained one, never one whose loss would cut a frame off, and nothing when no pair is strained."""

from __future__ import annotations

import numpy as np

from workers.algorithms.mosaic import TiePoints
from workers.records import PairRecord
from workers.stages.align_frames import _conflicting_pair


def _shift(dx: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _scene(bias_px: float) -> tuple[list[PairRecord], dict[tuple[int, int], TiePoints]]:
    """Frames 0-3 side by side, 100 px apart (frame k -> plane: + 100 k); pair (0, 2) a small overlap whose tie
    points are ``bias_px`` off; frame 3 joined by one weak pair only."""
    points = np.random.default_rng(4).uniform(0, 100, (40, 2))
    inliers = {(0, 1): 200, (1, 2): 180, (0, 2): 30, (2, 3): 10}
    pairs, ties = [], {}
    for (i, j), n in inliers.items():
        offset = np.array([100.0 * (i - j) + (bias_px if (i, j) == (0, 2) else 0.0), 0.0])
        ties[(i, j)] = TiePoints(points, points + offset)
        pairs.append(PairRecord(i, j, n, n, True, "H", _shift(offset[0]), n))
    return pairs, ties


def test_the_weakest_pair_that_keeps_every_frame_joined_is_dropped() -> None:
    pairs, ties = _scene(bias_px=3.0)
    # the adjustment met (0, 2) halfway... here all the way: frame 2 sits 3 px off, straining (1, 2)
    pulled = {0: np.eye(3), 1: _shift(100.0), 2: _shift(197.0), 3: _shift(297.0)}
    # (2, 3) is weaker still but frame 3 hangs on it alone
    assert _conflicting_pair(pairs, pulled, ties, floor_px=1.0) == {(0, 2)}


def test_nothing_is_dropped_when_every_pair_meets_its_own_fit() -> None:
    pairs, ties = _scene(bias_px=0.0)
    true = {k: _shift(100.0 * k) for k in range(4)}
    assert _conflicting_pair(pairs, true, ties, floor_px=1.0) == set()
    # a strain under the floor is noise, not a conflict
    assert _conflicting_pair(pairs, {**true, 2: _shift(199.5), 3: _shift(299.5)}, ties, floor_px=1.0) == set()
