"""Levelling the adjusted plane: the root frame's tilt taken out of a strip's mosaic.

Frames are the synthetic strip's true homographies (``tests.strip_scenes``: random heading, scale and
zero-mean perspective per frame) with tie points drawn from the truth, so the only error left after the
adjustment is the plane's own: the root frame's tilt, which no tie point can see.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.strip_scenes import _strip_homographies
from workers.algorithms.geometry import fit_similarity
from workers.algorithms.mosaic import (
    TiePoints,
    apply_homography,
    chain_homographies,
    frame_corners,
    level_plane,
    refine_homographies,
    triple_overlap_share,
)

SIZE = (20_000, 800)  # a strip frame at a quarter of the camera's width
FRAMES = 10
ROOT = FRAMES // 2


def _strip(seed: int) -> tuple[list[np.ndarray], dict[tuple[int, int], TiePoints], dict[int, np.ndarray]]:
    """True frame -> ground homographies, tie points of consecutive frames (0.1 px noise, spread over the
    overlap) and the start the adjustment gets: the pairwise homographies chained from the root."""
    rng = np.random.default_rng(seed)
    truth = _strip_homographies(rng, FRAMES, SIZE, 0.55, 0.3, 0.005, 0.002)
    ties, pairwise = {}, {}
    for i in range(FRAMES - 1):
        to_j = np.linalg.inv(truth[i + 1]) @ truth[i]
        # frame i's top rows are frame i + 1's bottom rows
        points = np.column_stack([rng.uniform(0, SIZE[0] - 1, 400), rng.uniform(0, 0.45 * SIZE[1], 400)])
        seen = apply_homography(to_j, points) + rng.normal(0, 0.1, points.shape)
        ties[(i, i + 1)] = TiePoints(points, seen)
        pairwise[(i, i + 1)] = to_j
    parent = {k: k + 1 if k < ROOT else k - 1 for k in range(FRAMES) if k != ROOT}
    return truth, ties, chain_homographies(ROOT, parent, pairwise)


def corner_errors(homs: dict[int, np.ndarray], truth: list[np.ndarray], size: tuple[int, int] = SIZE) -> np.ndarray:
    """Every frame corner's distance (px) from the truth after the one similarity that fits them best."""
    found = np.concatenate([apply_homography(homs[k], frame_corners(*size)) for k in sorted(homs)])
    true = np.concatenate([apply_homography(truth[k], frame_corners(*size)) for k in sorted(homs)])
    return np.linalg.norm(apply_homography(fit_similarity(found, true), found) - true, axis=1)


def test_a_levelled_strip_keeps_its_shape() -> None:
    for seed in (0, 1, 2):
        truth, ties, start = _strip(seed)
        sizes = dict.fromkeys(start, SIZE)
        adjusted = refine_homographies(start, ties, ROOT, sizes, perspective_damping=0.0)
        tilted, levelled = corner_errors(adjusted, truth), corner_errors(level_plane(adjusted, sizes), truth)
        # the root frame's tilt fans the strip out (its corners tens of px off); levelled, it is the truth's
        assert tilted.max() > 5.0, (seed, tilted.max())
        assert levelled.max() < 1.0, (seed, levelled.max())


def test_levelling_is_a_plane_homography_and_idempotent() -> None:
    truth, ties, start = _strip(3)
    sizes = dict.fromkeys(start, SIZE)
    adjusted = refine_homographies(start, ties, ROOT, sizes, perspective_damping=0.0)
    levelled = level_plane(adjusted, sizes)
    # one homography G moves every frame: G = levelled_k adjusted_k^-1 is the same for all k
    moves = [levelled[k] @ np.linalg.inv(adjusted[k]) for k in sorted(adjusted)]
    for move in moves[1:]:
        np.testing.assert_allclose(move / move[2, 2], moves[0] / moves[0][2, 2], rtol=0, atol=1e-9)
    # the tie points meet as well as before, and levelling a level plane moves nothing
    for (i, j), t in ties.items():
        before = apply_homography(np.linalg.inv(adjusted[j]) @ adjusted[i], t.points_i)
        after = apply_homography(np.linalg.inv(levelled[j]) @ levelled[i], t.points_i)
        assert np.abs(after - before).max() < 1e-6
    again = level_plane(levelled, sizes)
    for k in levelled:
        np.testing.assert_allclose(again[k], levelled[k], rtol=1e-9, atol=1e-4)  # px, on a plane 20000 px wide
    # the plane point under the frames' mean centre stays put: the mosaic does not jump away from the root's
    centre = np.array([[(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]])
    mean = np.mean([apply_homography(adjusted[k], centre)[0] for k in adjusted], axis=0)
    assert np.linalg.norm(apply_homography(moves[0], mean[None]) - mean) < 1e-6


@pytest.mark.parametrize(("overlap", "share"), [(0.5, 0.0), (0.45, 0.0), (0.55, 1.0), (0.6, 1.0)])
def test_triple_overlap_share_tells_a_strip_that_cannot_carry_its_scale(overlap: float, share: float) -> None:
    """A strip of 75000 x 1800 frames (working copies at 1/8), each ``(1 - overlap) * height`` north of the
    last, turned by up to 0.3 degrees: above 50 % forward overlap every frame's neighbours share ground."""
    rng = np.random.default_rng(3)
    width, height = 9375, 225
    homographies = {}
    for k in range(12):
        turn = np.deg2rad(rng.uniform(-0.3, 0.3))
        rotate = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]])
        centre = _shift((width - 1) / 2, (height - 1) / 2)
        homographies[k] = _shift(0.0, -k * (1 - overlap) * height) @ centre @ rotate @ np.linalg.inv(centre)
    assert triple_overlap_share(homographies, dict.fromkeys(homographies, (width, height))) == share


def _shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
