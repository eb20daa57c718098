"""bench/strip_geometry.py's measure: corner errors after one similarity, and the share a frame scale explains."""

from __future__ import annotations

import numpy as np

from bench.strip_geometry import corner_errors

SIZE = (20_000, 480)


def _frame(dx: float, scale: float = 1.0, angle: float = 0.0) -> np.ndarray:
    """A frame's px -> ground: scaled and turned about its centre, then ``dx`` px along x."""
    c, s = scale * np.cos(angle), scale * np.sin(angle)
    centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
    move = np.eye(3)
    move[:2, :2] = [[c, -s], [s, c]]
    move[:2, 2] = centre - move[:2, :2] @ centre + [dx, 0.0]
    return move


def test_a_frame_scaled_about_its_centre_is_all_scale() -> None:
    truth = [_frame(k * 30_000.0) for k in range(5)]
    found = {k: truth[k] for k in range(5)}
    found[2] = _frame(60_000.0, scale=1.0 + 1e-4)  # the middle frame 1e-4 too wide and tall
    errors, share = corner_errors(found, truth, SIZE)
    assert errors.shape == (5, 4, 2)
    # its corners about 1 px off (half its width times 1e-4), the others barely, once the similarity is fitted
    assert 0.8 < np.linalg.norm(errors[2], axis=1).max() < 1.1
    assert share > 0.99, share


def test_a_turned_frame_is_not_scale() -> None:
    truth = [_frame(k * 30_000.0) for k in range(5)]
    found = {k: truth[k] for k in range(5)}
    found[2] = _frame(60_000.0, angle=1e-4)
    errors, share = corner_errors(found, truth, SIZE)
    assert np.linalg.norm(errors[2], axis=1).max() > 0.8
    assert share < 0.05, share
